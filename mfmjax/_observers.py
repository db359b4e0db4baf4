r"""Exact integral state observers with minimal norm (eq. 14-16) and the performance index (17).

With $y(t) = C e^{At} x_0 + y_f(t)$ ($y_f$ the response from rest, computed exactly for the
zoh/foh/delayed inputs by `simulate`'s step map) the minimal-norm observer of eq. (14) is
$x_0 = M_0^{-1} \int_0^{T_{OB}} e^{A't} C' (y(t) - y_f(t))\,dt$,
$M_0 = \int_0^{T_{OB}} e^{A't} C'C e^{At} dt$. Swapping the order of integration in the
$y_f$ term gives exactly the paper's $\bar G_2(t)$ kernel, with a MINUS sign (the paper prints +;
see `method.md` section 6). The final state of eq. (15) is $x(T_{OB}) = e^{AT_{OB}} x_0 + x_f(T_{OB})$.

Numerics: $e^{At}$ is only ever propagated forward ($C e^{A t_{k+1}} = C e^{A t_k} e^{A\,dt}$),
never inverted, so long windows are safe; the $t$-integrals use the Gregory rule (O(dt^4));
$M_0$ is equilibrated before it is solved, and its conditioning flags unobservable windows.
"""

from __future__ import annotations

import math
import types
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import _boundary as _b
from ._boundary import require_x64
from ._jit import jit
from ._linalg import conditioning_eigvals, small_matmul, solve
from ._model import Model, growing_poles, simulation_form
from ._pytree import replace_fields
from ._quadrature import EDGE, edge_padded, gregory_weights, record_bucket
from ._signals import Signals
from ._simulate import forced_response
from ._status import Status

MIN_WINDOW = 8  # fewest samples in an observer window (Gregory rule needs 6)
GROWTH_LIMIT = 10.0  # e-foldings of a growing mode over a window beyond which it swamps M0
UNOBSERVABLE_COND = 1e13  # cond of the equilibrated Gramian above this: flagged


class Observation(eqx.Module):
    """Result of the observers on one window (batched paths read `status`, never raise)."""

    x_initial: jax.Array  # state at the window start (eq. 14)
    x_final: jax.Array  # state at the window end (eq. 15)
    y_sim: jax.Array  # (W,) simulated output on the window from x_initial
    E: jax.Array  # performance index (eq. 17) on the window
    cond: jax.Array  # cond of the equilibrated observability Gramian M0
    status: jax.Array


def observe_window(
    model: Model, y, u, dt: float, start, length: int, ob_length=None, valid=None
) -> Observation:
    """Observers + E on samples `start .. start+length-1` of a record (y (T,), u (T, K)).

    `length` is static, `start` may be traced (moving windows, eq. 16). Inputs before `start`
    are taken from the record (delays see the real history). The initial-state observer uses the
    first `ob_length` samples (default all); the simulation and E cover the whole window, or its
    first `valid` samples (`observe_forced`).
    """
    return observe_forced(forced_response(model, u, dt), y, dt, start, length, ob_length, None,
                          valid)


def observe_forced(
    forced, y, dt: float, start, length: int, ob_length, state_mask=None, valid=None
):
    """`observe_window` on a precomputed whole-record drive (shared by moving windows).

    `state_mask` (n,) marks the live states of a zero-padded realisation (batched search over
    orders): padded states get x = 0 and do not enter the Gramian's conditioning. `ob_length`
    may be traced. `valid` (traced, <= `length`) makes only the window's first `valid` samples
    count (E, the final state, the overflow test): one program for windows of any length up
    to the static `length` (a record padded beyond `valid`; `y_sim` there is meaningless).
    """
    ss, Phi, drive, direct = forced
    n = ss.A.shape[0]
    dr = jax.lax.dynamic_slice_in_dim(drive, start, length)
    di = jax.lax.dynamic_slice_in_dim(direct, start, length)
    yw = jax.lax.dynamic_slice_in_dim(y, start, length)

    def step(carry, d):  # forced response from rest and the free-response rows C e^{A t_j}
        x, row = carry
        return ((small_matmul(Phi, x) + d, small_matmul(Phi.T, row)),
                (small_matmul(ss.C, x)[0], row))

    _, (y_f, rows) = jax.lax.scan(step, (jnp.zeros(n), ss.C[0]), dr)
    y_forced = y_f + di
    q = gregory_weights(length, 0, dt, end=valid)
    if valid is not None:  # the padding may overflow (an unstable candidate): never count it
        inside = jnp.arange(length) < valid
        rows = jnp.where(inside[:, None], rows, 0.0)
    q_ob = gregory_weights(length, 0, dt, end=length if ob_length is None else ob_length)
    M0 = rows.T @ (q_ob[:, None] * rows)  # observability Gramian over the observer window
    rhs = rows.T @ (q_ob * (yw - y_forced))
    d = 1.0 / jnp.sqrt(jnp.where(jnp.diagonal(M0) > 0, jnp.diagonal(M0), 1.0))
    Me = d[:, None] * M0 * d[None, :]
    if state_mask is not None:
        live = state_mask[:, None] & state_mask[None, :]
        Me = jnp.where(live, Me, jnp.eye(n))
        rhs = jnp.where(state_mask, rhs, 0.0)
    x0 = d * solve(Me, d * rhs)
    lam = conditioning_eigvals(Me, jnp.asarray([0, n - 1]))
    cond = lam[1] / jnp.maximum(lam[0], lam[1] * jnp.finfo(jnp.float64).eps)

    def traj(x, d):
        return small_matmul(Phi, x) + d, x

    _, xs = jax.lax.scan(traj, x0, dr)
    y_sim = xs @ ss.C[0] + di
    if valid is None:
        E = jnp.sum(q * (yw - y_sim) ** 2)
        x_final = xs[-1]
    else:
        E = jnp.sum(jnp.where(inside, q * (yw - y_sim) ** 2, 0.0))
        x_final = jax.lax.dynamic_index_in_dim(xs, valid - 1, keepdims=False)
    status = jnp.where(cond > UNOBSERVABLE_COND, Status.UNOBSERVABLE, 0)
    finite = jnp.all(jnp.isfinite(x0)) & jnp.isfinite(E) & jnp.all(jnp.isfinite(rows))
    status = status | jnp.where(finite, 0, Status.OVERFLOW)
    return Observation(x0, x_final, y_sim, E, cond, status.astype(jnp.int32))


# -- public boundary -------------------------------------------------------------------------


def _window(model: Model, signals: Signals, window, fn: str):
    require_x64(fn)
    if not isinstance(model, Model):
        raise TypeError(f"{fn}(): model must be a Model, got {type(model).__name__}"
                        f"{_b.swap_hint(fn, model)}")
    if not isinstance(signals, Signals):
        raise TypeError(f"{fn}(): signals must be a Signals, got {type(signals).__name__}"
                        f"{_b.swap_hint(fn, signals)}")
    _b.same_inputs(fn, model, signals)
    return validation_window(signals, window, None, model.n, fn, "window")[:2]


def validation_window(signals: Signals, window, observer_window, n: int, fn: str,
                      name: str = "validate window"):
    """(start, length, observer length) in samples of a window (t0, t1) (default: the record)
    and of its initial-state observer window (default: the whole window), checked at the
    public boundary for an order-`n` observer; `name` is the argument the errors name."""
    T, dt, t0 = signals.n_samples, signals.host_dt, signals.t0
    if window is None:
        v0, v1 = 0, T - 1
    else:
        w0, w1 = _b.window(fn, "validate" if name == "validate window" else name, window)
        v0, v1 = round((w0 - t0) / dt), round((w1 - t0) / dt)
        if 0 <= v0 and v1 <= T - 1 and v1 <= v0 and w0 < w1:  # (it said "must lie inside")
            raise ValueError(
                f"{fn}(): {name} ({w0:g}, {w1:g}) rounds to one sample (t = "
                f"{t0 + v0 * dt:g}: the ends are read at the nearest samples, dt = {dt:g}); "
                f"widen it to at least {max(MIN_WINDOW, 2 * n)} samples")
        if v0 < 0 or v1 > T - 1 or v1 <= v0:
            raise ValueError(
                f"{fn}(): {name} ({w0:g}, {w1:g}) must lie inside the record "
                f"[{t0:g}, {t0 + (T - 1) * dt:g}] with start < end"
            )
    length, need = v1 - v0 + 1, max(MIN_WINDOW, 2 * n)
    if length < need:
        raise ValueError(
            f"{fn}(): the {name} holds {length} samples, need at least {need} for an "
            f"order-{n} observer; widen it"
        )
    if observer_window is not None:
        observer_window = _b.number(fn, "observer_window", observer_window, lo=0, lo_open=True)
    ob = length if observer_window is None else round(observer_window / dt) + 1
    if not MIN_WINDOW <= ob <= length:
        raise ValueError(
            f"{fn}(): observer_window must fit inside the {name} and hold at least "
            f"{MIN_WINDOW} samples"
        )
    return v0, length, ob


def checked(obs: Observation, fn: str, model: Model | None = None,
            duration: float | None = None) -> Observation:
    """`obs`, or a ValueError naming `fn` when its status says overflow or unobservable (for
    a `model` whose growing mode rises more than e^GROWTH_LIMIT over the window's `duration`,
    that mode swamps M0: a shorter window)."""
    if not isinstance(obs.status, jax.core.Tracer):
        st = int(obs.status)
        # both bits: a singular M0 gave a non-finite x0 (the OVERFLOW bit follows from it)
        if st & Status.OVERFLOW and not st & Status.UNOBSERVABLE:
            raise ValueError(
                f"{fn}(): the model's response overflows float64 on this window (unstable "
                "model); shorten the window"
            )
        if st & Status.UNOBSERVABLE:
            growth = 0.0  # e-foldings of the model's fastest growing mode over the window
            if model is not None and duration is not None and not _b.is_traced(model.a):
                growth = float(np.max(growing_poles(model.a).real, initial=0.0)) * duration
            raise ValueError(
                f"{fn}(): the state is not observable on this window (cond(M0) = "
                f"{float(obs.cond):.1e}); " + (
                    f"the model is unstable and its growing mode rises e^{growth:.0f}-fold over "
                    "the window, swamping the observer's Gramian: shorten the window"
                    if growth > GROWTH_LIMIT else "widen the window or check the model"))
    # under an outer jit/vmap the status stays in the result (read `obs.status`): an
    # eqx.error_if here would keep the caller's program out of the persistent compile cache
    return obs


def observe(model: Model, signals: Signals, window=None, *, observer_window: float | None = None):
    r"""Initial state (eq. 14), final state (eq. 15), simulated output and E (eq. 17) on a window.

    **Arguments:** `window` = (t_start, t_end) in the time units of `signals` (default: the whole
    record); `observer_window`: length $T_{OB}$ of the initial-state observer from the window
    start (default: the whole window). The model's delays and intersample modes are used.

    **Returns:** an `Observation` (`x_initial`, `x_final`, `y_sim`, `E`, `cond`, `status`).
    Raises a clear error for unobservable windows and overflowing (unstable) responses; under
    an outer jit/vmap nothing can raise, and `status` (a `Status` bit set) says so instead.
    """
    obs = observation(model, signals, window, observer_window=observer_window)
    return checked(obs, "observe", model, (obs.y_sim.shape[0] - 1) * signals.host_dt)


def observation(model: Model, signals: Signals, window=None, *,
                observer_window: float | None = None) -> Observation:
    """`observe` without raising on the model's failures: overflow and unobservability stay in
    `status` (for callers that report them, e.g. the CLI's validation line). Bad arguments
    still raise."""
    start, length = _window(model, signals, window, "observe")
    ob = None
    if observer_window is not None:
        observer_window = _b.number("observe", "observer_window", observer_window, lo=0,
                                    lo_open=True, fix="give a length in the record's time unit")
        ob = round(observer_window / signals.host_dt) + 1
        if not MIN_WINDOW <= ob <= length:
            raise ValueError(
                f"observe(): observer_window={observer_window:g} must hold {MIN_WINDOW} to "
                f"{length} samples of the window"
            )
    if _b.is_traced(signals.y) or _b.is_traced(signals.u):
        obs = _observe(simulation_form(model), signals.y, signals.u, signals.dt,
                       jnp.asarray(start, dtype=jnp.int32), length, ob)
        return obs
    _history_warning(model, signals, start)
    _settings_warning(model, signals)
    y, u, bound = padded_window(signals, start, length)
    # one program per order n (`simulation_form`), whatever the numerator orders
    obs = _observe(simulation_form(model), y, u, signals.dt, np.int32(start), bound,
                   np.int32(length if ob is None else ob), np.int32(length))
    if _b.is_traced(obs.y_sim):  # a traced model
        y_sim = obs.y_sim[:length]
    else:
        y_sim = jax.device_put(np.asarray(obs.y_sim)[:length])  # host slice: no program
    return replace_fields(obs, y_sim=y_sim)


_observe = jit(observe_window)


def _history_warning(model: Model, signals: Signals, start: int) -> None:
    """Warn when a delayed input's response in the window reaches before the record (the
    window starts less than its delay after the first sample) while that input varies at the
    record's start: the forced response takes the input before the record as held at its
    first value (an exact model on noise-free data cut from a longer record: fit 45 %)."""
    if _b.is_traced(model.delays):
        return
    dt, u = signals.host_dt, np.asarray(signals.u)
    for k, tau in enumerate(np.asarray(model.delays, dtype=np.float64).reshape(-1)):
        need = math.ceil(tau / dt - EDGE)  # samples of the input's history the delay reaches
        if start < need and np.ptp(u[: need + 1, k]) > 0:
            name = model.input_names[k] if model.input_names else f"u{k + 1}"
            warnings.warn(
                f"observe(): input {name!r} is delayed by {tau:g} and the window starts "
                f"{start * dt:g} after the record's first sample: the response in its first "
                f"{(need - start) * dt:g} uses {name!r} from before the record, taken as held at "
                f"its first value ({u[0, k]:g}), while the record's {name!r} varies from its "
                f"start; start the window at {signals.t0 + need * dt:g} or later "
                "(window=(t_start, t_end)), unless the input was steady at that value before "
                "the record", stacklevel=_b.user_stacklevel())
            return


def _settings_warning(model: Model, signals: Signals) -> None:
    """Warn when the signals hold a zoh input (a rule a user gave: the default is foh) that
    the model treats as foh: the model's rules are the ones used (a model built with the
    defaults on zoh data with a 3 s delay gave a fit of 33 %, unsaid). Delays are not
    compared: a refined or estimated model's delays differ from the data's by design."""
    if any(s == "zoh" and s != m for s, m in zip(signals.intersample, model.intersample)):
        warnings.warn(
            f"observe(): the signals' intersample {list(signals.intersample)} differs from "
            f"the model's {list(model.intersample)}; the model's is used, as it was identified "
            "or built with it (its delays too: model.delays): give the model the data's "
            "(Model.from_coefficients(..., intersample=, delays=)) if those are right",
            stacklevel=_b.user_stacklevel())
    order = swapped_inputs(model.input_names, signals.input_names)
    if order:
        warnings.warn(f"observe(): {order}", stacklevel=_b.user_stacklevel())


def swapped_inputs(fitted, given) -> str:
    """A sentence when the record's inputs are the fitted ones (by name) in another order: the
    k-th column drives the k-th input, so the result would be for swapped inputs (a fit of
    -7 % against 75 % on a two-input record); '' otherwise (other names, e.g. the defaults
    u1, u2 against a file's, are not compared)."""
    fitted, given = tuple(fitted), tuple(given)
    if fitted == given or sorted(fitted) != sorted(given) or len(set(fitted)) < len(fitted):
        return ""
    return (f"the record's inputs {list(given)} are the fitted {list(fitted)} in another "
            f"order; the k-th column is taken as the k-th input: reorder the record's columns "
            f"to {list(fitted)}")


def padded_window(signals: Signals, start: int, length: int, bound: int | None = None):
    """(y, u, bound) of concrete `signals`: the window of `length` samples from `start` padded
    to its `record_bucket` `bound` (or the `bound` given: a share of the record's, its
    `window_bucket`), and the record to hold it, both by repeating the last sample (NumPy: no
    program): to its `record_bucket` R for a window from the record's start, else to R +
    bound. Only the window's own samples may count (`observe_forced`'s `valid`): windows and
    records of every length in a bucket then share one program (the record padded to hold
    start + bound changed shape with the window's start)."""
    T = signals.n_samples
    bound = record_bucket(length) if bound is None else bound
    R = record_bucket(T)
    pad = (max(R, bound) if start == 0 else R + bound) - T
    y, u = (edge_padded(np.asarray(x), pad) for x in (signals.y, signals.u))
    return y, u, bound


def initial_state(model: Model, signals: Signals, window=None):
    """State at the window start from the window's y and u samples (eq. 14, corrected sign)."""
    return observe(model, signals, window).x_initial


def final_state(model: Model, signals: Signals, window=None):
    """State at the window end from the window's y and u samples (eq. 15)."""
    return observe(model, signals, window).x_final


def moving_final_states(model: Model, signals: Signals, T_ob: float, times):
    r"""Eq. (16): $x(t_j)$ from the last $T_{OB}$ of data before each $t_j$ in `times`.

    Each $t_j$ and $T_{OB}$ are taken to the nearest sample (x at the sample nearest $t_j$).
    All windows have the same length, so this is one vmapped computation. A window whose
    observer is unobservable or overflows raises as `observe` does, naming its t_j (under an
    outer jit/vmap its row is NaN).
    """
    require_x64("moving_final_states")
    if not isinstance(signals, Signals):
        raise TypeError(f"moving_final_states(): signals must be a Signals, got "
                        f"{type(signals).__name__}"
                        f"{_b.swap_hint('moving_final_states', signals)}")
    T_ob = _b.number("moving_final_states", "T_ob", T_ob, lo=0, lo_open=True,
                     fix="give the observer length in the record's time unit")
    length = round(T_ob / signals.host_dt) + 1
    _b.eager_only("moving_final_states", times, fix="the times t_j set which samples each "
                  "window holds: give them as concrete numbers")
    times = _b.array("moving_final_states", "times", times, ndim=(0, 1))
    if times.size == 0:
        raise ValueError("moving_final_states(): times is empty; give at least one time t_j")
    times = np.atleast_1d(np.asarray(times, dtype=np.float64))  # NumPy: no eager programs
    ends = np.round((times - signals.t0) / signals.host_dt).astype(np.int32)
    e_np = [int(v) for v in ends]
    if min(e_np) - (length - 1) < 0 or max(e_np) > signals.n_samples - 1:
        j = next(i for i, e in enumerate(e_np) if e - (length - 1) < 0
                 or e > signals.n_samples - 1)
        end = signals.t0 + (signals.n_samples - 1) * signals.host_dt
        raise ValueError(
            f"moving_final_states(): every t_j must have T_ob of data before it inside the "
            f"record [{signals.t0:.15g}, {end:.15g}]: t_j = {times[j]:.15g} (times[{j}]) "
            + ("lies after its end" if e_np[j] > signals.n_samples - 1 else
               f"has less than T_ob = {T_ob:g} before it; T_ob is longer than the record"
               if length > signals.n_samples else  # (it named an "earliest" past the end)
               f"has less than T_ob = {T_ob:g} before it; the earliest is "
               f"{signals.t0 + (length - 1) * signals.host_dt:.15g}"))
    try:
        _window(model, signals, (signals.t0, signals.t0 + (length - 1) * signals.host_dt),
                "moving_final_states")
    except ValueError as err:  # (a window too short for the order): say which T_ob
        raise ValueError(f"{err} (T_ob = {T_ob:g}: each window ends at its t_j)") from None
    if _b.is_traced(signals.y) or _b.is_traced(signals.u):
        y, u, bound = signals.y, signals.u, length
    else:  # the record and the windows padded to their buckets: one program per bucket pair
        bound = record_bucket(length)
        y, u, _ = padded_window(signals, 1, length, bound)
    x, status, cond = _moving(simulation_form(model), y, u, signals.dt, jax.device_put(ends),
                              np.int32(length), bound)
    if not _b.is_traced(status):  # as observe: an unobservable or overflowing window raises
        status, cond = np.asarray(status), np.asarray(cond)
        for j in np.flatnonzero(status)[:1]:
            try:
                checked(types.SimpleNamespace(status=status[j], cond=cond[j]),
                        "moving_final_states", model, (length - 1) * signals.host_dt)
            except ValueError as err:
                raise ValueError(f"{err} (T_ob = {T_ob:g}, the window ending at t_j = "
                                 f"{times[j]:g})") from None
    return x


@jit
def _moving(model, y, u, dt, ends, length, bound: int):
    """x(t_j) of eq. (16) from windows of `length` (a value) samples ending at `ends`, each
    held in a `bound`-sample buffer (static) of which only the first `length` count."""
    forced = forced_response(model, u, dt)  # once for the record, not once per window
    obs = jax.vmap(lambda e: observe_forced(forced, y, dt, e - (length - 1), bound, length,
                                            None, length))(ends)
    # a window whose status is not ok gives NaN (under an outer jit nothing can raise)
    x = jnp.where(obs.status[:, None] == 0, obs.x_final, jnp.nan)
    return x, obs.status, obs.cond


def performance_index(model: Model, signals: Signals, window=None, *, observer_window=None):
    r"""E of eq. (17): $\int (y - y_{sim})^2 dt$ on the window, $y_{sim}$ from the observed $x_0$."""
    return observe(model, signals, window, observer_window=observer_window).E


CONSTANT_RTOL = 1e-12  # y's spread below this fraction of |y| (per sample): constant to rounding


def masked_fit_percent(y, y_sim, valid):
    """`fit_percent` (traced) of the first `valid` samples of y and y_sim (a padded window;
    all of them for `valid` = len(y)); NaN for a y that is constant, also to rounding (its
    mean's rounding left a spread of 1e-14 at a level of 97, and fits of -1e16 %)."""
    keep = jnp.arange(y.shape[0]) < valid
    mean = jnp.sum(jnp.where(keep, y, 0.0)) / valid
    spread = jnp.linalg.norm(jnp.where(keep, y - mean, 0.0))
    miss = jnp.linalg.norm(jnp.where(keep, y - y_sim, 0.0))
    level = jnp.max(jnp.where(keep, jnp.abs(y), 0.0))
    moves = spread > CONSTANT_RTOL * level * jnp.sqrt(jnp.asarray(valid, jnp.float64))
    return 100.0 * (1.0 - miss / jnp.where(moves, spread, jnp.nan))


def fit_percent(y, y_sim):
    """NRMSE fit as MATLAB's `compare`: 100 (1 - ||y - y_sim|| / ||y - mean(y)||)."""
    traced = _b.is_traced(y) or _b.is_traced(y_sim)
    if not traced:
        require_x64("fit_percent")
        y = _b.array("fit_percent", "y", y, ndim=1)
        y_sim = _b.array("fit_percent", "y_sim", y_sim, ndim=1, finite=False)
        if y_sim.size and not np.all(np.isfinite(y_sim)):
            raise ValueError(f"fit_percent(): y_sim has a NaN or inf at sample "
                             f"{int(np.argmin(np.isfinite(y_sim)))}: the simulation did not stay "
                             "finite (an unstable or diverged model?); its fit is undefined")
        if y.shape != y_sim.shape or y.size < 2:
            raise ValueError(f"fit_percent(): y and y_sim must be 1-D of equal length >= 2 "
                             f"(got shapes {y.shape} and {y_sim.shape})")
        if not np.any(y != y[0]):
            raise ValueError("fit_percent(): the fit of a constant output y is undefined "
                             "(||y - mean(y)|| = 0); compare E or the mean square error instead")
        scale = max(float(np.max(np.abs(y))), float(np.max(np.abs(y_sim))), 1e-300)
        y, y_sim = y / scale, y_sim / scale  # the norms below cannot overflow
        spread = float(np.linalg.norm(y - np.mean(y)))
        if not spread > 0:
            raise ValueError("fit_percent(): the fit of an output y that is constant to float64 "
                             "precision is undefined; compare E or the mean square error instead")
        return jax.device_put(np.float64(100.0 * (1.0 - float(np.linalg.norm(y - y_sim))
                                                  / spread)))  # no eager program
    y, y_sim = jnp.asarray(y), jnp.asarray(y_sim)
    return masked_fit_percent(y, y_sim, y.shape[0])  # a constant y: fit undefined, NaN
