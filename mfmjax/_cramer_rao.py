r"""The Cramer-Rao bound of the free parameters for white output noise."""

from __future__ import annotations

import warnings

import jax
import numpy as np

from ._jit import jit
from ._linalg import small_matmul
from ._model import Model, growing_poles
from ._output_error import (
    free_parameters,
    gauss_newton_covariance,
    order_parameters,
    with_parameters,
)
from ._quadrature import edge_padded, record_bucket
from ._simulate import forced_response


def cramer_rao(model: Model, u, x0, *, dt: float, sigma: float, length: int | None = None):
    r"""Cramer-Rao standard deviations of the free parameters of `model` (x0 unknown too) for white
    output noise of standard deviation `sigma`: $\sqrt{\mathrm{diag}(\sigma^2 (J^T J)^{-1})}$,
    $J = \partial y_{sim} / \partial(\theta, x_0)$ by `jax.jacfwd` of the exact simulation.
    Arguments in the order of `simulate(model, u, x0, dt=...)`: the experiment `u` (T, K) from
    state `x0`, sampled every `dt`; `length` limits it to the first samples.

    **Returns:** (names, std of the parameters).
    """
    from ._boundary import check_cramer_rao, eager_only

    eager_only("cramer_rao", model, u, x0, dt, sigma, length)
    check_cramer_rao(model, u, x0, dt, sigma, length)
    u = np.asarray(u, dtype=np.float64).reshape(np.shape(u)[0], -1)
    length = u.shape[0] if length is None else int(length)
    names, theta0 = free_parameters(model)
    # one program per order n: the sensitivities of every coefficient of the numerators of
    # order n, then the structure's own columns (and x0's)
    base, theta, live = order_parameters(model, theta0)
    v = np.concatenate([theta, np.asarray(x0, dtype=np.float64)])
    # the experiment's length is a value: u padded to its record bucket (the last sample held),
    # J over the bucket of `length`, its rows beyond `length` dropped here
    bound = record_bucket(length)
    u = edge_padded(u, max(record_bucket(u.shape[0]), bound) - u.shape[0])
    J = np.asarray(_sensitivities(base, jax.device_put(u), v, np.float64(dt), bound))[:length]
    J = J[:, np.concatenate([live, theta.size + np.arange(model.n)])]
    with np.errstate(over="ignore"):
        big = not (np.all(np.isfinite(J)) and np.all(np.isfinite(np.linalg.norm(J, axis=0))))
    if big:  # J^T J overflowed: every bound came back inf, read as "undetermined"
        raise ValueError(f"cramer_rao(): the sensitivities overflow float64 (|dy/dtheta| up "
                         f"to {np.nanmax(np.abs(J)):.3g}): u or x0 is too large for this model; "
                         "scale the experiment (the bounds scale with sigma / |u|)")
    # J / sigma: the bounds of an experiment scaled by c (u, sigma -> c u, c sigma) do not
    # change (sigma^2 of 1e-155 underflowed: every bound came back inf, read as undetermined)
    with np.errstate(over="ignore"):
        J = J / sigma
    if not np.all(np.isfinite(J)):  # (numpy's "SVD did not converge" came from the SVD)
        raise ValueError(f"cramer_rao(): sigma={sigma:.3g} is too small for these sensitivities "
                         f"(their ratio overflows float64): the bounds are below float64's "
                         "range; scale the experiment (the bounds scale with sigma / |u|)")
    std = np.sqrt(np.diag(gauss_newton_covariance(J, 1.0)))[: theta0.size]
    rate = float(np.max(growing_poles(model.a).real, initial=0.0))
    if not np.all(np.isfinite(std)) and rate > 0:
        warnings.warn(f"cramer_rao(): the model is unstable (growth rate {rate:.3g}): its "
                      f"sensitivities grow e^{rate * (length - 1) * dt:.0f}-fold over the "
                      "experiment and are numerically collinear, so the inf bounds do not mean "
                      f"undetermined parameters; give length= a few growth times (3 / rate = "
                      f"{round(3 / (rate * dt))} samples)", stacklevel=2)
    return names, std


@jit
def _sensitivities(model, u, v, dt, length: int):
    """J = d y_sim / d(theta, x0) at v = (free parameters, x0) over the first `length` samples:
    `jax.jacfwd` of the exact simulation, one compiled program (eager, it dispatched every
    operation on its own)."""
    p = v.shape[0] - model.n
    sim = simulated_output(model, u, dt, 0, length)
    return jax.jacfwd(lambda w: sim(w[:p], w[p:]))(v)


def simulated_output(model, u, dt, start, length):
    """y_sim (length,) of `model` from state x0 at sample `start`: (theta, x0) -> output."""
    def f(theta, x0):
        m = with_parameters(model, theta)
        ss, Phi, drive, direct = forced_response(m, u, dt)
        dr = jax.lax.dynamic_slice_in_dim(drive, start, length)
        di = jax.lax.dynamic_slice_in_dim(direct, start, length)

        def step(x, d):
            return small_matmul(Phi, x) + d, small_matmul(ss.C, x)[0]

        _, ys = jax.lax.scan(step, x0, dr)
        return ys + di
    return f
