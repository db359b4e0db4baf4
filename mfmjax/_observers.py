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

import equinox as eqx
import jax
import jax.numpy as jnp
from jax.scipy.linalg import expm

from ._model import Model
from ._quadrature import gregory_weights
from ._signals import Signals
from ._simulate import _forced
from ._status import Status

UNOBSERVABLE_COND = 1e13  # cond of the equilibrated Gramian above this: flagged


class Observation(eqx.Module):
    """Result of the observers on one window (batched paths read `status`, never raise)."""

    x_initial: jax.Array  # state at the window start (eq. 14)
    x_final: jax.Array  # state at the window end (eq. 15)
    y_sim: jax.Array  # (W,) simulated output on the window from x_initial
    E: jax.Array  # performance index (eq. 17) on the window
    cond: jax.Array  # cond of the equilibrated observability Gramian M0
    status: jax.Array


def observe_window(model: Model, y, u, dt: float, start, length: int) -> Observation:
    """Observers + E on samples `start .. start+length-1` of a record (y (T,), u (T, K)).

    `length` is static, `start` may be traced (moving windows, eq. 16). Inputs before `start`
    are taken from the record (delays see the real history).
    """
    ss, drive, direct = _forced(model, u, dt)
    n = model.n
    Phi = expm(ss.A * dt)
    dr = jax.lax.dynamic_slice_in_dim(drive, start, length)
    di = jax.lax.dynamic_slice_in_dim(direct, start, length)
    yw = jax.lax.dynamic_slice_in_dim(y, start, length)

    def step(carry, d):  # forced response from rest and the free-response rows C e^{A t_j}
        x, row = carry
        return (Phi @ x + d, row @ Phi), (ss.C[0] @ x, row)

    _, (y_f, rows) = jax.lax.scan(step, (jnp.zeros(n), ss.C[0]), dr)
    y_forced = y_f + di
    q = gregory_weights(length, 0, dt)
    M0 = rows.T @ (q[:, None] * rows)  # observability Gramian over the window
    rhs = rows.T @ (q * (yw - y_forced))
    d = 1.0 / jnp.sqrt(jnp.where(jnp.diagonal(M0) > 0, jnp.diagonal(M0), 1.0))
    Me = d[:, None] * M0 * d[None, :]
    x0 = d * jnp.linalg.solve(Me, d * rhs)
    lam = jnp.linalg.eigvalsh(Me)
    cond = lam[-1] / jnp.maximum(lam[0], lam[-1] * jnp.finfo(jnp.float64).eps)

    def traj(x, d):
        return Phi @ x + d, x

    _, xs = jax.lax.scan(traj, x0, dr)
    y_sim = xs @ ss.C[0] + di
    E = jnp.sum(q * (yw - y_sim) ** 2)
    x_final = xs[-1]
    status = jnp.where(cond > UNOBSERVABLE_COND, Status.UNOBSERVABLE, 0)
    status = status | jnp.where(jnp.all(jnp.isfinite(x0)) & jnp.isfinite(E), 0, Status.NONFINITE)
    return Observation(x0, x_final, y_sim, E, cond, status.astype(jnp.int32))
