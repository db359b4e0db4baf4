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

import equinox as eqx
import jax
import jax.numpy as jnp

from ._linalg import expm
from ._model import Model
from ._quadrature import delayed_samples, shift_samples, split_delay
from ._statespace import state_space
from ._status import Status

_BIG = 1e150  # state magnitude treated as overflow (unstable model on a long window)


def _gammas(A, b, delta):
    """e^{A delta}, Gamma_0 b, Gamma_1 b for one input column b (augmented expm)."""
    n = A.shape[0]
    aug = jnp.zeros((n + 2, n + 2))
    aug = aug.at[:n, :n].set(A).at[:n, n].set(b).at[n, n + 1].set(1.0)
    E = expm(aug * delta)
    return E[:n, :n], E[:n, n], E[:n, n + 1]


def _input_terms(A, b, mode: str, frac, dt: float):
    """(P, Q, R) vectors (n,) of one input for fractional delay `frac` in [0, 1)."""
    d1, d2 = frac * dt, (1.0 - frac) * dt
    _, g0a, g1a = _gammas(A, b, d1)
    E2, g0b, g1b = _gammas(A, b, d2)
    if mode == "zoh":
        return E2 @ g0a, g0b, jnp.zeros_like(b)
    P = E2 @ (frac * g0a - g1a / dt)
    Q = E2 @ ((1.0 - frac) * g0a + g1a / dt) + g0b - g1b / dt
    R = g1b / dt
    return P, Q, R


def _forced(model: Model, u, dt: float):
    """Per-step drive (T, n) and direct term (T,) of all inputs (offset included)."""
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
    drive, direct = forced_terms(ss, cols, modes, delays, dt, T)
    return ss, drive, direct


def forced_terms(ss, cols, modes, delays, dt: float, T: int):
    """Per-step drive (T, n) and direct term (T,) of input columns through (A, B, D)."""
    drive = jnp.zeros((T, ss.A.shape[0]))
    direct = jnp.zeros(T)
    for k, (x, mode, tau) in enumerate(zip(cols, modes, delays)):
        d, f = split_delay(tau, dt)
        P, Q, R = _input_terms(ss.A, ss.B[:, k], mode, f, dt)
        um1, u0, up1 = shift_samples(x, d + 1), shift_samples(x, d), shift_samples(x, d - 1)
        drive = drive + um1[:, None] * P + u0[:, None] * Q + up1[:, None] * R
        direct = direct + ss.D[0, k] * delayed_samples(x, tau, dt, mode)
    return drive, direct


def simulate_status(model: Model, u, x0, dt: float):
    """Batched-path simulation: returns (y (T,), x (T, n), status) and never raises.

    An overflowing (unstable) response is frozen at its last finite state and flagged
    `Status.OVERFLOW` instead of turning into inf/NaN.
    """
    u = jnp.asarray(u, dtype=jnp.float64).reshape(jnp.shape(u)[0], -1)
    ss, drive, direct = _forced(model, u, dt)
    Phi = expm(ss.A * dt)

    def step(carry, dr):
        x, bad = carry
        x_new = Phi @ x + dr
        blown = bad | ~jnp.all(jnp.abs(x_new) < _BIG)
        x_new = jnp.where(blown, x, x_new)
        return (x_new, blown), x

    (_, bad), xs = jax.lax.scan(step, (jnp.asarray(x0, dtype=jnp.float64), False), drive)
    y = xs @ ss.C[0] + direct
    return y, xs, jnp.where(bad, Status.OVERFLOW, 0).astype(jnp.int32)


def simulate(model: Model, u, x0=None, *, dt: float, return_state: bool = False):
    r"""Exact response of `model` to sampled inputs `u` (T, K) from state `x0` at the first sample.

    Each input follows the model's intersample mode (zoh/foh) and delay exactly (see module).
    `x0` defaults to zeros (state of eq. 18). Jit/vmap/grad friendly (over models, `u`, `x0`).
    Raises (also under jit, via `eqx.error_if`) if the response overflows float64.

    **Returns:** y (T,), or (y, x) with the states (T, n) when `return_state`.
    """
    u = jnp.asarray(u, dtype=jnp.float64)
    if u.ndim == 1:
        u = u[:, None]
    K = model.n_inputs
    if u.ndim != 2 or u.shape[1] != K:
        raise ValueError(f"simulate(): u must have shape (T, {K}) for this model, got {u.shape}")
    if x0 is None:
        x0 = jnp.zeros(model.n)
    x0 = jnp.asarray(x0, dtype=jnp.float64)
    if x0.shape != (model.n,):
        raise ValueError(f"simulate(): x0 must have shape ({model.n},), got {x0.shape}")
    if not dt > 0:
        raise ValueError(f"simulate(): dt must be > 0 (got {dt})")
    y, xs, status = simulate_status(model, u, x0, float(dt))
    y = eqx.error_if(
        y, status != 0, "simulate(): the response overflows float64 (unstable model)"
    )
    return (y, xs) if return_state else y
