r"""Exact simulation of a model from sampled inputs (zoh / foh, fractional delays), `lax.scan`.

Each input's interpolant is honoured exactly: over a sampling step the delayed input
$u_k(t - \tau_k)$, $\tau_k = (d_k + f_k)\,dt$, is piecewise constant (zoh) or piecewise linear
(foh) with one break at $f_k\,dt$, so the step map is
$x_{j+1} = \Phi x_j + \sum_k P_k u_{k,j-d_k-1} + Q_k u_{k,j-d_k} + R_k u_{k,j-d_k+1}$ with
$P, Q, R$ from the matrix exponential of the augmented matrix
$\begin{bmatrix} A & B & 0\\ 0 & 0 & 1\\ 0 & 0 & 0\end{bmatrix}\delta$, whose top row holds
$e^{A\delta}$, $\Gamma_0 = \int_0^\delta e^{As}ds\,B$, $\Gamma_1 = \int_0^\delta e^{As}(\delta-s)ds\,B$.
Inputs before the first sample are held at the first sample's value.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from . import _boundary as _b
from ._boundary import require_x64
from ._jit import jit
from ._linalg import EXPM_RANGE, balance, expm, small_matmul
from ._model import Model, simulation_form
from ._quadrature import delayed_samples, edge_padded, record_bucket, shift_samples, split_delay
from ._signals import Signals
from ._statespace import state_space
from ._status import Status

_BIG = 1e150  # state magnitude treated as overflow (unstable model on a long window)


def step_terms(A, B, modes, fracs, dt: float):
    """Phi = e^{A dt} and per input column b_k of `B` (n, S) its (P, Q, R) vectors (n,) for
    fractional delay `fracs[k]` in [0, 1), from one batched expm of the 2S + 1 augmented
    matrices (module docstring; A alone for Phi). One expm per matrix made a larger program:
    `output_error` compiled in 1.50 s against 1.10 s and ran 66-71 ms against 46 ms warm."""
    n, S = A.shape[0], len(modes)
    # one balancing of the state for all (`balance`; B's column weighs in, the input
    # generator's states keep scale 1): a stiff model's canonical form took 47 squarings and
    # erred by 1e-7
    ds = balance(jnp.zeros((n + 1, n + 1)).at[:n, :n].set(A).at[:n, n].set(
        jnp.sum(jnp.abs(B), axis=1)))[:n]
    aug = jnp.zeros((S + 1, n + 2, n + 2)).at[:, :n, :n].set(A * ds[None, :] / ds[:, None])
    aug = aug.at[:S, :n, n].set(B.T / ds).at[:S, n, n + 1].set(1.0)  # the last: Phi's
    f = jnp.stack(fracs).astype(jnp.float64) if S else jnp.zeros(0)
    deltas = jnp.concatenate([f * dt, (1.0 - f) * dt, jnp.full(1, dt)])
    E = jax.vmap(expm)(jnp.concatenate([aug[:S], aug[:S], aug[S:]]) * deltas[:, None, None])
    # rows :n of the unbalanced matrices' exponentials (the rows used below)
    E = E.at[:, :n, :].multiply(ds[None, :, None]).at[:, :, :n].divide(ds[None, None, :])
    E2, g0, g1 = E[S : 2 * S, :n, :n], E[:, :n, n], E[:, :n, n + 1]
    terms = []
    for k, mode in enumerate(modes):
        g0a, g1a, g0b, g1b = g0[k], g1[k], g0[S + k], g1[S + k]
        if mode == "zoh":
            terms.append((E2[k] @ g0a, g0b, jnp.zeros(n)))
            continue
        terms.append((E2[k] @ (f[k] * g0a - g1a / dt),
                      E2[k] @ ((1.0 - f[k]) * g0a + g1a / dt) + g0b - g1b / dt, g1b / dt))
    return E[-1, :n, :n], terms


def forced_response(model: Model, u, dt: float):
    """(ss, Phi, drive (T, n), direct (T,)) of all inputs (offset included)."""
    ss = state_space(model)
    T = u.shape[0]
    K = model.n_inputs
    cols = [u[:, k] for k in range(K)]
    modes = list(model.intersample)
    delays = [model.delays[k] for k in range(K)]
    if model.has_offset:
        cols.append(jnp.ones(T))
        modes.append("zoh")
        delays.append(jnp.asarray(0.0))
    Phi, drive, direct = forced_terms(ss, cols, modes, delays, dt, T)
    # a negative or non-finite delay (a model edited by hand) is no dead time: it read
    # future samples; NaN (traced; eager calls refuse it, `_boundary.model_delays`)
    ok = delays_valid(model)
    return ss, Phi, jnp.where(ok, drive, jnp.nan), jnp.where(ok, direct, jnp.nan)


def delays_valid(model: Model):
    """The model's delays are dead times: finite and >= 0 (a traced bool)."""
    d = jnp.asarray(model.delays, jnp.float64)
    return jnp.all(jnp.isfinite(d) & (d >= 0))


def forced_terms(ss, cols, modes, delays, dt: float, T: int, rows=None):
    """Phi = e^{A dt}, the per-step drive (T, n) and the direct term (T,) of input columns
    through (A, B, D); with `rows` (sample indices, may be traced) only those steps, exactly
    as in the whole record."""
    L = T if rows is None else rows.shape[0]
    drive = jnp.zeros((L, ss.A.shape[0]))
    direct = jnp.zeros(L)
    split = [split_delay(tau, dt) for tau in delays]
    Phi, terms = step_terms(ss.A, ss.B[:, : len(cols)], modes, [f for _, f in split], dt)
    for k, (x, mode, tau) in enumerate(zip(cols, modes, delays)):
        d, (P, Q, R) = split[k][0], terms[k]
        um1, u0, up1 = (shift_samples(x, d + i, rows) for i in (1, 0, -1))
        drive = drive + um1[:, None] * P + u0[:, None] * Q + up1[:, None] * R
        direct = direct + ss.D[0, k] * delayed_samples(x, tau, dt, mode, rows)
    return Phi, drive, direct


def simulate_status(model: Model, u, x0, dt: float, valid=None):
    """Batched-path simulation: returns (y (T,), x (T, n), status) and never raises.

    An overflowing (unstable) response is frozen at its last finite state and flagged
    `Status.OVERFLOW` instead of turning into inf/NaN. `valid` (may be traced): only the first
    `valid` samples count for that flag (`u` padded beyond them, see `simulate`).
    """
    u = jnp.asarray(u, dtype=jnp.float64).reshape(jnp.shape(u)[0], -1)
    ss, Phi, drive, direct = forced_response(model, u, dt)
    inside = jnp.arange(u.shape[0]) < (u.shape[0] if valid is None else valid)

    def step(carry, d):
        (x, bad), (dr, counts) = carry, d
        x_new = small_matmul(Phi, x) + dr
        blown = bad | (counts & ~jnp.all(jnp.abs(x_new) < _BIG))
        x_new = jnp.where(blown, x, x_new)
        return (x_new, blown), x

    (_, bad), xs = jax.lax.scan(step, (jnp.asarray(x0, dtype=jnp.float64), False),
                                (drive, inside))
    y = xs @ ss.C[0] + direct
    status = jnp.where(bad, Status.OVERFLOW, 0) | jnp.where(delays_valid(model), 0,
                                                              Status.OUT_OF_BOUNDS)
    return y, xs, status.astype(jnp.int32)


def simulate(model: Model, u, x0=None, *, dt: float, return_state: bool = False):
    r"""Exact response of `model` to sampled inputs `u` (T, K) from state `x0` at the first sample.

    Each input follows the model's intersample mode (zoh/foh) and delay exactly (see module).
    `x0` defaults to zeros (state of eq. 18). Jit/vmap/grad friendly (over models, `u`, `x0`).
    Non-finite `u` or `x0` raise a ValueError; so does a response that leaves the float64 range
    (an unstable model, or inputs too large), with the model's unstable poles named. Under an
    outer jit/vmap nothing can raise: an overflowing response comes back as NaN.

    **Returns:** y (T,), or (y, x) with the states (T, n) when `return_state`.
    """
    require_x64("simulate")
    if not isinstance(model, Model):
        hint = _b.swap_hint("simulate", model) or (
            "; arguments swapped? the order is simulate(model, u, ...)"
            if isinstance(u, Model) else "")
        raise TypeError(f"simulate(): model must be a Model, got {type(model).__name__}{hint}")
    K = model.n_inputs
    _b.model_delays("simulate", model)
    if isinstance(u, Signals):
        raise TypeError("simulate(): u must be the inputs (T, K), got a Signals: pass "
                        "signals.u, or use observe(model, signals) / compare(model, signals) "
                        "to simulate from the observed initial state")
    u = _b.array("simulate", "u", u, ndim=(1, 2))
    u = (jnp if _b.is_traced(u) else np).asarray(u, dtype=np.float64)  # NumPy: no program
    given = u.shape  # as the caller passed it, for the message
    if u.ndim == 1:
        u = u[:, None]
    if u.shape[1] != K or u.shape[0] < 1:
        raise ValueError(
            f"simulate(): u must have shape (T, {K}) for this model (time-major, one column per "
            f"input), got {given}" + ("; transpose it (u.T)" if u.shape[0] == K else "")
        )
    if x0 is None:
        x0 = np.zeros(model.n)
    x0 = _b.array("simulate", "x0", x0)
    x0 = (jnp if _b.is_traced(x0) else np).asarray(x0, dtype=np.float64)  # NumPy: no program
    if x0.shape != (model.n,):
        raise ValueError(f"simulate(): x0 must have shape ({model.n},), got {x0.shape}")
    dt = np.float64(_b.number("simulate", "dt", dt, lo=0, lo_open=True,  # a value: no program
                              fix="give the sampling interval"))          # per dt
    # a concrete u is padded to its record bucket: records of every length in it share one
    # program; the response is causal, so the first T samples never see the padding
    T = u.shape[0]
    if _b.is_traced(u):
        args = (u, x0, dt)
    else:
        args = (edge_padded(u, record_bucket(T) - T), x0, dt, np.int32(T))
    # one program per order n (`simulation_form`), whatever the numerator orders
    y, xs, status = _simulate(simulation_form(model), *args)
    if _b.is_traced(status) or _b.is_traced(y):
        # no eqx.error_if here: a program holding one is never written to the persistent
        # compilation cache; the overflow shows as NaN instead of a frozen response
        y, xs = y[:T], xs[:T]
        y = jnp.where(status != 0, jnp.nan, y)
        return (y, xs) if return_state else y
    y = np.asarray(y)[:T]  # host slices (no program); the states only when asked for
    if int(status) != 0 or not np.all(np.isfinite(y)):
        raise ValueError(_overflow_message(model, u, x0, float(dt)))
    y = jax.device_put(y)
    return (y, jax.device_put(np.asarray(xs)[:T])) if return_state else y


_simulate = jit(simulate_status)  # one cacheable program per order and record bucket


def _overflow_message(model: Model, u, x0, dt: float) -> str:
    """Why a concrete simulation left the float64 range: unstable poles, a pole too fast for
    the matrix exponential's squarings at this dt, or huge inputs."""
    a = np.asarray(model.a, dtype=np.float64)
    poles = np.roots(a[::-1]) if np.all(np.isfinite(a)) else np.array([np.nan])
    bad = poles[~(poles.real <= 0)]
    if bad.size:
        listed = ", ".join(f"{p.real:.4g}{p.imag:+.4g}j" if p.imag else f"{p.real:.4g}"
                           for p in bad)
        return (f"simulate(): the response overflows float64 because the model is unstable "
                f"(poles with positive real part: {listed}); simulate a shorter record or "
                "use a stable model")
    fastest = float(np.max(np.abs(poles)) * dt) if poles.size else 0.0
    if fastest > EXPM_RANGE:  # (a = [1e16, 1] at dt = 1: "rescale the inputs",
        # which could not help)
        return (f"simulate(): a pole of magnitude {fastest / dt:.3g} at dt = {dt:g} (|p| dt = "
                f"{fastest:.3g}) is beyond the matrix exponential's range (|p| dt up to "
                f"{EXPM_RANGE:.3g}); such a mode settles within a tiny fraction "
                "of a sample: leave it out of the model (keep its static gain)")
    scale = max(float(np.max(np.abs(u), initial=0.0)), float(np.max(np.abs(x0), initial=0.0)))
    return (f"simulate(): the response overflows float64 (largest |u| or |x0| = {scale:.3g}; "
            f"states above {_BIG:g} count as overflow); rescale the inputs")
