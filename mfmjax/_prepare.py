"""Data preparation before identification: linear detrending and resampling onto a uniform grid.

Both are eager NumPy steps at the edge of the data layer (they look at the concrete samples and
return a new `Signals`); nothing here is traced or jitted, except `Trend.restore`, which is plain
arithmetic and works inside jit.

- `detrend(signals, kind)` removes a least-squares line (or the mean) from the output and from
  each input and returns the removed lines as a `Trend`, which removes the same lines from a
  validation record (`Trend.apply`) and puts the output's line back on a simulated output
  (`Trend.restore`). The lines are functions of absolute time `t`, so a window of the same
  record (`Signals.window` keeps `t0`) gets the line's values at its own times.
- `resample(t, y, u, dt=...)` puts a non-uniform record, or inputs logged on their own time
  grids, onto the uniform grid `t0 + k dt` that `Signals` needs, each input by its intersample
  rule (zoh: the last value held; foh: linear interpolation), the output by linear
  interpolation or a cubic spline.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import _boundary as _b
from ._pytree import replace_fields
from ._signals import DETRENDED, INTERSAMPLE, QUANTUM_SHARE, Signals, decimal_quantum

DETREND_KINDS = ("linear", "constant")
OUTPUT_RULES = ("linear", "cubic")
_GRID_RTOL = 1e-9  # a grid time within 1e-9 dt of a sample time counts as that sample time
_GAP = 10.0  # a step longer than this many median steps (and grid steps) is a logging gap
_COARSE = 1.5  # dt above this many median steps of a record: warn about aliasing
_FINE = 10.0  # dt below the output's median step / this: interpolated, or a unit slip


# -- detrending ---------------------------------------------------------------------------------


def _line(t: np.ndarray, x: np.ndarray, kind: str, t_ref: float) -> tuple[float, float]:
    """Least-squares (level at t_ref, slope) of samples x(t); slope 0 for kind 'constant'.

    The slope is computed about the mean time (centred: no cancellation for large t0)."""
    mean = float(np.mean(x))
    if kind == "constant":
        return mean, 0.0
    tc = t - np.mean(t)
    slope = float(tc @ (x - mean) / (tc @ tc))
    return mean + slope * (t_ref - float(np.mean(t))), slope


class Trend(eqx.Module):
    """The lines `detrend` removed: per signal, the level at time `t0` and the slope.

    The output's line is $\\ell_y(t) = $ `y_level` $+$ `y_slope` $(t - t_0)$, input k's is
    `u_level[k]` + `u_slope[k]` $(t - t_0)$ (slopes are 0 for kind `"constant"`). A model
    identified on the detrended record describes deviations from these lines: no offset term
    is needed (the operating point was removed with them), which is why `detrend` returns its
    record with `offset=False` unless told otherwise; `note` says so in words.

    - `apply(signals)`: the same lines removed from another record (validation data), evaluated
      at that record's own times.
    - `restore(t, y)`: the output's line added back to a simulated (detrended) output.
    - `output_line(t)`, `input_lines(t)`: the lines at times `t`.
    """

    y_level: jax.Array
    y_slope: jax.Array
    u_level: jax.Array  # (K,)
    u_slope: jax.Array  # (K,)
    kind: str = eqx.field(static=True)
    t0: float = eqx.field(static=True)
    output_name: str = eqx.field(static=True)
    input_names: tuple[str, ...] = eqx.field(static=True)
    note: str = eqx.field(static=True)

    @property
    def n_inputs(self) -> int:
        return self.u_level.shape[0]

    def _xp(self, t):
        """NumPy for concrete lines and times (no eager programs), else `jax.numpy`."""
        traced = any(_b.is_traced(x) for x in (t, self.y_level, self.y_slope, self.u_level,
                                                 self.u_slope))
        return (jnp, self) if traced else (np, jax.device_get(self))

    def output_line(self, t) -> jax.Array:
        """$\\ell_y(t)$ at times `t` (any shape)."""
        xp, line = self._xp(t)
        out = line.y_level + line.y_slope * (xp.asarray(t, dtype=xp.float64) - self.t0)
        return out if xp is jnp else jax.device_put(out)

    def input_lines(self, t) -> jax.Array:
        """The inputs' lines at times `t` (T,): shape (T, K)."""
        xp, line = self._xp(t)
        dt = xp.asarray(t, dtype=xp.float64)[:, None] - self.t0
        out = line.u_level[None, :] + line.u_slope[None, :] * dt
        return out if xp is jnp else jax.device_put(out)

    def apply(self, signals: Signals, *, offset: bool = False) -> Signals:
        """Remove these lines (fitted on another record) from `signals`, at its own times.

        **Arguments:** `signals`, a record with the same inputs; `offset` as in `detrend`.

        **Returns:** the detrended `Signals` (its time grid, rules, delays and names kept).
        """
        _check_concrete("Trend.apply", signals)
        offset = _offset("Trend.apply", offset)
        if signals.n_inputs != self.n_inputs:
            raise ValueError(
                f"Trend.apply(): the record has {signals.n_inputs} input(s) "
                f"{list(signals.input_names)} but the trend was fitted on {self.n_inputs} "
                f"{list(self.input_names)}; give a record with the same inputs"
            )
        from ._observers import swapped_inputs

        order = swapped_inputs(self.input_names, signals.input_names)
        if order:  # the lines of one input would be removed from another
            raise ValueError(f"Trend.apply(): {order}")
        names = (signals.output_name, tuple(signals.input_names))
        if names != (self.output_name, tuple(self.input_names)):
            warnings.warn(f"Trend.apply(): the trend was fitted on output "
                          f"{self.output_name!r}, inputs {list(self.input_names)}, and the record "
                          f"has output {signals.output_name!r}, inputs "
                          f"{list(signals.input_names)}: their lines are removed in that order; "
                          "check that the record holds the same signals", stacklevel=_b.user_stacklevel())
        t = np.asarray(signals.t)
        y = np.asarray(signals.y) - np.asarray(self.output_line(t))
        u = np.asarray(signals.u) - np.asarray(self.input_lines(t))
        return _detrended(signals, y, u, offset, self.note)

    def to_dict(self) -> dict:
        """The lines as plain numbers (JSON-ready; `Trend.from_dict` reads them back)."""
        line = jax.device_get(self)
        return {"kind": self.kind, "t0": self.t0, "y_level": float(line.y_level),
                "y_slope": float(line.y_slope),
                "u_level": [float(v) for v in np.asarray(line.u_level)],
                "u_slope": [float(v) for v in np.asarray(line.u_slope)],
                "output_name": self.output_name, "input_names": list(self.input_names),
                "note": self.note}

    @classmethod
    def from_dict(cls, d: dict) -> Trend:
        """A `Trend` from `to_dict`'s description (a ValueError naming what is wrong)."""
        keys = ("kind", "t0", "y_level", "y_slope", "u_level", "u_slope", "output_name",
                "input_names", "note")
        try:
            nums = [np.asarray(d[k], dtype=np.float64).reshape(-1) for k in keys[1:6]]
            K = nums[3].size
            ok = (set(d) == set(keys) and d["kind"] in DETREND_KINDS
                  and isinstance(d["input_names"], (list, tuple))
                  and all(np.all(np.isfinite(v)) for v in nums)
                  and [v.size for v in nums] == [1, 1, 1, K, K]
                  and len(d["input_names"]) == K)
        except (KeyError, TypeError, ValueError):
            ok = False
        if not ok:
            raise ValueError(f"Trend.from_dict(): expected the keys {list(keys)} with finite "
                             f"levels and slopes, one per input (got {d!r})")
        levels = (nums[1].reshape(()), nums[2].reshape(()), nums[3], nums[4])
        return cls(*jax.device_put(levels), kind=d["kind"], t0=float(nums[0][0]),
                   output_name=str(d["output_name"]),
                   input_names=tuple(str(n) for n in d["input_names"]), note=str(d["note"]))

    def restore(self, t, y) -> jax.Array:
        """A simulated output of the detrended model back in the record's units: y + $\\ell_y(t)$.

        **Arguments:** `t` the sample times (T,), `y` the output (..., T) (batch axes in front).
        """
        t = jnp.asarray(t, dtype=jnp.float64)
        y = jnp.asarray(y, dtype=jnp.float64)
        if t.ndim != 1 or y.ndim < 1 or y.shape[-1] != t.shape[0]:
            raise ValueError(f"Trend.restore(): y must have shape (..., T) with T = len(t) "
                             f"(got t {t.shape}, y {y.shape})")
        return y + self.output_line(t)


def _check_concrete(fn: str, signals) -> None:
    _b.require_x64(fn)  # the detrended record went through device_put: float32 without it
    if not isinstance(signals, Signals):
        raise TypeError(f"{fn}(): signals must be a Signals, got {type(signals).__name__}")
    _b.eager_only(fn, signals, fix="detrend the data before the transformation")


def _offset(fn: str, offset) -> bool:
    if not isinstance(offset, (bool, np.bool_)):
        raise TypeError(f"{fn}(): offset must be True or False, got {offset!r}")
    return bool(offset)


def _detrended(signals: Signals, y, u, offset: bool, note: str) -> Signals:
    return replace_fields(
        signals,
        y=jnp.asarray(y, dtype=jnp.float64),
        u=jnp.asarray(u, dtype=jnp.float64).reshape(signals.u.shape),
        offset=offset,
        offset_note="" if offset else note,
    )


def detrend(signals: Signals, kind: str = "linear", *, offset: bool = False
            ) -> tuple[Signals, Trend]:
    r"""Remove a least-squares line (or the mean) from the output and from each input.

    For each signal $x$ of the record (the output and every input), fits $x(t) \approx c +
    s\,(t - t_0)$ over the record by least squares (`kind="linear"`) or takes its mean
    (`kind="constant"`, $s = 0$), and subtracts it. The model identified on the result
    describes deviations from these lines, so it needs no offset term: the record comes back
    with `offset=False` (its `offset_note` says why) unless `offset=True` is given.

    **Arguments:**

    - `signals`: the record (`Signals`, concrete arrays).
    - `kind`: `"linear"` (default) or `"constant"`.
    - `offset`: the offset setting of the returned record (default False: the operating point
      was removed with the lines).

    **Returns:** `(Signals, Trend)`: the detrended record (time, rules, delays and names kept)
    and the removed lines; `Trend.apply` removes the same lines from validation data and
    `Trend.restore` adds the output's line back to a simulated output.
    """
    _check_concrete("detrend", signals)
    kind = _b.choice("detrend", "kind", kind, DETREND_KINDS)
    offset = _offset("detrend", offset)
    t = np.asarray(signals.t)
    y, u = np.asarray(signals.y), np.asarray(signals.u)
    t0 = signals.t0
    y_level, y_slope = _line(t, y, kind, t0)
    lines = [_line(t, u[:, k], kind, t0) for k in range(signals.n_inputs)]
    u_level = np.array([c for c, _ in lines], dtype=np.float64)
    u_slope = np.array([s for _, s in lines], dtype=np.float64)
    what = "least-squares line" if kind == "linear" else "mean"
    note = (f"no offset term {DETRENDED} the {what} of the output and of each input was "
            "removed, and the operating point with it)")
    levels = jax.device_put(tuple(np.asarray(v, dtype=np.float64)  # no eager programs
                                  for v in (y_level, y_slope, u_level, u_slope)))
    trend = Trend(
        *levels, kind=kind, t0=float(t0),
        output_name=signals.output_name, input_names=tuple(signals.input_names), note=note,
    )
    y_d = y - np.asarray(trend.output_line(t))
    u_d = u - np.asarray(trend.input_lines(t))
    for k, name in enumerate(signals.input_names):
        scale = max(float(np.max(np.abs(u[:, k]))), 1e-300)
        if np.max(np.abs(u_d[:, k])) <= 1e-12 * scale and np.ptp(u[:, k]) > 0:
            warnings.warn(
                f"detrend(): input {name!r} is a straight line over the record, so nothing of "
                "it is left after detrending (the model cannot see it); use kind='constant' "
                "or drop the input", stacklevel=_b.user_stacklevel())
    return _detrended(signals, y_d, u_d, offset, note), trend


# -- resampling ----------------------------------------------------------------------------------


def _time(fn: str, name: str, t) -> np.ndarray:
    t = _b.array(fn, name, t, ndim=1, fix="clean the time column first")
    if t.shape[0] < 2:
        raise ValueError(f"{fn}(): {name} has {t.shape[0]} sample(s); a record needs at least 2")
    steps = np.diff(t)
    if np.any(steps <= 0):
        row = int(np.argmax(steps <= 0)) + 1
        raise ValueError(f"{fn}(): {name} must be strictly increasing (row {row} is "
                         f"{t[row]:g} after {t[row - 1]:g}); sort the record or drop duplicate rows")
    return t


def _values(fn: str, name: str, v, n: int, tname: str) -> np.ndarray:
    v = _b.array(fn, name, v, ndim=1)
    if v.shape[0] != n:
        raise ValueError(f"{fn}(): length mismatch: {name} has {v.shape[0]} samples but "
                         f"{tname} has {n}; give one value per time")
    return v


def _grid_tol(dt: float, *times: np.ndarray) -> float:
    """How close a grid time must be to a sample time to count as it: 1e-9 dt, or 8 ulps of
    the largest time (epoch seconds near 1.7e9, logged at 10 Hz with 3 decimals, carry 2.4e-7 s
    of rounding: with 1e-9 dt alone a held input came out one sample early on 13 % of the
    grid, and the record's last sample was dropped), or half the decimal quantum q the
    sample times were written to, where q is at most `QUANTUM_SHARE` of dt and of their
    smallest step (30 Hz stamps written in ms are up to 0.5 ms late: a held input came out
    one sample late on a third to two thirds of the 1/30 grid)."""
    big = max(float(np.max(np.abs(x))) for x in times)
    tol = max(_GRID_RTOL * dt, 8 * float(np.spacing(big)))
    q = decimal_quantum(times[0])
    step = float(np.min(np.diff(times[0]))) if times[0].size > 1 else dt
    if q is not None and q <= QUANTUM_SHARE * min(dt, step):
        tol = max(tol, 0.5 * q * (1 + 1e-6))
    return tol


def _zoh(t_k: np.ndarray, v: np.ndarray, grid: np.ndarray, dt: float) -> np.ndarray:
    """The last sample at or before each grid time (a grid time within `_grid_tol` of a sample
    time counts as that time, so that grids built by t0 + k dt hit their samples exactly)."""
    j = np.searchsorted(t_k, grid + _grid_tol(dt, t_k, grid), side="right") - 1
    return v[np.clip(j, 0, t_k.shape[0] - 1)]


def _interp(t_k, v, grid, rule: str, dt: float) -> np.ndarray:
    if rule == "zoh":
        return _zoh(t_k, v, grid, dt)
    if rule == "cubic":
        from scipy.interpolate import CubicSpline

        if t_k.shape[0] < 4:
            return np.interp(grid, t_k, v)  # too few points for a spline: linear
        return CubicSpline(t_k, v)(grid)
    return np.interp(grid, t_k, v)  # foh / linear


def resample_arrays(fn: str, t, y, u, *, dt, intersample="foh", output_rule: str = "linear",
                    input_names: Sequence[str] | None = None, output_name: str = "y"):
    """The numerics of `resample` as arrays: (t0, y (T,), u (T, K), intersample, names);
    `output_name` names the output in warnings."""
    t = _time(fn, "t", t)
    y = _values(fn, "y", y, t.shape[0], "t")
    dt = _b.number(fn, "dt", dt, lo=0, lo_open=True,
                   fix="give the step of the uniform grid in the record's time unit")
    output_rule = _b.choice(fn, "output_rule", output_rule, OUTPUT_RULES)
    series = []  # (name, t_k, values)
    if u is None:
        pass
    elif isinstance(u, Mapping):
        for name, pair in u.items():
            if not isinstance(pair, (tuple, list)) or len(pair) != 2:
                raise TypeError(f"{fn}(): u[{name!r}] must be a pair (t_k, values_k), got "
                                f"{type(pair).__name__}")
            t_k = _time(fn, f"u[{name!r}] time", pair[0])
            series.append((str(name), t_k, _values(fn, f"u[{name!r}]", pair[1], t_k.shape[0],
                                                   f"u[{name!r}] time")))
        if input_names is not None and list(input_names) != [s[0] for s in series]:
            raise ValueError(f"{fn}(): u is a dict, so the inputs are named by its keys "
                             f"{[s[0] for s in series]}; drop input_names={list(input_names)}")
    else:
        ua = _b.array(fn, "u", u, ndim=(1, 2))
        ua = ua[:, None] if ua.ndim == 1 else ua
        if ua.shape[0] != t.shape[0]:
            raise ValueError(f"{fn}(): length mismatch: u has {ua.shape[0]} samples but t has "
                             f"{t.shape[0]}; for inputs on their own time grids give u as a "
                             "dict name -> (t_k, values_k)")
        names = (list(input_names) if input_names is not None
                 else [f"u{k + 1}" for k in range(ua.shape[1])])
        if len(names) != ua.shape[1]:
            raise ValueError(f"{fn}(): input_names needs {ua.shape[1]} names, got {len(names)}")
        series = [(str(names[k]), t, ua[:, k]) for k in range(ua.shape[1])]
    K = len(series)
    if isinstance(intersample, str) or intersample is None:
        rules = [intersample or "foh"] * K
    else:
        rules = list(intersample)
        if len(rules) != K:
            raise ValueError(f"{fn}(): intersample needs one entry per input ({K}), got "
                             f"{len(rules)}")
    for k, rule in enumerate(rules):
        if rule not in INTERSAMPLE:
            raise ValueError(f"{fn}(): unknown intersample rule {rule!r} for input "
                             f"{series[k][0]!r}; use one of {INTERSAMPLE}")
    start = max([t[0]] + [s[1][0] for s in series])
    end = min([t[-1]] + [s[1][-1] for s in series])
    if not end > start:
        raise ValueError(f"{fn}(): the output and the inputs share no time span (output "
                         f"{t[0]:g}..{t[-1]:g}; latest start {start:g}, earliest end {end:g})")
    # more than a step of the grid and of the column's own clock (an input logged at 1 Hz
    # under a 0.1 s grid ends up to 1 s before the output without anything cut off)
    cut = []
    for name, t_k in [(output_name, t)] + [(s[0], s[1]) for s in series]:
        lag = max(dt, float(np.median(np.diff(t_k)))) if t_k.size > 1 else dt
        if t_k[0] > t[0] + lag or t_k[-1] < t[-1] - lag:
            cut.append(f"{name!r} {t_k[0]:g}..{t_k[-1]:g}")
    if cut:  # a column reported only on change (a historian's) ends at its last change
        warnings.warn(f"{fn}(): the record is cut to {start:g}..{end:g}, the span every "
                      f"column covers (output {t[0]:g}..{t[-1]:g}; {', '.join(cut)}); a "
                      "column stored only when it changes holds its last value: fill it "
                      "forward to the record's end first if that is what it means",
                      stacklevel=_b.user_stacklevel())
    steps = int(np.floor((end - start + _grid_tol(dt, t)) / dt))
    if steps < 1:
        raise ValueError(f"{fn}(): dt={dt:g} is coarser than the record ({start:g}..{end:g}, "
                         f"{end - start:g} long); a uniform grid needs at least 2 samples: "
                         "choose a smaller dt")
    for name, t_k in [(output_name, t)] + [(s[0], s[1]) for s in series]:
        median = float(np.median(np.diff(t_k)))
        if dt > _COARSE * median:
            warnings.warn(
                f"{fn}(): dt={dt:g} is coarser than the median step of {name!r} ({median:g}); its "
                "faster content aliases without a low-pass filter: filter first or choose a "
                "smaller dt", stacklevel=_b.user_stacklevel())
            break
    median = float(np.median(np.diff(t)))
    if dt * _FINE < median:  # 199,003 samples from 200 rows logged in ms with dt in s
        warnings.warn(
            f"{fn}(): dt={dt:g} is {median / dt:.3g}x finer than the output's median step "
            f"({median:g}): all but one in {median / dt:.3g} samples are interpolated, not "
            "measured; is the time column in another unit than dt (ms against s)? Give dt in "
            "the time column's unit", stacklevel=_b.user_stacklevel())
    for name, t_k in [(output_name, t)] + [(s[0], s[1]) for s in series]:
        gaps = np.diff(t_k)
        big = int(np.argmax(gaps))
        if gaps[big] > _GAP * max(float(np.median(gaps)), dt):
            warnings.warn(
                f"{fn}(): {name!r} has a gap from {t_k[big]:g} to {t_k[big + 1]:g} "
                f"({gaps[big]:g}, {gaps[big] / np.median(gaps):.3g} of its median steps): it is "
                "interpolated across, which no plant did; split the record there and join the "
                "parts with Signals.concatenate (command line: --identify-window on one side "
                "of it)", stacklevel=_b.user_stacklevel())
    grid = start + dt * np.arange(steps + 1, dtype=np.float64)
    y_new = _interp(t, y, grid, "cubic" if output_rule == "cubic" else "foh", dt)
    u_new = np.zeros((grid.shape[0], K), dtype=np.float64)
    for k, (_, t_k, v) in enumerate(series):
        u_new[:, k] = _interp(t_k, v, grid, rules[k], dt)
    return float(start), y_new, u_new, tuple(rules), tuple(s[0] for s in series)


def resample(t, y, u=None, *, dt, intersample="foh", output_rule: str = "linear",
             **kwargs) -> Signals:
    r"""A non-uniform or mismatched record on the uniform grid $t_0 + k\,dt$, as `Signals`.

    The grid starts at the first time all signals share (`t[0]` when they start together) and
    ends at or before the last one they share. Inputs are read by their intersample rule:
    `"zoh"` holds the last sample (the value a digital controller applied), `"foh"` interpolates
    linearly; both reproduce the samples exactly where the grid meets a sample time. The output
    is interpolated linearly (`output_rule="linear"`, exact for piecewise-linear signals) or by a
    not-a-knot cubic spline (`"cubic"`, scipy). A grid coarser than a record's median step
    warns (no anti-alias filter is applied).

    **Arguments:**

    - `t`: the output's sample times (T,), strictly increasing; `y`: the output (T,).
    - `u`: inputs on the same times, (T,) or (T, K); or a dict `name -> (t_k, values_k)` for
      inputs logged on their own time grids (each resampled by its own rule); or None.
    - `dt`: the grid step (> 0, shorter than the record).
    - `intersample`: per input `"zoh"` or `"foh"` (one string for all), also stored in the
      returned `Signals`.
    - `output_rule`: `"linear"` (default) or `"cubic"`: how the output is interpolated (the
      quadrature rule of the returned `Signals` stays its default).
    - `**kwargs`: passed to `Signals` (`delays`, `offset`, `smooth`, `output_name`,
      `input_names`; with a dict `u` the keys name the inputs).

    **Returns:** `Signals` on the uniform grid.
    """
    for bad in ("t0", "t"):
        if bad in kwargs:
            raise TypeError(f"resample(): {bad}= is not an option (the grid starts at the first "
                            "shared time of the record)")
    _b.eager_only("resample", t, y, u, dt)
    names = kwargs.pop("input_names", None)
    t0, y_new, u_new, rules, names = resample_arrays(
        "resample", t, y, u, dt=dt, intersample=intersample, output_rule=output_rule,
        input_names=names, output_name=str(kwargs.get("output_name", "y")))
    return Signals(y_new, u_new, dt=float(dt), t0=t0, intersample=rules, input_names=names,
                   **kwargs)
