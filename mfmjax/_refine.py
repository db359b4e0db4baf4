r"""Differentiable scores, hyperparameter refinement and output-error estimation.

- `scores`: J, J_rel (eq. 8), E (eq. 17) and fit of the MFM estimate as smooth functions of the
  modulating-function settings h, N, M (real N, M >= n), the delays, eta and the data: jax.grad
  and jax.jacfwd work through the whole chain (weights, Gram, KKT solve, observer, simulation).
  The cubic output rule switches its one-sided stencil where tau + h crosses a sample, so the
  weights, hence the scores, have O(dt^4) kinks there: derivatives are exact between them.
- `refine`: minimises log E (or log J_rel) over (h, N, M, delays) with `optimistix.BFGS`; every
  setting is a smooth map of an unconstrained variable into its box, so bounds always hold.
- `output_error`: from the MFM estimate (the closed form stays the initialiser and reference),
  minimises the simulation residual over the parameters and the initial state with
  `optimistix.LevenbergMarquardt` through the exact simulation; returns the Gauss-Newton
  covariance $\sigma^2 (J^T J)^{-1}$ and standard errors. `cramer_rao` gives the bound for
  white output noise from `jax.jacfwd` of the simulation.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from ._identify import _identify
from ._linalg import expm
from ._model import Model
from ._modulating import ModulatingFunction
from ._observers import _observe_forced, fit_percent, validation_window
from ._signals import Signals
from ._simulate import _forced
from ._structure import Structure

SETTINGS = ("h", "N", "M", "delays")
MAX_EXPONENT = 12.0  # default upper bound of N and M in refine
USABLE = ("successful", "max_steps_reached", "nonlinear_max_steps_reached")  # solver codes


def _scores(signals, structure, h, N, M, delays, eta, h_max, delay_max, v0, length, ob):
    sig = eqx.tree_at(lambda s: s.delays, signals, jnp.asarray(delays, dtype=jnp.float64))
    mf = ModulatingFunction(N, M, h, h_max=h_max)
    model = _identify(sig, structure, mf, eta, delay_max)
    obs = _observe_forced(_forced(model, sig.u, sig.dt), sig.y, sig.dt, v0, length, ob)
    yv = jax.lax.dynamic_slice_in_dim(sig.y, v0, length)
    out = {"J": model.J, "J_rel": model.J_rel, "E": obs.E, "fit": fit_percent(yv, obs.y_sim),
           "status": model.status | obs.status}
    return out, model


def scores(
    signals: Signals, structure: Structure, *, h, N, M, delays=None, eta=None, validate=None,
    observer_window=None, h_max: float | None = None, delay_max: float | None = None,
) -> dict:
    r"""J, J_rel (eq. 8), E (eq. 17) and fit % of the MFM estimate for one setting, as
    differentiable functions of `h`, `N`, `M` (real, >= n), `delays`, `eta` and the data.

    E and fit are on the `validate` window (default: the record) with the state from the
    initial-state observer over `observer_window` (default: the window). Under jax.grad / jit
    give static bounds `h_max` and `delay_max` (they fix the kernel length).

    **Returns:** dict with `J`, `J_rel`, `E`, `fit`, `status`.
    """
    from ._boundary import check_scores

    check_scores(signals, structure, h=h, N=N, M=M, delays=delays, eta=eta, validate=validate,
                 observer_window=observer_window, h_max=h_max, delay_max=delay_max)
    structure = structure.for_inputs(signals.n_inputs)
    v0, length, ob = validation_window(signals, validate, observer_window, structure.n, "scores")
    p = structure.n_params + int(signals.offset)
    eta = jnp.ones(p) if eta is None else jnp.asarray(eta, dtype=jnp.float64)
    if eta.shape != (p,):
        raise ValueError(f"scores(): eta must have {p} entries, got shape {eta.shape}")
    delays = signals.delays if delays is None else jnp.asarray(delays, dtype=jnp.float64)
    if h_max is None:
        h_max = float(h)  # raises for a tracer: then h_max is required
    if delay_max is None:
        delay_max = float(np.max(np.asarray(delays), initial=0.0))
    return _scores_jit(signals, structure, h, N, M, delays, eta, float(h_max),
                       float(delay_max), v0, length, ob)[0]


_scores_jit = eqx.filter_jit(_scores)


# -- hyperparameter refinement ---------------------------------------------------------------


class Refinement(eqx.Module):
    """Result of `refine`: the refined model and settings, the score path and the solver code."""

    model: Model
    start: Model
    settings: dict
    start_settings: dict
    path: np.ndarray  # score after each accepted BFGS step (first entry: the start)
    result: str  # optimistix result name ("successful", "max_steps_reached", ...)
    steps: int
    score: str = eqx.field(static=True)

    @property
    def improved(self) -> bool:
        return bool(self.path[-1] < self.path[0])


def _logit(x, lo, hi):
    r = np.clip((np.asarray(x, dtype=np.float64) - lo) / (hi - lo), 1e-6, 1 - 1e-6)
    return np.log(r / (1 - r))


class _Objective(eqx.Module):
    """log score of the settings lo + (hi - lo) sigmoid(z) (a pytree: one compilation)."""

    signals: Signals
    x0: dict
    lo: dict
    hi: dict
    eta: jax.Array
    structure: Structure = eqx.field(static=True)
    vary: tuple = eqx.field(static=True)
    h_max: float = eqx.field(static=True)
    d_max: float = eqx.field(static=True)
    window: tuple = eqx.field(static=True)
    key: str = eqx.field(static=True)

    def settings(self, z):
        s = dict(self.x0)
        for k in self.vary:
            s[k] = self.lo[k] + (self.hi[k] - self.lo[k]) * jax.nn.sigmoid(z[k])
        return s

    def __call__(self, z, args):
        s = self.settings(z)
        out, _ = _scores(self.signals, self.structure, s["h"], s["N"], s["M"], s["delays"],
                         self.eta, self.h_max, self.d_max, *self.window)
        val = out[self.key]
        ok = jnp.isfinite(val) & (val > 0) & (out["status"] == 0)
        return jnp.where(ok, jnp.log(jnp.where(ok, val, 1.0)), jnp.inf), None


@eqx.filter_jit
def _value(fn, z):
    return fn(z, None)[0]


def refine(
    signals: Signals, start: Model, *, score: str = "E", vary=SETTINGS, bounds: dict | None = None,
    validate=None, observer_window=None, max_steps: int = 40, rtol: float = 1e-6,
    atol: float = 1e-8, top: int = 3,
) -> Refinement:
    r"""Refine the modulating-function settings (and delays) of `start` by gradient descent.

    Minimises $\log E$ (score "E", on `validate` with the initial-state observer, default) or
    $\log J_{rel}$ (score "J") with `optimistix.BFGS` over the settings named in `vary` (any of
    "h", "N", "M", "delays"). Default bounds: h in [h0/4, min(4 h0, record/3)], N and M in
    [n, 12], delays in [0, max(2 tau0, tau0 + 20 dt)] (and below record/4); `bounds` overrides
    any of them as {"h": (lo, hi), ...}. Every setting is a sigmoid of an unconstrained
    variable, so the iterates never leave the box.

    `start` may be a `SearchResult`: its best `top` candidates are refined and the refinement
    with the lowest score is returned. A refinement that fails (solver error, non-finite score,
    or no improvement) returns the starting model, with the solver's code in `result`.
    """
    from ._boundary import check_refine
    from ._search import SearchResult

    check_refine(signals, score=score, vary=vary, bounds=bounds, validate=validate,
                 observer_window=observer_window, max_steps=max_steps, rtol=rtol, atol=atol,
                 top=top)

    if isinstance(start, SearchResult):  # refine the best `top` candidates, keep the best
        if len(start) == 0:
            raise ValueError("refine(): the search result is empty")
        runs = [refine(signals, start.best(i), score=score, vary=vary, bounds=bounds,
                       validate=validate, observer_window=observer_window,
                       max_steps=max_steps, rtol=rtol, atol=atol)
                for i in range(min(top, len(start)))]
        return min(runs, key=lambda r: float(r.path.min()))
    if not isinstance(start, Model) or start.mf is None:
        raise TypeError("refine(): start must be a Model from identify or a SearchResult")
    if score not in ("E", "J"):
        raise ValueError(f"refine(): score must be 'E' or 'J' (got {score!r})")
    bad = sorted(set(vary) - set(SETTINGS))
    if bad or not vary:
        raise ValueError(f"refine(): vary must name some of {SETTINGS} (got {list(vary)})")
    K, n, dt = signals.n_inputs, start.n, signals.dt
    if "delays" in vary and K == 0:
        raise ValueError("refine(): no inputs, nothing to delay")
    duration = signals.duration
    h0, N0, M0 = float(start.mf.h), float(start.mf.N), float(start.mf.M)
    d0 = np.asarray(start.delays, dtype=np.float64).reshape(K)
    box = {
        "h": (h0 / 4, min(4 * h0, duration / 3)),
        "N": (float(n), MAX_EXPONENT), "M": (float(n), MAX_EXPONENT),
        "delays": (np.zeros(K), np.minimum(np.maximum(2 * d0, d0 + 20 * dt), duration / 4)),
    }
    for key, val in (bounds or {}).items():
        if key not in SETTINGS:
            raise ValueError(f"refine(): unknown bound {key!r}; use {SETTINGS}")
        box[key] = (np.asarray(val[0], dtype=np.float64), np.asarray(val[1], dtype=np.float64))
    x0 = {"h": h0, "N": N0, "M": M0, "delays": d0}
    for key in vary:
        lo, hi = box[key]
        if np.any(np.asarray(lo) >= np.asarray(hi)) or np.any(x0[key] < lo) or np.any(
                x0[key] > hi):
            raise ValueError(f"refine(): the start {key}={x0[key]} must lie in its bounds "
                             f"[{lo}, {hi}] with lo < hi")
    v0, length, ob = validation_window(signals, validate, observer_window, start.structure.n,
                                       "refine")
    p = start.structure.n_params + int(signals.offset)
    objective = _Objective(
        signals=signals, x0={k: jnp.asarray(v, dtype=jnp.float64) for k, v in x0.items()},
        lo={k: jnp.asarray(box[k][0], dtype=jnp.float64) for k in vary},
        hi={k: jnp.asarray(box[k][1], dtype=jnp.float64) for k in vary}, eta=jnp.ones(p),
        structure=start.structure, vary=tuple(vary),
        h_max=float(np.max(box["h"][1]) if "h" in vary else h0),
        d_max=float(np.max(box["delays"][1]) if "delays" in vary else np.max(d0, initial=0.0)),
        window=(v0, length, ob), key={"E": "E", "J": "J_rel"}[score],
    )
    z0 = {key: jnp.asarray(_logit(x0[key], *box[key])) for key in vary}
    solver = optx.BFGS(rtol=rtol, atol=atol)
    state = _bfgs_init(solver, objective, z0)
    z, path, result, steps = z0, [float(_value(objective, z0))], optx.RESULTS.successful, 0
    best_z, best_f = z0, path[0]
    for steps in range(1, max_steps + 1):
        z, state = _bfgs_step(solver, objective, z, state)
        f = float(_value(objective, z))  # the iterate (a line-search trial may be worse)
        path.append(f)
        if math.isfinite(f) and f < best_f:
            best_z, best_f = z, f
        done, result = _bfgs_terminate(solver, objective, z, state)
        if bool(done):
            break
    else:
        result = optx.RESULTS.max_steps_reached
    code = _result_name(result)
    s_start = {k: _plain(v) for k, v in x0.items()}
    if not math.isfinite(path[0]) or best_f >= path[0] or code not in USABLE:
        return Refinement(start, start, s_start, s_start, np.exp(np.asarray(path)), code, steps,
                          score)
    s = {k: _plain(v) for k, v in objective.settings(best_z).items()}
    sig = eqx.tree_at(lambda q: q.delays, signals, jnp.asarray(s["delays"]).reshape(K))
    from ._identify import identify

    model = identify(sig, start.structure, ModulatingFunction(s["N"], s["M"], s["h"]))
    return Refinement(model, start, s, s_start, np.exp(np.asarray(path)), code, steps, score)


def _plain(v):
    v = np.asarray(v, dtype=np.float64)
    return float(v) if v.ndim == 0 else [float(x) for x in v]


def _result_name(result) -> str:
    for name in ("successful", "max_steps_reached", "nonlinear_divergence",
                 "nonlinear_max_steps_reached"):
        if hasattr(optx.RESULTS, name) and result == getattr(optx.RESULTS, name):
            return name
    return "failed"


@eqx.filter_jit
def _bfgs_init(solver, fn, y):
    f_struct = jax.ShapeDtypeStruct((), jnp.float64)
    return solver.init(fn, y, None, {}, f_struct, None, frozenset())


@eqx.filter_jit
def _bfgs_step(solver, fn, y, state):
    y, state, _ = solver.step(fn, y, None, {}, state, frozenset())
    return y, state


@eqx.filter_jit
def _bfgs_terminate(solver, fn, y, state):
    return solver.terminate(fn, y, None, {}, state, frozenset())


# -- output-error refinement of the parameters ------------------------------------------------


class OutputError(eqx.Module):
    """Result of `output_error` (parameters ordered as `names`)."""

    model: Model
    start: Model
    x0: jax.Array  # initial state at the window start
    names: tuple
    theta: np.ndarray
    std_errors: np.ndarray
    covariance: np.ndarray
    sigma2: float  # residual variance estimate
    E_start: float  # sum of squared residuals x dt (eq. 17) before / after
    E: float
    result: str
    steps: int


def _free(model: Model):
    """Free parameters: a_0..a_{n-1} (a_n = 1), every b_kj, the offset."""
    n = model.n
    names = [f"a_{i}" for i in range(n)]
    vals = [np.asarray(model.a)[:n]]
    for k, bk in enumerate(model.b):
        names += [f"b_{k + 1}{j}" for j in range(bk.shape[0])]
        vals.append(np.asarray(bk))
    if model.has_offset:
        names.append("offset")
        vals.append(np.atleast_1d(np.asarray(model.offset)))
    return tuple(names), np.concatenate(vals)


def _with(model: Model, theta):
    n = model.n
    a = jnp.concatenate([theta[:n], jnp.ones(1)])
    pos, bs = n, []
    for bk in model.b:
        bs.append(theta[pos : pos + bk.shape[0]])
        pos += bk.shape[0]
    offset = theta[pos] if model.has_offset else model.offset
    return eqx.tree_at(lambda m: (m.a, m.b, m.offset), model, (a, tuple(bs), offset))


class _Residual(eqx.Module):
    """y - y_sim(theta0 + scale z_theta, x_init + x_scale z_x) on the window (a pytree)."""

    model: Model
    u: jax.Array
    y: jax.Array
    theta0: jax.Array
    scale: jax.Array
    x_init: jax.Array
    x_scale: jax.Array
    dt: float = eqx.field(static=True)
    start: int = eqx.field(static=True)
    length: int = eqx.field(static=True)

    def __call__(self, z, args):
        p = self.theta0.shape[0]
        sim = _simulated(self.model, self.u, self.dt, self.start, self.length)
        return self.y - sim(self.theta0 + self.scale * z[:p], self.x_init + self.x_scale * z[p:])


@eqx.filter_jit
def _jacobian(fn, z):
    return jax.jacfwd(fn)(z, None)


def _simulated(model, u, dt, start, length):
    """y_sim (length,) of `model` from state x0 at sample `start`: (theta, x0) -> output."""
    def f(theta, x0):
        m = _with(model, theta)
        ss, drive, direct = _forced(m, u, dt)
        Phi = expm(ss.A * dt)
        dr = jax.lax.dynamic_slice_in_dim(drive, start, length)
        di = jax.lax.dynamic_slice_in_dim(direct, start, length)

        def step(x, d):
            return Phi @ x + d, ss.C[0] @ x

        _, ys = jax.lax.scan(step, x0, dr)
        return ys + di
    return f


def output_error(
    signals: Signals, model: Model, *, window=None, max_steps: int = 100, rtol: float = 1e-10,
    atol: float = 1e-12,
) -> OutputError:
    r"""Output-error (simulation-residual) estimate started from `model` (the MFM estimate).

    Minimises $\sum_k (y_k - y_{sim,k}(\theta, x_0))^2$ on `window` (default: the record) over
    the free parameters (a_0..a_{n-1}, b, offset; a_n = 1, delays fixed) and the initial state,
    with `optimistix.LevenbergMarquardt` through the exact simulation (the initial state starts
    from the initial-state observer, eq. 14). This removes the equation-error bias of MFM under
    output noise. Parameters are scaled by their starting magnitude.

    **Returns:** `OutputError` with the refined model, x0, standard errors and the Gauss-Newton
    covariance $\hat\sigma^2 (J^T J)^{-1}$ ($\hat\sigma^2$ = residual sum of squares / (N - p)).
    A failed solve returns the starting model with the solver's code in `result`.
    """
    from ._observers import observe

    if not isinstance(model, Model):
        raise TypeError("output_error(): model must be a Model")
    obs = observe(model, signals, window)
    k0 = 0 if window is None else round((float(window[0]) - signals.t0) / signals.dt)
    length = int(obs.y_sim.shape[0])
    yv = jax.lax.dynamic_slice_in_dim(signals.y, k0, length)
    names, theta0 = _free(model)
    scale = np.maximum(np.abs(theta0), 1e-8 * max(np.max(np.abs(theta0)), 1e-300))
    x_scale = np.maximum(np.abs(np.asarray(obs.x_initial)), 1e-6 * float(jnp.std(yv)) + 1e-300)
    p_theta = theta0.size
    residual = _Residual(model, signals.u, yv, jnp.asarray(theta0), jnp.asarray(scale),
                         obs.x_initial, jnp.asarray(x_scale), signals.dt, k0, length)
    z0 = jnp.zeros(p_theta + model.n)
    z, result, n_steps = _lm(residual, z0, max_steps, rtol, atol)
    code = _result_name(result)
    r0, r = residual(z0, None), residual(z, None)
    E0 = float(jnp.sum(r0**2)) * signals.dt
    E1 = float(jnp.sum(r**2)) * signals.dt
    # out of steps but better than the start: kept (the code says so); otherwise the start
    ok = code in USABLE and math.isfinite(E1) and E1 <= E0
    if not ok:
        z, E1 = z0, E0
    theta = np.asarray(theta0 + scale * np.asarray(z[:p_theta]))
    x0 = obs.x_initial + jnp.asarray(x_scale) * z[p_theta:]
    Jz = _jacobian(residual, z)  # d r / d z; parameters = theta0 + scale * z
    Jp = np.asarray(Jz) / np.concatenate([scale, x_scale])[None, :]
    dof = max(length - Jp.shape[1], 1)
    sigma2 = float(np.sum(np.asarray(r) ** 2)) / dof if ok else float(np.sum(
        np.asarray(r0) ** 2)) / dof
    cov = sigma2 * np.linalg.pinv(Jp.T @ Jp)
    new = _with(model, jnp.asarray(theta)) if ok else model
    return OutputError(new, model, x0, names, theta, np.sqrt(np.diag(cov))[:p_theta],
                       cov[:p_theta, :p_theta], sigma2, E0, E1, code, int(n_steps))


@eqx.filter_jit
def _lm(residual, z0, max_steps, rtol, atol):
    sol = optx.least_squares(residual, optx.LevenbergMarquardt(rtol=rtol, atol=atol), z0,
                             max_steps=max_steps, throw=False)
    return sol.value, sol.result, sol.stats["num_steps"]


def cramer_rao(model: Model, u, dt: float, x0, sigma: float, *, length: int | None = None):
    r"""Cramer-Rao standard deviations of the free parameters (and x0) of `model` for white
    output noise of standard deviation `sigma`: $\sqrt{\mathrm{diag}(\sigma^2 (J^T J)^{-1})}$,
    $J = \partial y_{sim} / \partial(\theta, x_0)$ by `jax.jacfwd` of the exact simulation.

    **Returns:** (names, std of the parameters).
    """
    u = jnp.asarray(u, dtype=jnp.float64).reshape(jnp.shape(u)[0], -1)
    length = u.shape[0] if length is None else length
    names, theta0 = _free(model)
    sim = _simulated(model, u, dt, 0, length)
    J = jax.jacfwd(lambda v: sim(v[: theta0.size], v[theta0.size :]))(
        jnp.concatenate([jnp.asarray(theta0), jnp.asarray(x0, dtype=jnp.float64)]))
    J = np.asarray(J)
    cov = sigma**2 * np.linalg.pinv(J.T @ J)
    return names, np.sqrt(np.diag(cov))[: theta0.size]
