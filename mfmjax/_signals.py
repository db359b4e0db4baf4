"""One experiment's sampled data: output y, K inputs, time grid, intersample behaviour, delays.

Conventions (written once): arrays are time-major, `y` has shape (T,), `u` has shape (T, K);
batch axes go in front. Sample k is at time `t0 + k * dt`.
"""

from __future__ import annotations

import csv
import math
import re
import warnings
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import _boundary as _b
from ._pytree import replace_fields

INTERSAMPLE = ("zoh", "foh")
_UNIFORM_RTOL = 1e-6  # allowed relative jitter of the time column against its mean step


def decimal_quantum(t: np.ndarray) -> float | None:
    """The power of ten the time stamps were written to (0.001 for 0.033, 0.067, 0.1, ...):
    the largest 10^-d, d = 0..12, of which every stamp is a multiple to float64 rounding;
    None when there is none (stamps computed, not printed)."""
    t = np.asarray(t, dtype=np.float64)
    big = float(np.max(np.abs(t))) if t.size else 0.0
    for d in range(13):
        s = t * 10.0**d
        if np.max(np.abs(s - np.round(s)), initial=0.0) <= max(1e-6, 16 * _EPS * big * 10.0**d):
            return 10.0**-d
    return None


_EPS = float(np.finfo(np.float64).eps)
# a uniform grid whose stamps were rounded to a quantum q (a logger writing milliseconds at
# 30 Hz) is uniform when q is at most this share of the step: a missing sample moves a stamp
# by a whole step from the line, far beyond the q that rounding can
QUANTUM_SHARE = 0.1


def _concrete(x) -> bool:
    return not isinstance(x, jax.core.Tracer)


def _same_step(a, b) -> float:
    """How far the steps of two records may differ and be one: 1e-9 of it, or the rounding
    of their time stamps over their lengths (epoch seconds near 1.7e9 carry 2.4e-7 s: records
    of 300 and 101 samples at 0.1 s read dt 0.10000000031895462 and 0.1)."""
    def rounding(r):
        end = abs(float(r.t0)) + r.n_samples * float(r.dt)
        return 4 * _EPS * end / max(r.n_samples - 1, 1)
    return 1e-9 * float(a.dt) + rounding(a) + rounding(b)


def _rounded_grid(t: np.ndarray, dt: float, rounding: float) -> float | None:
    """The step of a uniform grid whose stamps `t` were written to a decimal quantum
    q <= `QUANTUM_SHARE` dt: some line a + b k holds every stamp within q/2, i.e. the
    narrowest strip around the stamps (a convex function of its slope, minimised by golden
    section) is at most q wide (q itself: a grid half a quantum off the written digits, 80 Hz
    in ms, rounds its ties both ways). Returns the
    least-squares slope (3.3e-6 relative error from the end points at 30 Hz in ms over 3000
    samples, 4.4e-9 from the fit); None for any other stamps."""
    q = decimal_quantum(t)
    if q is None or q > QUANTUM_SHARE * dt:
        return None
    k = np.arange(t.size, dtype=np.float64)
    kc = k - k.mean()
    x = t - t[0]
    slope = float(kc @ x / (kc @ kc))
    r = x - slope * k  # residuals about the least-squares slope (and any intercept)
    # a line within q/2 of every stamp differs from the least-squares one by at most
    # q/2 + max|r - mean r| anywhere, so its slope by twice that over the record
    bound = 2 * (q + 2 * float(np.max(np.abs(r - r.mean())))) / (t.size - 1)
    lo, hi = -bound, bound
    g = (math.sqrt(5) - 1) / 2
    s1, s2 = hi - g * (hi - lo), lo + g * (hi - lo)
    f1, f2 = np.ptp(r - s1 * k), np.ptp(r - s2 * k)
    for _ in range(80):  # the bracket shrinks 0.618^80 = 2e-17 times
        if f1 <= f2:
            hi, s2, f2 = s2, s1, f1
            s1 = hi - g * (hi - lo)
            f1 = np.ptp(r - s1 * k)
        else:
            lo, s1, f1 = s1, s2, f2
            s2 = lo + g * (hi - lo)
            f2 = np.ptp(r - s2 * k)
    width = float(min(f1, f2))
    # (a width of q itself: ties rounded both ways. Stamps cannot tell a one-quantum slip
    # from rounding: 300 stamps of 10 s in whole seconds with the last 150 one second late
    # are the grid of step 10.0033 rounded, and a rule refusing them refused 99.99 Hz in ms)
    return slope if width <= q * (1 + 1e-6) + 2 * rounding else None


def _per_input(value, K: int, name: str, default, cast):
    if value is None:
        return tuple(default for _ in range(K))
    if isinstance(value, (str, bool, int, float)) and not isinstance(value, (list, tuple)):
        return tuple(cast(value) for _ in range(K))
    value = tuple(value)
    if len(value) != K:
        raise ValueError(f"Signals(): {name} needs one entry per input ({K}), got {len(value)}")
    return tuple(cast(v) for v in value)


DEGENERATE_CORR = 1.0 - 1e-12  # |corr(y, u_k)| above this: u_k is the output up to scale


DEPENDENT_RTOL = 1e-6  # smallest / largest singular value of the unit input columns below it
NEARLY_RTOL = 0.05  # below it (a correlation above 0.995 for two inputs): nearly collinear


def dependent_inputs(signals, delays=None) -> tuple[str, ...]:
    """Names of inputs that are linearly dependent (u2 = 2 u1, one signal logged twice): no
    method can split the gain among them, and the Gram's conditioning test misses it under
    output noise (noise fills the eigenvalue it reads). Checked among inputs of equal delay
    and intersample rule (only those are the same continuous signal up to a factor), their
    columns centred when the offset term is on (u2 = 2 u1 + c), constant inputs left to
    `NO_EXCITATION`; dependent when the smallest singular value of the unit-norm columns is
    below `DEPENDENT_RTOL` of the largest (from their K x K Gram, whose eigenvalues resolve
    ratios down to 1e-12, the square of that). `delays` (K,) replaces the signals' own (a
    search candidate's). Empty for traced data or traced delays."""
    delays = signals.delays if delays is None else delays
    gram = _input_gram(signals)
    if gram is None or not _concrete(delays):
        return ()
    return _dependent(signals, gram, delays)


def dependent_candidates(signals, delays) -> tuple[np.ndarray, tuple[str, ...]]:
    """For search candidates with input delays `delays` (C, K): which of them have linearly
    dependent inputs (`dependent_inputs` under their delays), and the inputs' names."""
    delays = np.asarray(delays, dtype=np.float64).reshape(len(delays), -1)
    gram = _input_gram(signals)
    if gram is None or not len(delays):
        return np.zeros(len(delays), bool), ()
    if np.all(delays == delays[0]):  # no delay grid (np.unique on rows costs 0.1 ms)
        rows, inverse = delays[:1], np.zeros(len(delays), int)
    else:
        rows, inverse = np.unique(delays, axis=0, return_inverse=True)
    found = [_dependent(signals, gram, row) for row in rows]
    names = tuple(k for k in signals.input_names if any(k in f for f in found))
    return np.asarray([bool(f) for f in found])[inverse.reshape(-1)], names


def _input_gram(signals, centre: bool = False):
    """The inputs' K x K Gram (centred with the offset term, or `centre`) and column norms;
    None for traced data or fewer than two inputs."""
    u = signals.u
    if not _concrete(u) or u.ndim != 2 or u.shape[-1] < 2:
        return None
    u = np.asarray(u, dtype=np.float64)
    if signals.offset or centre:
        u = u - np.mean(u, axis=0)
    C = u.T @ u
    return C, np.sqrt(np.diagonal(C))


def nearly_dependent_inputs(signals, delays=None) -> tuple[tuple[str, ...], float]:
    """(names, ratio): inputs whose unit columns' smallest singular value is below
    `NEARLY_RTOL` of the largest (the least ratio found), as `dependent_inputs` judges them:
    two inputs 1 % apart gave gains of 6.4 and -3.5 for 2 and 1, status ok, nothing said."""
    delays = signals.delays if delays is None else delays
    gram = _input_gram(signals, centre=True)  # (a level both share is no dependence: it
    # flagged independent +-1 inputs about 20 without the offset term)
    if gram is None or not _concrete(delays):
        return (), 1.0
    return _dependent(signals, gram, delays, NEARLY_RTOL, ratio=True)


def _dependent(signals, gram, delays, rtol: float = DEPENDENT_RTOL, ratio: bool = False):
    """`dependent_inputs` from the inputs' Gram under `delays` (with `ratio`: and the least
    singular value ratio of the groups found)."""
    C, norms = gram
    delays = np.asarray(delays, dtype=np.float64).reshape(-1)
    groups: dict = {}
    for k, rule in enumerate(signals.intersample):
        if norms[k] > 0:
            groups.setdefault((float(delays[k]), rule), []).append(k)
    out, least = [], 1.0
    for ks in groups.values():
        if len(ks) < 2:
            continue
        w, v = np.linalg.eigh(C[np.ix_(ks, ks)] / np.outer(norms[ks], norms[ks]))
        if w[0] <= rtol**2 * w[-1]:
            out += [signals.input_names[k] for k, c in zip(ks, v[:, 0]) if abs(c) > 1e-3]
            least = min(least, float(np.sqrt(max(w[0], 0.0) / w[-1])))
    return (tuple(out), least) if ratio else tuple(out)


def _refuse_output_as_input(y, u, output_name, names):
    """An input that is the output itself (up to an affine map: |corr| > 1 - 1e-12) makes every
    model degenerate (y = u explains the data with any denominator): refuse it."""
    yc = y - y.mean()
    ny = np.linalg.norm(yc)
    if ny == 0 or y.shape[0] < 3:  # any two 2-sample columns are perfectly correlated
        return
    for k in range(u.shape[1]):
        uc = u[:, k] - u[:, k].mean()
        nu = np.linalg.norm(uc)
        if nu > 0 and abs(float(yc @ uc)) / (ny * nu) > DEGENERATE_CORR:
            raise ValueError(
                f"Signals(): input {names[k]!r} is the output {output_name!r} itself (up to "
                "scale and offset): every model would be degenerate; remove it from the inputs"
            )


INPUT_SPREAD = 0.05  # an input turns the offset term on only if std > 5 % of |mean|


def offset_needed(y, u=None, names=()) -> tuple[bool, str]:
    """The default offset rule: (include the constant input?, the reason in words). On when

    - the output sits at an operating point away from zero: |mean y| > 2 std y, unless the
      record starts at rest at zero (the mean of its first samples, up to 10, within 10 % of
      the output's range of zero: a step or impulse response). A step test from an ambient
      level (20 degC rising to 110) is not at rest at zero: on (the start used to be compared
      with half the range, so a_0 and the gain came out wrong with status ok);
    - or an input `u` (T, K) sits at an operating point by the same test (its start: the
      least |u| among its first samples) and varies about it (std > `INPUT_SPREAD` |mean|):
      a deviation output with an absolute input (a valve at 40-50 %, a PRBS around 5) needs
      a constant to cancel b_k0 u_k at rest. An input that barely moves about its level (a
      measured step applied at t = 0, 1 % noise) is nearly the constant column itself: the
      split between its gain and the offset would be decided by its noise (b = 0 and offset
      6 for a gain of 6, status ok);
    - or the output's start (`output_start`: its first samples' line at the first sample) is
      away from zero (beyond 10 % of its range) while every input varies and its first
      sample is at zero (a free response, u = 0, stays off): the output at zero input is not
      zero (a heater PRBS
      0-100 % starting off, and a temperature from an ambient 20 degC: a and b 3-60 % off
      with status ok without the term). A record that starts from x0 != 0 and is then
      excited gets an offset it does not need, estimated near zero.

    Off otherwise. Where the output starts away from zero with an input away from zero there
    and every input varies (`offset_undecided`), the data do not say whether the output at
    zero input is zero: the same heater starting on (100 % at the first sample) needs the
    term, a plant started from x0 != 0 does not. The term stays off and the note says so;
    `estimate` fits both and keeps the term where it predicts the held-back data better
    (pass offset=True to `identify` or `search` when the output has a level of its own).

    A traced y or u (inside jit/vmap) cannot be inspected: the term is left off; pass
    offset=True."""
    if not _concrete(y) or (u is not None and not _concrete(u)):
        return False, "offset term off (traced data: pass offset=True to estimate one)"
    y = np.asarray(y)
    on, why = _at_operating_point(y)
    if on:
        return True, (f"offset term estimated (auto: the output {why})")
    cols = [] if u is None else np.asarray(u).reshape(np.shape(u)[0], -1).T
    names = names or [f"u{k + 1}" for k in range(len(cols))]
    starts = [float(np.min(np.abs(col[:10]))) for col in cols]
    for name, col, start in zip(names, cols, starts):
        on, level = _at_operating_point(col, start=start)
        if on and np.std(col) > INPUT_SPREAD * abs(np.mean(col)):
            return True, (f"offset term estimated (auto: input {name!r} {level}, while the "
                          "output is near or at rest at zero: a deviation output with an "
                          "absolute input)")
    # the output's start with the inputs at zero there (`output_start`)
    y_span, y_start = float(np.ptp(y)), output_start(y)
    if len(cols) and abs(y_start) > 0.1 * y_span and \
            all(0 < np.ptp(col) and abs(float(col[0])) <= 0.1 * np.ptp(col) for col in cols):
        return True, (f"offset term estimated (auto: the output starts at {y_start:.4g}, "
                      f"against a range of {y_span:.4g}, while every input starts at zero: "
                      "the output at zero input is not zero)")
    if _undecided(y, cols):
        return False, (f"no offset term (auto: the output {why}; it starts at "
                       f"{y_start:.4g}, against a range of {y_span:.4g}, with an "
                       "input away from zero there, so the data do not say whether the output "
                       "at zero input is zero: pass offset=True if it is not (an ambient "
                       "level); `estimate` decides on held-back data)")
    return False, f"no offset term (auto: the output {why})"


def output_start(y) -> float:
    """The output at its first sample, read from its first samples (up to 10): the value there
    of their least-squares line. y[0] alone put the offset term on 9 of 100 records of a 10 dB
    Monte Carlo whose output starts at zero; their mean put it on first-order responses that
    rise within those samples."""
    return start_and_error(y)[0]


def start_and_error(y) -> tuple[float, float]:
    """(`output_start`, its standard error from the line's residuals; 0 for 2 samples)."""
    head = np.asarray(y[: min(10, y.shape[0])], dtype=np.float64)
    L, t = head.shape[0], np.arange(head.shape[0])
    line = np.polyfit(t, head, 1)
    resid = head - np.polyval(line, t)
    se = np.sqrt(np.sum(resid**2) / max(L - 2, 1) * 2 * (2 * L - 1) / (L * (L + 1)))
    return float(line[1]), float(se)


UNDECIDED_START = 0.05  # the output's start beyond 5 % of its 2-98 % spread: undecided


def _undecided(y, cols) -> bool:
    """The output's start (`output_start`) is away from zero: beyond 10 % of its full range,
    or beyond both `UNDECIDED_START` of the spread of its 2nd to 98th percentile and 3
    standard errors of the start (from the line's residuals). A wrongly undecided record costs
    `estimate` a second pass (the 5 % alone made 23-24 of 100 records of a 10 dB Monte Carlo
    undecided), while the 10 % alone, which noise widens, left a heater that needs the term
    off, unchecked, in 12 of 40 records at 10 % noise (10 of 40 now). And every input varies
    about its level (std > `INPUT_SPREAD` |mean|: the constant column is not nearly one of
    them, so the term is identifiable). Where `offset_needed` left the term off, an input is
    then away from zero at the first sample: a heater on from the start above an ambient
    level (the term needed) and a plant started from x0 != 0 (not needed) look alike there."""
    spread = float(np.subtract(*np.percentile(y, [98, 2])))  # noise widens the full range
    start, se = start_and_error(y)
    away = min(0.1 * float(np.ptp(y)), max(UNDECIDED_START * spread, 3 * se))
    return bool(len(cols)) and abs(start) > away \
        and all(0 < np.ptp(col) and np.std(col) > INPUT_SPREAD * abs(np.mean(col))
                for col in cols)


DETRENDED = "(detrended:"  # in the offset note of a record `detrend` returned: a decision


def offset_undecided(signals) -> bool:
    """The default rule (`offset_needed`) left `signals`' offset term off where the data cannot
    tell whether it is needed (`_undecided`): `estimate` then fits both and keeps the term
    only where it predicts the held-back data better. False when the user chose the term, or
    `detrend` did (its record describes deviations from the removed lines)."""
    if signals.offset or not signals.offset_note or DETRENDED in signals.offset_note or \
            not _concrete(signals.y) or not _concrete(signals.u):
        return False
    cols = np.asarray(signals.u).reshape(signals.n_samples, -1).T
    return _undecided(np.asarray(signals.y), cols)


def _at_operating_point(x, start: float | None = None) -> tuple[bool, str]:
    """(does the signal sit at an operating point away from zero?, why in words): |mean| >
    2 std and not starting at rest at zero: `start` (default the mean of the first samples,
    up to 10; an input's is the least |u| among them, so a step at the first samples, u[0] =
    0 then 1, starts at rest) within 10 % of its range of zero."""
    mean, std, span = float(np.mean(x)), float(np.std(x)), float(np.ptp(x))
    if start is None:
        start = float(np.mean(x[: min(10, x.shape[0])]))
    if abs(mean) <= 2 * std:
        return False, "has its mean within 2 standard deviations of zero"
    if abs(start) <= 0.1 * span:
        return False, (f"starts at rest at zero, at {start:.4g} against a range of {span:.4g}: "
                       "a step or impulse response")
    if std == 0:  # a constant away from zero (1.16e+303 standard deviations, it said)
        return True, f"is constant at {mean:.4g}"
    return True, f"sits at {mean:.4g}, {abs(mean) / std:.3g} standard deviations from zero"


class Signals(eqx.Module):
    """Validated container for one experiment (uniform sampling, MISO).

    **Arguments:**

    - `y`: output samples, shape (T,).
    - `u`: input samples, shape (T, K) (or (T,) for K = 1, or None for K = 0).
    - `dt`: sampling interval, or give `t` (a uniform, increasing time column) instead. Kept
      as a float64 value (a NumPy scalar, which behaves as a float), not a compile-time
      constant: a record at a new dt compiles nothing new.
    - `t0`: time of the first sample (ignored when `t` is given).
    - `intersample`: per input, `"zoh"` (piecewise constant, e.g. a digital controller's
      output) or `"foh"` (piecewise linear). Default `"foh"`.
    - `delays`: per input transport delay in time units (>= 0, any real value).
    - `offset`: add a constant input (u = 1, m = 0) to the model, for signals with an offset.
      Default `None` decides from the data (`offset_needed`): on for plant data around an
      operating point away from zero (the output's mean is more than 2 standard deviations
      from zero and the record does not start at rest at zero, i.e. its first samples are
      farther from zero than 10 % of its range), off for records from rest or
      around zero; `offset_note` says what was decided and why. Give True/False to choose.
    - `smooth`: per input, use the higher-order (cubic) rule as for the output.
    - `output_rule`: quadrature rule of the output, `"cubic"` (default, O(dt^4)) or `"foh"`
      (piecewise linear, for comparison).
    - `output_name`, `input_names`: labels for tables and files.
    """

    y: jax.Array
    u: jax.Array
    delays: jax.Array
    dt: np.float64  # a value (NumPy float64 on the host, traced in programs): no program per dt
    # the same dt as a host number, for host decisions (kernel and window lengths) when `dt` is
    # traced: records stacked for `jax.vmap` (stacking needs equal static fields, so equal dt);
    # None in `unlabelled` copies, which programs take
    dt_host: float | None = eqx.field(static=True)
    t0: float = eqx.field(static=True)
    intersample: tuple[str, ...] = eqx.field(static=True)
    smooth: tuple[bool, ...] = eqx.field(static=True)
    offset: bool = eqx.field(static=True)
    output_rule: str = eqx.field(static=True)
    output_name: str = eqx.field(static=True)
    input_names: tuple[str, ...] = eqx.field(static=True)
    offset_note: str = eqx.field(static=True)  # how the offset term was chosen ('' if given)

    def __init__(
        self,
        y,
        u=None,
        *,
        dt: float | None = None,
        t=None,
        t0: float = 0.0,
        intersample=None,
        delays=None,
        offset: bool | None = None,
        smooth=None,
        output_rule: str = "cubic",
        output_name: str = "y",
        input_names: Sequence[str] | None = None,
    ):
        _b.require_x64("Signals")
        y = jnp.asarray(_b.array("Signals", "y", y, finite=False), dtype=jnp.float64)
        if y.ndim != 1:
            raise ValueError(f"Signals(): y must be 1-D (T,), got shape {y.shape}")
        T = y.shape[0]
        if T < 2:
            raise ValueError(f"Signals(): y has {T} sample(s); a record needs at least 2")
        if u is None:
            u = np.zeros((T, 0))
        u = _b.array("Signals", "u", u, finite=False)
        if u.ndim == 1:  # on the host where concrete: no eager program per shape
            u = u[:, None]
        u = jnp.asarray(u, dtype=jnp.float64)
        if u.ndim != 2:
            raise ValueError(f"Signals(): u must have shape (T, K), got {u.shape}")
        if u.shape[0] != T:
            raise ValueError(
                f"Signals(): length mismatch: y has {T} samples but u has {u.shape[0]}; "
                "pass columns of equal length"
            )
        K = u.shape[1]
        if t is not None:
            if dt is not None:
                raise ValueError("Signals(): give either t (a time column) or dt, not both")
            if t0 != 0.0:  # it was ignored: t[0] is the start
                raise ValueError("Signals(): give either t (a time column, whose first value "
                                 "is the start) or t0, not both")
            narrow = np.dtype(getattr(t, "dtype", np.float64))
            t = _b.array("Signals", "t", t, finite=False)
            if t.shape != (T,):
                raise ValueError(
                    f"Signals(): length mismatch: time has {t.shape[0] if t.ndim else 0} "
                    f"samples but y has {T}"
                )
            if not np.all(np.isfinite(t)):
                raise ValueError(
                    f"Signals(): the time column has a NaN or inf at row "
                    f"{int(np.argmin(np.isfinite(t)))} (0-based); drop that row (from_csv: "
                    "resample=DT or --resample DT drops rows whose time is blank or NaN)")
            steps = np.diff(t)
            if T < 2 or np.any(steps <= 0):
                bad = int(np.argmax(steps <= 0)) + 1 if T >= 2 else 0
                raise ValueError(
                    f"Signals(): time must be strictly increasing (row {bad} is not); "
                    + (f"the time column is {narrow.name}, whose precision at "
                       f"{float(np.max(np.abs(t))):.3g} is "
                       f"{float(np.spacing(np.max(np.abs(t)).astype(narrow))):.3g}: give it "
                       "as float64 (or as times since the start)"
                       if narrow.kind == "f" and narrow.itemsize < 8 else
                       "sort the record or drop duplicate rows")
                )
            dt = float((t[-1] - t[0]) / (T - 1))
            # jitter beyond the time stamps' own rounding (epoch seconds near 1.7e9 carry
            # 2.4e-7 s of it, above 1e-6 of a 0.1 s step)
            rounding = 4 * _EPS * float(np.max(np.abs(t)))
            grid = None
            if np.max(np.abs(steps - dt)) > max(_UNIFORM_RTOL * dt, rounding):
                grid = _rounded_grid(t, dt, rounding)
                dt = grid if grid is not None else dt
            if grid is None and np.max(np.abs(steps - dt)) > max(_UNIFORM_RTOL * dt, rounding):
                bad = int(np.argmax(np.abs(steps - dt))) + 1
                raise ValueError(
                    f"Signals(): time is not uniformly sampled (step at row {bad} is "
                    f"{steps[bad - 1]:.10g}, mean step {dt:.10g}); resample to a uniform grid"
                )
            t0 = float(t[0])
        if dt is None:
            raise ValueError("Signals(): give the sampling interval dt or a time column t")
        dt = _b.number("Signals", "dt", dt, lo=0, lo_open=True,
                       fix="give the sampling interval in the record's time unit")
        t0 = _b.number("Signals", "t0", t0, fix="give the time of the first sample")
        intersample = _per_input(intersample, K, "intersample", "foh", str)
        for k, mode in enumerate(intersample):
            if mode not in INTERSAMPLE:
                raise ValueError(
                    f"Signals(): unknown intersample mode {mode!r} for input {k + 1}; "
                    f"use one of {INTERSAMPLE}"
                )
        smooth = _per_input(smooth, K, "smooth", False, bool)
        if output_rule not in ("cubic", "foh"):
            raise ValueError(
                f"Signals(): unknown output_rule {output_rule!r}; use 'cubic' or 'foh'"
            )
        if delays is None:
            delays = np.zeros(K)
        delays = _b.array("Signals", "delays", delays, finite=False)
        delays = jnp.atleast_1d(jnp.asarray(delays, dtype=jnp.float64)) if _b.is_traced(delays) \
            else jax.device_put(np.atleast_1d(np.asarray(delays, dtype=np.float64)))
        if delays.shape != (K,):
            raise ValueError(
                f"Signals(): delays needs one entry per input ({K}), got shape {delays.shape}"
            )
        if _concrete(delays):
            dv = np.asarray(delays)
            if not np.all(np.isfinite(dv)) or np.any(dv < 0):
                raise ValueError(f"Signals(): delays must be finite and >= 0 (got {dv.tolist()})")
            if np.any(dv >= (T - 1) * dt):
                raise ValueError(
                    f"Signals(): a delay ({dv.max():g}) is not shorter than the record "
                    f"({(T - 1) * dt:g}); check the time unit of delays"
                )
        names = tuple(str(v) for v in input_names) if input_names is not None else tuple(
            f"u{k + 1}" for k in range(K)
        )  # (as strings: a model labelled with the integers 1, 2 was refused by `labelled`)
        if len(names) != K:
            raise ValueError(f"Signals(): input_names needs {K} names, got {len(names)}")
        twice = sorted({str(v) for v in names if list(map(str, names)).count(str(v)) > 1})
        if twice:  # (estimate raised a LinAlgError from inside its stages)
            raise ValueError(f"Signals(): input_names has {twice} more than once; name each "
                             "input once (one column given twice as an input is one input)")
        host_y = [(output_name, np.asarray(y))] if _concrete(y) else []
        host_u = [(names[k], np.asarray(u)[:, k]) for k in range(K)] if _concrete(u) else []
        _refuse_nonfinite("Signals()", host_y + host_u)  # columns checked on the host
        if _concrete(y) and _concrete(u):
            _refuse_output_as_input(np.asarray(y), np.asarray(u), output_name, names)
        self.y, self.u, self.delays = y, u, delays
        self.dt, self.dt_host, self.t0 = np.float64(dt), float(dt), float(t0)
        note = ""
        if offset is not None and not isinstance(offset, (bool, np.bool_)):  # "no" read True
            raise TypeError(f"Signals(): offset must be True, False or None (the data decide), "
                            f"got {offset!r}")
        if offset is None:
            offset, note = offset_needed(y, u, names)
        self.intersample, self.smooth, self.offset = intersample, smooth, bool(offset)
        self.offset_note = note
        self.output_rule = output_rule
        self.output_name, self.input_names = str(output_name), names

    def unlabelled(self, **changes) -> Signals:
        """The same data with t0 = 0, default names and no `offset_note`: what jitted programs
        see, so that a new t0, column name or note never compiles a new program (labels are put
        back on the results; the note, with its numbers, differs between records: a record at
        another operating point compiled `identify` and the search's chunk again).
        `changes`: other fields replaced in the same copy (e.g. padded y and u)."""
        K = self.n_inputs
        return replace_fields(self, t0=0.0, output_name="y", offset_note="", dt_host=None,
                              input_names=tuple(f"u{k + 1}" for k in range(K)), **changes)

    def window(self, t0: float, t1: float) -> Signals:
        """The samples with t0 <= t <= t1 (rounded to the grid) as their own record; time,
        rules, delays, offset and names are kept."""
        _b.require_x64("Signals.window")  # device_put narrowed to float32 without it
        _b.window("Signals.window", "window", (t0, t1))
        T, dt = self.n_samples, self.host_dt  # a number also for stacked records under vmap
        a, b = round((float(t0) - self.t0) / dt), round((float(t1) - self.t0) / dt)
        if 0 <= a == b <= T - 1:
            raise ValueError(f"Signals.window(): ({float(t0):g}, {float(t1):g}) rounds to one "
                             f"sample (t = {self.t0 + a * dt:g}) of the grid of step {dt:g}; a "
                             "window needs at least 2 samples: widen it")
        if not 0 <= a < b <= T - 1:
            raise ValueError(f"Signals.window(): ({float(t0):.15g}, {float(t1):.15g}) must lie "
                             f"inside the record [{self.t0:.15g}, {self.t0 + (T - 1) * dt:.15g}]")
        if _b.is_traced(self.y) or _b.is_traced(self.u):
            y, u = self.y[a:b + 1], self.u[a:b + 1]
        else:  # sliced on the host: no program per window length
            y, u = jax.device_put((np.asarray(self.y)[a:b + 1], np.asarray(self.u)[a:b + 1]))
        return replace_fields(self, y=y, u=u, t0=self.t0 + a * dt)

    @staticmethod
    def concatenate(records: Sequence[Signals]) -> tuple[Signals, list]:
        r"""Several experiments of one system as one record and its experiment windows.

        The records (same dt, inputs, intersample rules, offset choice and names) are laid end
        to end in time (each starts one dt after the previous one ends). Pass the windows as
        `identify=` to `search` or `estimate`: the Gram integral (eq. 9-10) then sums each
        experiment's valid samples only (a modulating function never straddles two
        experiments), so the equation error of every experiment is weighted by its duration
        (equal weight per unit time; scale a record's y and u to weight it otherwise).
        Simulations (E, fit, observers) must stay inside one window.

        **Returns:** (Signals, [(t0, t1) of each experiment]).
        """
        records = list(records)
        if not records or not all(isinstance(r, Signals) for r in records):
            raise TypeError("Signals.concatenate(): give a list of Signals (one per experiment)")
        _b.eager_only("Signals.concatenate", records)
        first = records[0]
        for i, r in enumerate(records[1:], 1):
            for attr in ("dt", "intersample", "smooth", "offset", "output_rule", "output_name",
                         "input_names"):
                if attr == "dt" and abs(r.dt - first.dt) <= _same_step(r, first):
                    continue  # the same step, to the time stamps' rounding
                if getattr(r, attr) != getattr(first, attr):
                    show = (lambda v: f"{float(v):.15g}") if attr == "dt" else repr  # noqa: E731
                    raise ValueError(f"Signals.concatenate(): record {i} has {attr}="
                                     f"{show(getattr(r, attr))}, record 0 has "
                                     f"{show(getattr(first, attr))}; experiments must match")
            if not np.array_equal(np.asarray(r.delays), np.asarray(first.delays)):
                raise ValueError(f"Signals.concatenate(): record {i} has other delays than "
                                 "record 0; experiments of one system share their delays")
        windows, t = [], first.t0
        for r in records:
            windows.append((t, t + (r.n_samples - 1) * r.dt))
            t += r.n_samples * r.dt
        note = first.offset_note
        if first.offset:
            levels = [float(np.mean(np.asarray(r.y))) for r in records]
            spread = max(float(np.std(np.asarray(r.y))) for r in records)
            u_levels = np.asarray([np.mean(np.asarray(r.u), axis=0) for r in records])
            u_spread = np.max([np.std(np.asarray(r.u), axis=0) for r in records], axis=0)
            alike = bool(np.all(np.ptp(u_levels, axis=0) <= u_spread)) if first.n_inputs \
                else True  # the inputs' levels cannot explain the output's move
            if max(levels) - min(levels) > spread and alike:
                warnings.warn(
                    "Signals.concatenate(): the records' outputs sit at "
                    f"{', '.join(f'{v:.4g}' for v in levels)}, further apart than any record's "
                    f"own spread ({spread:.3g}), while their inputs sit at the same levels, and "
                    "one offset term serves them all: records at different operating points "
                    "need their levels removed each (detrend(record, 'constant') or 'linear'), "
                    "then joined with offset=False", stacklevel=_b.user_stacklevel())
            if any(r.offset_note != note for r in records[1:]):  # (record 0's note said
                # "the output sits at 50.1" of a record joined with one at 80)
                note = (f"one offset term for the {len(records)} joined records (their own "
                        "notes: " + "; ".join(f"record {i}: {r.offset_note or 'given'}"
                                              for i, r in enumerate(records)) + ")")
        joined = replace_fields(first, y=jnp.concatenate([r.y for r in records]),
                                u=jnp.concatenate([r.u for r in records]), offset_note=note)
        return joined, windows

    # -- derived quantities -------------------------------------------------------------------
    @property
    def n_samples(self) -> int:
        return self.y.shape[-1]

    @property
    def n_inputs(self) -> int:
        """K, the number of measured inputs (the offset term is not counted)."""
        return self.u.shape[-1]

    @property
    def duration(self) -> float:
        return (self.n_samples - 1) * self.dt

    @property
    def host_dt(self) -> float:
        """dt as a host number for host decisions (kernel and window lengths in samples): the
        value, or under `jax.vmap` of stacked records the number they were built with."""
        if not _b.is_traced(self.dt):
            return float(self.dt)
        if self.dt_host is None:
            raise ValueError("Signals: dt is traced and no host value is known; build the "
                             "Signals with a number for dt outside the traced function")
        return self.dt_host

    @property
    def t(self) -> jax.Array:
        return jax.device_put(self.t0 + self.dt * np.arange(self.n_samples, dtype=np.float64))

    # -- constructors ---------------------------------------------------------------------------
    @classmethod
    def from_columns(
        cls,
        columns: dict,
        *,
        output: str,
        inputs: Sequence[str] = (),
        time: str | None = None,
        dt: float | None = None,
        source: str = "data",
        resample: float | None = None,
        **kwargs,
    ) -> Signals:
        """Build from a mapping of column name -> 1-D array (used by the CSV and pandas paths).

        A non-uniform time column is refused unless `resample=dt` is given: the columns are then
        put on the uniform grid of step dt from the first time (`mfmjax.resample`: inputs by
        their `intersample` rule, the output by linear interpolation)."""
        inputs = _column_list(inputs)
        if time is not None and "t0" in kwargs:
            raise ValueError(f"{source}: give either a time column (time=..., whose first value "
                             "is the start) or t0, not both")
        available = list(columns)
        for role, name in [("output", output)] + [("inputs", c) for c in inputs] + (
            [("time", time)] if time is not None else []
        ):
            if name not in columns:
                named = [c for c in available if str(c).strip()]  # (a trailing separator
                # gives an empty last name: the DaISy exchanger file's first line)
                headless = bool(named) and all(_is_number(c) for c in named)
                raise ValueError(
                    f"{source}: unknown column {name!r} for {role}; available: {available}"
                    + ("; the first line holds numbers, so the file has no header: give the "
                       "column names (names=[...], or --names on the command line)"
                       if headless else ""))
        if time is None and dt is None:
            raise ValueError(f"{source}: give a time column (time=...) or the sampling interval dt")
        arrays = {}
        for name in [output, *inputs] + ([time] if time else []):
            arrays[name] = np.asarray(columns[name], dtype=np.float64)
        if time and np.asarray(columns[time]).dtype in (np.float32, np.float16):
            arrays[time] = np.asarray(columns[time])  # Signals names its lost precision
        _warn_frozen(source, arrays, [output, *inputs], time)
        u = np.stack([arrays[c] for c in inputs], axis=1) if inputs else None
        if resample is not None:
            from ._prepare import resample_arrays

            if time is None or dt is not None:
                raise ValueError(f"{source}: resample= needs a time column (time=...) and no dt; "
                                 "it reads the record at its sample times")
            t_all = arrays[time]
            for c in [output, *inputs, time]:  # missing is NaN or a blank cell, not inf
                if np.isinf(arrays[c]).any():
                    raise ValueError(f"{source}: column {c!r} has an inf sample at row "
                                     f"{int(np.argmax(np.isinf(arrays[c])))} (0-based); "
                                     "resample drops missing samples (NaN, blank) but inf is "
                                     "a value (an overflow upstream?): blank it if it is "
                                     "missing")
            kept = {c: np.isfinite(arrays[c]) & np.isfinite(t_all) for c in [output, *inputs]}
            for c, keep in kept.items():  # a missing sample is dropped and interpolated across
                if keep.sum() < 2:
                    raise ValueError(f"{source}: column {c!r} has fewer than 2 finite samples")
            try:
                t0, y_r, u_r, rules, _ = resample_arrays(
                    "Signals.from_columns", t_all[kept[output]], arrays[output][kept[output]],
                    {c: (t_all[kept[c]], arrays[c][kept[c]]) for c in inputs}, dt=resample,
                    intersample=kwargs.pop("intersample", "foh"), output_name=output)
            except (ValueError, TypeError) as err:
                raise type(err)(f"{source}: {err}") from None
            return cls(y_r, u_r, dt=float(resample), t0=t0, intersample=rules,
                       output_name=output, input_names=inputs, **kwargs)
        try:
            return cls(
                arrays[output],
                u,
                dt=dt,
                t=arrays[time] if time else None,
                output_name=output,
                input_names=inputs,
                **kwargs,
            )
        except ValueError as err:
            if "not uniformly sampled" not in str(err):
                raise
            raise ValueError(f"{err} (from_columns/from_csv: pass resample=DT for a grid of "
                             "step DT; CLI: --resample DT)") from None

    @classmethod
    def from_csv(cls, path, *, output: str, inputs: Sequence[str] = (), time=None, dt=None,
                 names: Sequence[str] | None = None, **kwargs) -> Signals:
        """Read a CSV file with a header row (or headerless, columns named by `names`)."""
        inputs = _column_list(inputs)
        used = [output, *inputs] + ([time] if time is not None else [])
        columns = read_csv(path, names, used=[str(c) for c in used])
        return cls.from_columns(columns, output=output, inputs=inputs, time=time, dt=dt,
                                source=f"{path}", **kwargs)

    @classmethod
    def from_dataframe(cls, df, *, output: str, inputs: Sequence[str] = (), time=None, dt=None,
                       **kwargs) -> Signals:
        """Build from a pandas DataFrame (pandas is optional and only needed here).

        `time` names a column or the index (its name, or "index" for an unnamed one).
        Date-times (datetime64, with or without a time zone) and durations (timedelta64) are
        read as seconds since the first one, so `dt`, `h` and the delays are in seconds;
        numbers are taken in their own unit."""
        # labels are matched as text: output=1 finds the column labelled 1
        output, inputs = str(output), [str(c) for c in _column_list(inputs)]
        time = None if time is None else str(time)
        cols = {str(c): c for c in df.columns}
        if time is not None and time not in cols and (
                str(df.index.name) == str(time) or (df.index.name is None and time == "index")):
            df = df.rename_axis(str(time)).reset_index()  # the index (time="index": unnamed)
            cols = {str(c): c for c in df.columns}
        wanted = {str(c) for c in [output, *inputs] + ([time] if time is not None else [])}
        dup = sorted({str(c) for c in df.columns[df.columns.duplicated()]} & wanted)
        if dup:
            raise ValueError(f"DataFrame: the column name(s) {dup} occur more than once: rename "
                             "the columns (df.columns = [...]) so that each is named once")
        columns = {name: (_dataframe_column(df[c], name) if name in wanted else None)
                   for name, c in cols.items()}
        return cls.from_columns(columns, output=output, inputs=inputs, time=time, dt=dt,
                                source="DataFrame", **kwargs)


def _column_list(inputs) -> list:
    """The input column names as a list: one name given as a string is one column (it was
    split into its letters: inputs="heat" read columns 'h', 'e', ...)."""
    return [inputs] if isinstance(inputs, str) else list(inputs)


def _dataframe_column(series, name: str) -> np.ndarray:
    """A DataFrame column as float64: date-times and durations in seconds since the first."""
    if series.dtype.kind in "mM":  # timedelta64 / datetime64 (a tz-aware dtype too)
        first = series.dropna()
        if first.empty:
            return np.full(len(series), np.nan)
        return (series - first.iloc[0]).dt.total_seconds().to_numpy(np.float64, na_value=np.nan)
    if series.dtype.kind == "f" and series.dtype.itemsize < 8:  # float32 stays float32 here,
        return series.to_numpy()  # so that a time column's lost precision is named (Signals)
    try:
        return series.to_numpy(dtype=np.float64, na_value=np.nan)
    except (TypeError, ValueError):
        cell = next((v for v in series if not _is_number(str(v))), None)
        raise ValueError(f"DataFrame: column {name!r} holds {cell!r}, not a number: convert it "
                         "(pandas.to_numeric; pandas.to_datetime for a time column, which is "
                         "then read in seconds)") from None


def _refuse_nonfinite(source: str, columns: list) -> None:
    """Refuse the first (label, column) holding a NaN or inf, by its (0-based) row."""
    for label, arr in columns:
        finite = np.isfinite(arr)
        if not finite.all():
            raise ValueError(
                f"{source}: column {label!r} has a NaN or inf sample at row "
                f"{int(np.argmin(finite))} (0-based); remove or interpolate it before "
                "identification (with a time column, resample=DT or --resample DT drops missing "
                "samples and interpolates across them)")


def held_inputs_note(signals) -> tuple[str, ...]:
    """A note (or none) naming the inputs read as foh (not smooth) that switch between levels:
    at least half the steps repeat the last sample and most jumps cross more than one level
    (a quantised sensor moves to the next one), or two or three levels only (a PRBS clocked
    every sample), with two changes or more: a PRBS, a DAC or a controller's output, held
    between samples, which foh reads as linear between them (an SRIVC fit of such a record
    moved b_11 by 4.85 standard errors, status "converged", nothing said; an audit of
    2026-11-28)."""
    if _b.is_traced(signals.u):
        return ()
    u = np.asarray(signals.u)
    held = []
    for k, (rule, smooth) in enumerate(zip(signals.intersample, signals.smooth)):
        x = u[:, k]
        d = np.diff(x)
        changes = np.flatnonzero(d != 0)
        if rule != "foh" or smooth or changes.size < 2:
            continue
        levels = np.unique(x)
        quantum = float(np.min(np.diff(levels)))
        across = np.mean(np.abs(d[changes]) > 1.5 * quantum)  # jumps over several levels: a
        # quantised sensor moves to the next level (a sine at 0.25 of 2 was flagged)
        if levels.size <= 3 or (np.mean(d == 0) >= 0.5 and across >= 0.5):  # (a PRBS clocked
            held.append(signals.input_names[k])  # every sample: two levels)
    if not held:
        return ()
    return (f"the input(s) {held} switch between levels (runs of equal samples, or two or three "
            "levels) but are read as foh (linear between samples): if they were held between "
            "samples (a PRBS, a DAC, a controller's output), declare intersample='zoh' "
            "(Signals, from_csv; --intersample zoh), else the model is biased",)


FROZEN_ROWS = 20  # this many repeats of a row in every column used: a frozen logger


def _warn_frozen(source: str, arrays: dict, used: list, time) -> None:
    """Warn where a record's rows repeat in every column used for `FROZEN_ROWS` rows or more
    (after the first row: a rest at the start is common): a frozen logger or a historian's
    held value, which noisy plant data never do and which would be fitted as real."""
    if len(used) < 2:  # an output alone (quantised, settled) repeats without a fault
        return
    X = np.column_stack([arrays[c] for c in used])
    same = np.all(X[1:] == X[:-1], axis=1)
    edges = np.flatnonzero(np.diff(np.concatenate([[0], same.astype(np.int8), [0]])))
    for a, b in zip(edges[::2], edges[1::2]):  # rows a..b equal row a
        if b - a >= FROZEN_ROWS and a > 0:
            at = ((lambda k: f"row {k} (t={arrays[time][k]:.10g})") if time
                  else (lambda k: f"row {k}"))
            warnings.warn(
                f"{source}: {b - a + 1} rows from {at(a)} to {at(b)} (0-based) repeat the same "
                f"values in every column used ({', '.join(map(repr, used))}): a frozen logger "
                "or a held value? They are fitted as real data. Drop those rows and resample "
                "(resample=DT, --resample DT: the gap is interpolated, with a warning), or "
                "identify on one side of them (Signals.window, --identify-window)",
                stacklevel=4)
            return


_COMMENT = ("{path}: line {line} starts with '#'; mfmjax reads no comment lines after the "
            "header: remove them")


def read_csv(path, names: Sequence[str] | None = None, *,
             used: Sequence[str] | None = None) -> dict[str, np.ndarray]:
    """Read a table of numbers into {name: float64 array}; clear errors on bad cells.
    `used`: read only these columns (the others map to None, so a historian's text status
    column not used does not stop the file).

    Comma-separated with a header row by default. With `names`, the file has no header and the
    columns get these names; fields may then also be separated by whitespace (DaISy .dat files).
    An all-numeric body is parsed in C (pandas when it is already imported or the file is large,
    else `numpy.loadtxt`); anything else (empty cells read as NaN, quoted fields, a bad row)
    goes through a line-by-line parser that names the offending line.
    """
    try:
        with open(path, "rb") as fh:
            raw = fh.read()
    except OSError as err:
        raise ValueError(f"cannot read {path}: {err.strerror}") from None
    if b"\x00" in raw[:65536]:
        raise ValueError(f"{path}: this is a binary file (it contains NUL bytes), not a text "
                         "table; give a comma-separated text file")
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as err:
        raise ValueError(
            f"{path}: not a UTF-8 text file (byte 0x{raw[err.start]:02x} at offset {err.start}); "
            "give a comma-separated text file in UTF-8 (or ASCII)"
        ) from None
    if "\r" in text:  # Windows (CRLF) and old Mac (CR alone) line ends: one rule for all
        text = text.replace("\r\n", "\n").replace("\r", "\n")
    first_line, rest = _first_line(text)
    if first_line is None:
        raise ValueError(f"{path}: the file is empty; expected a header row")
    if first_line.lstrip().startswith("#") and names is None:
        first_line = first_line.lstrip()[1:]  # numpy.savetxt's header: "# t,y,u"
    probe = _first_line(rest)[0] if names is None else first_line  # a data line: names may
    probe = probe or first_line  # hold ',' ("T [degC, PV]") or ';' ("T;PV")
    # a European export: "t;y;u" over "0;1,5;2,5" (as many ',' as ';' in the data line)
    if any(line.count(";") > line.count(",") for line in (probe, first_line)) or (
            ";" in probe and probe.count(";") >= probe.count(",")):
        raise ValueError(
            f"{path}: fields are separated by ';' (line 1: {first_line[:40]!r}); mfmjax reads "
            "comma-separated files with '.' as the decimal point: re-export the file as CSV, or "
            "read it with pandas.read_csv(path, sep=';', decimal=',') and "
            "Signals.from_dataframe"
        )
    comma = "," in first_line
    tab = names is None and not comma and "\t" in first_line  # names may hold spaces

    def split(line, n=None):
        if comma:
            cells = next(csv.reader([line], skipinitialspace=True))  # `"t", "y"`
        elif tab:  # a trailing tab, or data separated by spaces under a tab header, read too
            cells = line.split("\t")
            if n is not None and len(cells) != n:
                cells = (cells[:n] if len(cells) > n and not "".join(cells[n:]).strip()
                         else line.split() if len(line.split()) == n else cells)
        else:
            cells = line.split()
        return [c.strip() for c in cells]

    if names is None:
        header, body, first = split(first_line), rest, 2
    else:
        header, body, first = [str(n) for n in names], text, 1
    if len(set(header)) != len(header):
        headless = names is None and all(_is_number(c) for c in header)  # "0,0,1": at rest
        raise ValueError(f"{path}: duplicate column names {header}"
                         + ("; the first line holds numbers, so the file has no header: give "
                            "the column names (names=[...], or --names on the command line)"
                            if headless else ""))
    if not body.strip():
        raise ValueError(f"{path}: no data rows after the header")
    data = _parse_fast(body, "," if comma else "\t" if tab else None, len(header))
    if data is not None:
        return {name: data[:, j] for j, name in enumerate(header)}
    # the careful path: missing cells as NaN, date-time columns, or the precise error
    rows, linenos = [], []
    lines = (ln for ln in body.splitlines() if ln.strip())
    for lineno, line in enumerate(lines, start=first):
        if line.lstrip().startswith("#"):
            raise ValueError(_COMMENT.format(path=path, line=lineno))
        row = split(line, len(header))
        if len(row) != len(header):
            raise ValueError(
                f"{path}: line {lineno} has {len(row)} fields but "
                + (f"{len(header)} names were given (--names)" if names is not None
                   else f"the header has {len(header)} columns")
                + "; every row needs one field per column"
                + ("" if comma else " (fields are split at commas, else at tabs, else at "
                   "spaces)")
            )
        rows.append(row)
        linenos.append(lineno)
    return {name: _csv_column(path, name, [r[j] for r in rows], linenos, first)
            if used is None or name in used else None for j, name in enumerate(header)}


MISSING = ("", "nan", "NaN", "NAN", "#N/A", "N/A", "n/a", "NA", "#NA", "NULL", "null", "None")


def _csv_column(path, name: str, cells: list, linenos: list, first: int) -> np.ndarray:
    """One column of the careful path as float64: a missing value (`MISSING`: an empty cell,
    NaN, #N/A, NULL, ...) as NaN; a column of ISO 8601 date-times (`_iso_stamp`) as seconds
    since the first; anything else refused with its line and a hint."""
    out = np.full(len(cells), np.nan)
    bad = []
    for i, c in enumerate(cells):
        if c in MISSING:
            continue
        try:
            if "_" in c:  # Python's float() reads "1_00" as 100: no export writes that
                raise ValueError(c)
            out[i] = float(c)
        except ValueError:
            bad.append(i)
    if not bad:
        return out
    i = bad[0]
    unit_row = ("the file has a header row: drop names= (--names), which is for files "
                "without one" if first == 1 else "a unit row under the header? remove it")
    hint = ("missing values may be empty, NaN or #N/A; a time column may hold ISO 8601 "
            "date-times (2024-03-05 08:00:00), read as seconds since the first; write the "
            "decimal point as '.'")
    if len(bad) == len(cells) - sum(c in MISSING for c in cells):  # no number in the column
        stamps = {j: _iso_stamp(cells[j]) for j in bad}
        failed = [j for j in bad if stamps[j] is None]
        if not failed:
            out = np.full(len(cells), np.datetime64("NaT", "ns"))
            out[bad] = [stamps[j] for j in bad]
            return (out - out[bad[0]]) / np.timedelta64(1, "s")
        if failed == bad:  # the whole column is text
            hint = ("the column holds text or date-times not in ISO 8601: convert them to "
                    "numbers or to ISO 8601 (2024-03-05 08:00:00); from_csv and the command "
                    "line read only the columns given as output, inputs and time")
        elif failed == [bad[0]] and linenos[bad[0]] == first:
            hint = unit_row
        else:  # the first cell that is not a date-time like the others
            i = failed[0]
    elif bad == [i] and linenos[i] == first:
        hint = unit_row
    cell = cells[i]
    if _THOUSANDS.match(cell):  # "1,000" or "12,345.6": a separator, or (without '.') a comma
        hint = ("a thousands separator" + ("" if "." in cell else " or a decimal comma") +
                "? mfmjax reads plain numbers: re-export the file without separators, or read "
                "it with pandas.read_csv(path, thousands=',') (1,000 is 1000)" +
                ("" if "." in cell else " or decimal=',' (1,000 is 1.0), whichever the "
                 "export used,") + " and Signals.from_dataframe")
    elif "_" in cell and _is_number(cell):  # "1_00": Python's digit grouping, not a CSV's
        hint = ("'_' inside a number: Python would read it as digit grouping (1_00 as 100), a "
                "CSV export does not write it; remove the '_' or fix the export")
    elif _DECIMAL_COMMA.match(cell):  # "1,5" (tab-separated, or quoted in a comma file)
        hint = ("a decimal comma? mfmjax reads '.' as the decimal point: re-export the file, "
                "or read it with pandas.read_csv(path, sep=..., decimal=',') and "
                "Signals.from_dataframe")
    raise ValueError(f"{path}: line {linenos[i]} has a non-numeric value {cell[:20]!r} in "
                     f"column {name!r}; every row after the header must hold numbers ({hint})")


_DECIMAL_COMMA = re.compile(r"^[+-]?\d*,\d+([eE][+-]?\d+)?$")
_THOUSANDS = re.compile(r"^[+-]?\d{1,3}(,\d{3})+(\.\d*)?$")


def _iso_stamp(cell: str):
    """An ISO 8601 date-time (a final Z or an offset such as +01:00: converted to UTC) as
    datetime64[ns], or None (numpy's words 'now', 'today', 'NaT' are not date-times here)."""
    if not cell[:4].isdigit():
        return None
    text = cell[:-1] if cell[-1] in "Zz" else cell
    try:
        with warnings.catch_warnings():  # an offset: numpy converts it, with a warning
            warnings.simplefilter("ignore")
            return np.datetime64(text, "ns")
    except ValueError:
        return None


def _is_number(cell: str) -> bool:
    try:
        float(cell)
    except ValueError:
        return False
    return True


def _first_line(text: str):
    """(first non-blank line, the text after it), or (None, "") for a blank text."""
    pos = 0
    while pos < len(text):
        end = text.find("\n", pos)
        end = len(text) if end < 0 else end
        line = text[pos:end].rstrip("\r")
        if line.strip():
            return line, text[end + 1 :]
        pos = end + 1
    return None, ""


_PANDAS_MIN_CHARS = 32_000_000  # below this, importing pandas costs more than loadtxt saves


def _parse_fast(body: str, sep: str | None, n_cols: int):
    """An all-numeric, complete body parsed in C, or None when the careful path is needed
    (quoted fields, empty cells, short or long rows, non-numbers: that path names the line).
    `sep`: "," or a tab, or None for any whitespace."""
    import io
    import sys

    if (sep == "," and '"' in body) or "_" in body:  # Python reads "1_00" as 100: refused
        return None
    try:
        if "pandas" in sys.modules or len(body) > _PANDAS_MIN_CHARS:
            import pandas as pd

            data = pd.read_csv(io.StringIO(body), header=None, sep=sep or r"\s+",
                               dtype=np.float64, keep_default_na=False, na_values=[""],
                               engine="c").to_numpy(np.float64)
        else:
            data = np.loadtxt(io.StringIO(body), delimiter=sep, dtype=np.float64,
                              comments=None, ndmin=2)
    except Exception:  # any parse failure: the careful path reports it precisely
        return None
    if data.ndim != 2 or data.shape[1] != n_cols or np.isnan(data).any():
        return None  # pandas pads short rows with NaN: let the careful path judge them
    return data
