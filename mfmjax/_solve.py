r"""Constrained minimisation of $\theta^T G \theta$ subject to $\eta^T\theta = 1$ (eq. 11-12)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from . import _linalg
from ._boundary import require_x64
from ._jit import jit
from ._status import Status

DEAD_COLUMN_RTOL = 1e-10  # column norm below this fraction of its bound: no excitation, masked
A_N_RTOL = 1e-12  # |a_n| below this fraction of max |a_i| (each times its Gram column's norm,
# i.e. the equilibrated parameters, which do not depend on the time unit): a_n vanished
ILL_CONDITIONED = 1e12  # lambda_max / lambda_2 of the equilibrated G above this: flagged
_EPS = jnp.finfo(jnp.float64).eps


def check_gram(fn: str, G, eta, active=None) -> None:
    """Concrete arguments of the public solves: a Gram matrix (finite, symmetric, a
    non-negative diagonal) and a constraint that some active column carries (else eq. (11)
    has no solution). Traced ones are not checked (their result is NaN where it fails)."""
    from ._boundary import is_traced

    if any(is_traced(x) for x in (G, eta, active)):
        return
    G, eta = np.asarray(G, np.float64), np.asarray(eta, np.float64)
    on = np.ones(eta.shape, bool) if active is None else np.asarray(active, bool)
    if G.shape[0] == 0:
        raise ValueError(f"{fn}(): G is empty (0 parameters); give the Gram of at least one "
                         "column")
    if not (np.all(np.isfinite(G)) and np.all(np.isfinite(eta))):
        raise ValueError(f"{fn}(): G and eta must be finite (a non-finite Gram comes from "
                         "non-finite data)")
    scale = np.max(np.abs(G))
    if np.max(np.abs(G - G.T)) > 1e-8 * scale or np.any(np.diagonal(G) < 0):
        raise ValueError(f"{fn}(): G must be a Gram matrix (symmetric, positive semidefinite: "
                         "no negative diagonal entry); give gram(modulated_signals(...))")
    if not np.any(on & (eta != 0)):
        raise ValueError(f"{fn}(): eta is zero on every active column, so eta^T theta = 1 "
                         "(eq. 11) has no solution; give eta with nonzero entries (default "
                         "ones)")


def _finite_result(fn: str, theta, why: str) -> None:
    from ._boundary import is_traced

    if not is_traced(theta):
        if not np.all(np.isfinite(np.asarray(theta))):
            raise ValueError(f"{fn}(): no finite solution: {why}")


def closed_form(G, eta):
    r"""The paper's eq. (12): $\theta^0 = G^{-1}\eta / (\eta^T G^{-1} \eta)$. Reference only.

    Fails when G is singular, which it is on noise-free data in exact arithmetic: eager calls
    raise then, traced ones return inf/NaN.
    """
    require_x64("closed_form")
    G, eta = jnp.asarray(G, jnp.float64), jnp.asarray(eta, jnp.float64)  # float32 in: float64 out
    if G.ndim != 2 or G.shape[0] != G.shape[1] or eta.shape != G.shape[:1]:
        raise ValueError(f"closed_form(): G must be square (p, p) and eta (p,); got G "
                         f"{G.shape} and eta {eta.shape}")
    check_gram("closed_form", G, eta)
    g = jnp.linalg.solve(G, eta)
    theta = g / (eta @ g)
    _finite_result("closed_form", theta, "G is singular (as on noise-free data) or eta^T "
                   "G^-1 eta = 0; eq. (12) needs an invertible G: use constrained_solve")
    return theta


def _solve_shapes(G, eta, active) -> None:
    G, eta, active = (jnp.shape(x) for x in (G, eta, active))
    if len(G) != 2 or G[0] != G[1] or eta != G[:1] or active != G[:1]:
        raise ValueError(f"constrained_solve(): G must be square (p, p), eta and active (p,); "
                         f"got G {G}, eta {eta} and active {active}")


def constrained_solve(G, eta, active, conditioning: bool = True):
    r"""Production solve of eq. (11): equilibrated KKT system, well defined for singular G.

    With $D = \mathrm{diag}(G)^{-1/2}$ on the active columns, $\tilde G = D G D$ and
    $e = D\eta$ (scaled to unit norm), solve
    $\begin{bmatrix}\tilde G & e\\ e^T & 0\end{bmatrix}
     \begin{bmatrix}\tilde\theta\\ \lambda\end{bmatrix} = \begin{bmatrix}0\\ 1/\|e\|\end{bmatrix}$,
    $\theta = D\tilde\theta$. This is the same minimiser as eq. (12) whenever G is invertible, and
    stays unique while $G$ is positive definite on $\{\eta^T\theta = 0\}$. Inactive (masked)
    columns get $\theta_j = 0$. Pure XLA linear algebra (`_linalg`): safe under `vmap`.

    **Returns:** `(theta, cond, reduced_cond)`: `cond` is cond of the equilibrated active block
    (capped at 1/eps), `reduced_cond` is $\lambda_{max}/\lambda_2$, the conditioning of the
    constrained problem; both to relative accuracy 1e-4 (`conditioning_eigvals`).
    """
    require_x64("constrained_solve")
    G, eta, active = (jnp.asarray(G, jnp.float64), jnp.asarray(eta, jnp.float64),
                      jnp.asarray(active, dtype=bool))
    _solve_shapes(G, eta, active)
    p = G.shape[0]
    diag = jnp.diagonal(G)
    d = jnp.where(active & (diag > 0), 1.0 / jnp.sqrt(jnp.where(diag > 0, diag, 1.0)), 1.0)
    Gt = d[:, None] * G * d[None, :]
    mask2 = active[:, None] & active[None, :]
    Gt = jnp.where(mask2, Gt, jnp.where(jnp.eye(p, dtype=bool), 1.0, 0.0))
    e = jnp.where(active, d * eta, 0.0)
    s = jnp.linalg.norm(e)
    s = jnp.where(s > 0, s, 1.0)
    kkt = jnp.block([[Gt, (e / s)[:, None]], [(e / s)[None, :], jnp.zeros((1, 1))]])
    rhs = jnp.zeros(p + 1).at[p].set(1.0 / s)
    sol = _linalg.solve(kkt, rhs)
    theta = jnp.where(active, d * sol[:p], 0.0)
    if not conditioning:  # inner fixed-point steps need theta only
        return theta, None, None
    n_off = p - jnp.sum(active)  # inactive columns give that many zero eigenvalues first
    which = jnp.stack([jnp.clip(n_off, 0, p - 1), jnp.clip(n_off + 1, 0, p - 1), p - 1])
    lam = _linalg.conditioning_eigvals(jnp.where(mask2, Gt, 0.0), which)
    lmax = lam[2]
    lmin = jnp.maximum(lam[0], lmax * _EPS)
    l2 = jnp.maximum(lam[1], lmax * _EPS)
    return theta, lmax / lmin, lmax / l2


def solve_status(theta, reduced_cond, finite_data):
    """Status bits of a solve (see `Status`)."""
    status = jnp.where(finite_data & jnp.all(jnp.isfinite(theta)), 0, Status.NONFINITE)
    return status | jnp.where(reduced_cond > ILL_CONDITIONED, Status.ILL_CONDITIONED, 0)


def default_eta(p: int, offset: bool):
    r"""The constraint vector of eq. (11) by default: ones (the paper's choice) on a and b, and
    0 on the offset term when there is one. The offset's raw value carries the signals' levels
    (it is $c + a_0 L_y - \sum_k b_{k0} L_k$ for levels L), so a 1 there made the estimate
    depend on them on noisy data: at a level of 1e4 (noise 1 % of the spread) a and b moved by
    27 % (status ok) and search rankings changed already at 1e2. With 0 there only the offset
    moves with the levels. The on-line identifier's paper mode keeps the paper's ones."""
    eta = np.ones(p)
    if offset:
        eta[-1] = 0.0
    return eta


def centred_eta(eta, levels):
    r"""The constraint of eq. (11) on the centred parameters (`level_vector`): $\eta^T\theta =
    \eta'^T\theta'$ with $\eta' = \eta - \eta_{off}\,l$, so the centred solve is the same
    minimiser (noisy data included)."""
    return eta - eta[-1] * levels


def uncentred(theta, levels):
    r"""The signals' own parameters from the centred solve's: $\theta_{off} = \theta_{off}' -
    l^T\theta'$ (`level_vector`)."""
    return theta.at[-1].add(-(levels @ theta))


def finish_solve(theta, G, reduced_cond, n, data_ok, excited, n_max: int | None = None,
                 levels=None):
    r"""The post-solve step shared by `identify` and `search` (one candidate of order `n`).

    Status bits of the solve (`solve_status`), `NO_EXCITATION` unless `excited`, `A_N_ZERO`
    when $|a_n| g_n \le 10^{-12} \max_i |a_i| g_i$ ($g_i = G_{ii}^{1/2}$: the equilibrated
    parameters, free of the time unit); the divisor that normalises $a_n = 1$ (1 when
    $a_n$ vanished); the quadratic form $\theta^T G \theta$ of eq. (8) and the scale-free
    $J_{rel} = (\theta^T G\theta / \sum_i \theta_i^2 G_{ii})^{1/2}$.

    `n` is a static int in the compact layout (a_0..a_n first); in the padded layout of the
    search (a block a_0..a_{n_max}, zero beyond the candidate's order) it may be traced, with
    `n_max` the static block size. `levels` (`level_vector`): G is the Gram of the centred
    signals and `theta` in the signals' own parameters (`uncentred`): the quadratic form is
    the signals' own, J_rel that of the centred columns (independent of the levels).

    **Returns:** `(status, divisor, quad, J_rel)`.
    """
    status = solve_status(theta, reduced_cond, data_ok)
    status = status | jnp.where(excited, 0, Status.NO_EXCITATION)
    an = theta[n]
    a_len = n + 1 if n_max is None else n_max + 1
    # on the equilibrated parameters (theta_i sqrt(G_ii)): the raw a_i scale as (time unit)^-i,
    # and a plant with four poles near 1e3 rad/s written in seconds (a_0 = 4e12 against
    # a_4 = 1) had every n = 4 candidate flagged, in milliseconds none
    norms = jnp.sqrt(jnp.maximum(jnp.diagonal(G)[:a_len], 0.0))
    an_ok = jnp.abs(an) * norms[n] > A_N_RTOL * jnp.max(jnp.abs(theta[:a_len]) * norms)
    status = status | jnp.where(an_ok, 0, Status.A_N_ZERO)
    # with `levels`, G is the centred signals' Gram and theta' = P theta (P = I + e_off l^T,
    # the offset last) its parameters: theta' G theta' is the signals' own quadratic form, and
    # J_rel's terms are those of the centred columns, so J_rel does not depend on the levels
    # (with the raw columns it fell as 1 / level^2, and ranking by it depended on the level)
    centred = theta if levels is None else theta.at[-1].add(levels @ theta)
    quad = jnp.maximum(centred @ G @ centred, 0.0)
    terms = jnp.sum(centred**2 * jnp.diagonal(G))
    J_rel = jnp.sqrt(quad / jnp.where(terms > 0, terms, 1.0))
    return status, jnp.where(an_ok, an, 1.0), quad, J_rel



def public_constrained_solve(G, eta, active, conditioning: bool = True):
    """`constrained_solve` as one compiled program, its concrete arguments checked
    (`check_gram`) and a result that is not finite refused (eager; traced: NaN)."""
    require_x64("constrained_solve")
    _solve_shapes(G, eta, active)
    check_gram("constrained_solve", G, eta, active)
    out = _solve_program(G, eta, active, conditioning)
    _finite_result("constrained_solve", out[0], "G is zero (or not finite) on the active "
                   "columns; check the data and the mask")
    return out


public_constrained_solve.__doc__ = constrained_solve.__doc__  # the same contract and name
public_constrained_solve.__name__ = public_constrained_solve.__qualname__ = "constrained_solve"
_solve_program = jit(constrained_solve)  # one program (the eager loops were traced each call)
