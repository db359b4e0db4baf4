r"""Output-error (simulation-residual) estimation of the parameters, started from MFM.

`output_error`: from the MFM estimate (the closed form stays the initialiser and reference),
minimises the simulation residual over the parameters and the initial state with
Levenberg-Marquardt (`_lm`) through the exact simulation; returns the Gauss-Newton
covariance $\sigma^2 (J^T J)^{-1}$ and standard errors.
"""

from __future__ import annotations

import math
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import _boundary as _b
from . import _padded as padded
from ._jit import device, jit
from ._linalg import small_matmul
from ._model import Model, is_stable, simulation_form
from ._optim import USABLE
from ._pytree import replace_fields
from ._signals import Signals
from ._status import Status


class OutputErrorFit(eqx.Module):
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
    converged: bool  # the solver met its tolerances (not only ran out of steps while improving)
    stabilised: bool  # the start had poles with Re > 0; they were mirrored before the fit
    # with `delay_uncertainty`: each input's delay std error (NaN for a delay of 0, not
    # counted); None without it (the delays count as known)
    delay_std_errors: np.ndarray | None = None
    delays_fitted: bool = False  # `fit_delays`: the model's nonzero delays were fitted too
    # with `delay_uncertainty` or `fit_delays`: the covariance of (names..., every input's
    # delay), (p + K, p + K), a delay held or of 0 with zero rows; the bands of
    # `step_response` and `frequency_response` read it
    joint_covariance: np.ndarray | None = None

    def summary(self) -> str:
        """Parameters with standard errors, E before and after, and the solver's verdict."""
        lines = [f"output-error fit  n={self.model.n}  m={list(self.model.m)}",
                 f"{'parameter':<12}{'value':>16}{'std error':>14}"]
        for name, v, e in zip(self.names, self.theta, self.std_errors):
            lines.append(f"{name:<12}{v:>16.6e}{e:>14.3e}")
        if self.delay_std_errors is not None:
            for name, v, e in zip(self.model.input_names, np.asarray(self.model.delays),
                                  self.delay_std_errors):
                if not np.isnan(e):  # (inf: a fitted delay at its bound 0)
                    lines.append(f"{'delay ' + name:<12}{v:>16.6e}{e:>14.3e}" + (
                        "  (fitted)" if self.delays_fitted else
                        "  (held; its uncertainty is in the std errors above)"))
        lines.append(f"E: {self.E_start:.6e} (start) -> {self.E:.6e}")
        lost = [n for n, e in zip(self.names, self.std_errors) if not np.isfinite(e)]
        if lost:
            lines.append(f"NOT DETERMINED by the data (infinite std error, the value is "
                         f"arbitrary): {', '.join(lost)}")
        if self.stabilised:
            lines.append("start was unstable: its right-half-plane poles were mirrored first "
                         "(E start is the mirrored start's)")
        if int(self.model.status) & Status.UNSTABLE:
            lines.append("UNSTABLE: the fitted A(s) has a root with Re >= 0 (see the model's "
                         "status): validate it before use")
        lines.append(f"converged ({self.result})" if self.converged else
                     f"NOT CONVERGED ({self.result} after {self.steps} steps): the estimate is "
                     "the best iterate; raise max_steps or start from a better model")
        return "\n".join(lines)


def stabilised(model: Model) -> tuple[Model, bool]:
    """`model` with every pole of A(s) in the right half plane mirrored into the left one
    (|A| on the imaginary axis and the b's kept), and whether anything changed: an unstable
    MFM start cannot seed a simulation-residual fit on a long window."""
    a = np.asarray(model.a, dtype=np.float64)
    if is_stable(a):
        return model, False
    roots = np.roots(a[::-1])
    mirrored = np.where(roots.real >= 0, -np.abs(roots.real) - 1e-9 * np.abs(roots) + 1j * roots.imag,
                        roots)
    a_new = np.real(np.poly(mirrored))[::-1] * a[-1]
    return eqx.tree_at(lambda m: m.a, model, jnp.asarray(a_new / a_new[-1])), True


def free_parameters(model: Model):
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


def order_parameters(model: Model, theta):
    """(`simulation_form(model)`, `theta` placed in its free parameters, their positions): a
    vector ordered as `free_parameters(model)` laid out as the free parameters of the model with
    every numerator of order n (a_0..a_{n-1}, b_k0..b_kn, offset; the extra coefficients zero).
    Programs over a model's free parameters then compile once per order n, not per
    structure; the positions pick the structure's own entries (NumPy, on the host)."""
    n = model.n
    live = padded.indices(model, n, n + 1)
    full = np.zeros(n + model.n_inputs * (n + 1) + int(model.has_offset))
    full[live] = theta
    return simulation_form(model), full, live


def with_parameters(model: Model, theta):
    """`model` with the free parameters `theta` (ordered as `free_parameters`); a NumPy
    `theta` is split on the host (no program per structure)."""
    xp = np if isinstance(theta, np.ndarray) else jnp
    n = model.n
    a = xp.concatenate([theta[:n], xp.ones(1)])
    pos, bs = n, []
    for bk in model.b:
        bs.append(theta[pos : pos + bk.shape[0]])
        pos += bk.shape[0]
    offset = theta[pos] if model.has_offset else model.offset
    new = (a, tuple(bs), offset)
    return eqx.tree_at(lambda m: (m.a, m.b, m.offset), model,
                       jax.device_put(new) if xp is np else new)


def _fitted(model: Model, theta: np.ndarray) -> Model:
    """`model` with the output-error parameters `theta` (host): as `srivc`'s, its `theta` is
    the free-parameter vector, the MFM solve's diagnostics (J, J_rel, cond, mf) do not describe
    it and are dropped, and its status says whether A(s) is Hurwitz (`Status.UNSTABLE`)."""
    new = with_parameters(model, theta)
    stable = is_stable(new.a)
    nan = jax.device_put(np.float64(np.nan))
    return replace_fields(new, theta=jax.device_put(np.asarray(theta, dtype=np.float64)),
                          J=nan, J_rel=nan, cond=nan, mf=None, status=jax.device_put(
                              np.int32(0 if stable else int(Status.UNSTABLE))))


class _Residual(eqx.Module):
    """y - y_sim(theta0 + scale z_theta, x_init + x_scale z_x) on the window (a pytree), the
    model zero-padded (`mfmjax._padded`): every structure of one padded order is one program.
    z holds the padded theta and the padded initial state; the entries outside `free` are held
    at zero here, so their Jacobian columns vanish and `_lm` never moves them."""

    c: dict  # the padded start; its coefficients are replaced by theta
    signals: Signals  # unlabelled
    y: jax.Array
    theta0: jax.Array
    scale: jax.Array
    x_init: jax.Array
    x_scale: jax.Array
    free: jax.Array  # (size,) the free entries of z
    start: jax.Array  # first sample of the window (a value: a new window is not a new program)
    valid: jax.Array  # the window's own length (a value); residuals beyond it are zero
    length: int = eqx.field(static=True)  # the window's bucket (`padded_window`)
    # `fit_delays`: z ends with one entry per input, its delay = start's + delay_scale z (at
    # least 0; `free` says which move); None: the delays are held (no such entries)
    delay_scale: jax.Array | None = None

    @property
    def size(self) -> int:
        """Unknowns z: the padded parameters and initial state (and the delays, if fitted)."""
        K = 0 if self.delay_scale is None else self.delay_scale.shape[-1]
        return self.theta0.shape[-1] + self.x_init.shape[-1] + K

    def __call__(self, z, args):
        p, n = self.theta0.shape[0], self.x_init.shape[0]
        z = jnp.where(self.free, z, 0.0)  # padded coefficients are slots of the realisation
        c = padded.with_theta(self.c, self.theta0 + self.scale * z[:p], self.signals.offset)
        if self.delay_scale is not None:
            c = dict(c, delays=delays_at(self.c["delays"], self.delay_scale, z[p + n :]))
        (ss, Phi, drive, direct), _ = padded.padded_forced(self.signals, c,
                                                           self.start + jnp.arange(self.length))

        def step(x, d):
            return small_matmul(Phi, x) + d, small_matmul(ss.C, x)[0]

        _, ys = jax.lax.scan(step, self.x_init + self.x_scale * z[p : p + n], drive)
        return jnp.where(jnp.arange(self.length) < self.valid, self.y - (ys + direct), 0.0)


def delays_at(start, scale, z):
    """The fitted delays: the start's moved by `scale * z`, dead times (at least 0)."""
    return jnp.maximum(start + scale * z, 0.0)


def output_error(
    signals: Signals, model: Model, *, window=None, max_steps: int = 100, rtol: float = 1e-10,
    atol: float = 1e-12, delay_uncertainty: bool = False, fit_delays: bool = False,
) -> OutputErrorFit:
    r"""Output-error (simulation-residual) estimate started from `model` (the MFM estimate).

    Minimises $\sum_k (y_k - y_{sim,k}(\theta, x_0))^2$ on `window` (default: the record) over
    the free parameters (a_0..a_{n-1}, b, offset; a_n = 1, delays fixed) and the initial state,
    with Levenberg-Marquardt (`_lm`) through the exact simulation (the initial state starts
    from the initial-state observer, eq. 14). This removes the equation-error bias of MFM under
    output noise. Parameters are scaled by their starting magnitude.

    **Returns:** `OutputErrorFit` with the refined model, x0, standard errors and the Gauss-Newton
    covariance $\hat\sigma^2 (J^T J)^{-1}$ ($\hat\sigma^2$ = residual sum of squares / (N - p)).
    The delays are held, and count as known in the covariance, unless `delay_uncertainty`:
    give it when they were estimated from the same data (a search's delay grid, `refine`);
    J then has a column per nonzero delay (d residual / d tau_k, by forward mode through the
    simulation), the parameters' covariance is marginal over them, and `delay_std_errors` holds
    theirs (with a delay fitted by `refine` on a 10 dB record, std errors that held it known
    were 0.43-0.52 of the estimates' spread, 56-67 % coverage of nominal 95 % intervals).
    `fit_delays`: every nonzero delay of the start is fitted too (a delay of 0 is held: no
    dead time), jointly with the parameters (their Jacobian columns from the same forward-mode
    pass; delays stay >= 0), the covariance is the joint one as with `delay_uncertainty`, and
    the model carries the fitted delays: a delay picked from a search's grid moves off it.
    A failed solve returns the starting model with the solver's code in `result`. A fit that did
    not converge says so: `converged` is False, `summary()` prints NOT CONVERGED, and the call
    warns. An unstable start has its right-half-plane poles mirrored first (`stabilised`).

    **A batch of records** (Monte Carlo realisations, repeated experiments): `signals` a list of
    `Signals` of one layout and `model` one start or a list of them (one per record), whole
    records (no `window`). Chunks of pairs of one padded shape run in one compiled call each,
    on a thread per core (`output_error_many`); returns a list of fits, None where a start
    could not be simulated (overflow, unobservable), and one warning counts the fits that did
    not converge. Eager only: the Levenberg-Marquardt bookkeeping runs on the host, so
    `jax.jit`/`jax.vmap` over records is refused (`srivc` traces).
    """
    from ._boundary import check_output_error

    for name, flag in (("delay_uncertainty", delay_uncertainty), ("fit_delays", fit_delays)):
        if not isinstance(flag, bool):
            raise TypeError(f"output_error(): {name} must be True or False, got {flag!r}")
    if not isinstance(signals, Signals):
        if delay_uncertainty:
            raise ValueError("output_error(): delay_uncertainty is for one record (call "
                             "output_error on each record, or give fit_delays=True)")
        return _output_error_batch(signals, model, window, max_steps, rtol, atol, fit_delays)
    check_output_error(signals, window_=window, max_steps=max_steps, rtol=rtol, atol=atol)
    _eager_only(signals, model)
    _b.start_notes("output_error", model, signals)
    residual, meta = _prepare(signals, model, window, rehearse=(max_steps, rtol, atol),
                              fit_delays=fit_delays)
    return _finish(residual, meta, _lm(residual, *_lm_arguments(residual.size, max_steps, rtol,
                                                                atol)), delay_uncertainty)


def _eager_only(signals: Signals, model) -> None:
    """TypeError for a model that is not a `Model`, and for traced records or models."""
    if not isinstance(model, Model):
        raise TypeError(f"output_error(): model must be a Model (e.g. from identify), got "
                        f"{type(model).__name__}{_b.swap_hint('output_error', model)}")
    _b.eager_only("output_error", signals, model)


def _output_error_batch(signals, model, window, max_steps, rtol, atol, fit_delays) -> list:
    """`output_error` on a list of records (its docstring): checked like one record each."""
    from ._batch import as_records
    from ._boundary import check_output_error

    records, _ = as_records("output_error", signals)
    if window is not None:
        raise ValueError("output_error(): a list of records is fitted on whole records; give "
                         "window=None, or cut the records to the window first")
    models = list(model) if isinstance(model, list | tuple) else [model] * len(records)
    if len(models) != len(records):
        raise ValueError(f"output_error(): {len(records)} records but {len(models)} start "
                         "models; give one model for all records or one per record")
    for r, m in zip(records, models):
        check_output_error(r, window_=None, max_steps=max_steps, rtol=rtol, atol=atol)
        _eager_only(r, m)
        if m.n_inputs != r.n_inputs:
            raise ValueError(f"output_error(): a start model has {m.n_inputs} inputs but the "
                             f"records have {r.n_inputs}; start from models of these signals")
    for r, m in zip(records, models):  # as one record's call (a repeated text shows once)
        _b.start_notes("output_error", m, r)
    with warnings.catch_warnings():  # one warning for the batch, below
        warnings.simplefilter("ignore")
        fits = output_error_many(records, models, max_steps=max_steps, rtol=rtol, atol=atol,
                                 fit_delays=fit_delays)
    bad = [i for i, f in enumerate(fits) if f is None or not f.converged]
    if bad:
        warnings.warn(f"output_error(): {len(bad)} of {len(fits)} fits did not converge "
                      f"(records {bad[:10]}{'...' if len(bad) > 10 else ''}); each returned its "
                      "best iterate with its code in `result` (None: the start could not be "
                      "simulated)", stacklevel=3)
    return fits


_REHEARSED: set = set()  # residual layouts whose `_lm` program this process has compiled


def _rehearsal(parts: tuple, n_max: int, bound: int, limits: tuple):
    """On a residual layout's first call: a function that compiles `_lm` for it, a run of no
    step from a stand-in residual (the start's parts, initial state 0 and its scale 1), while
    the start observer runs on a second thread (`_prepare`): the two first compiles overlap.
    None for a layout seen before."""
    c, sig, yv, th0, sc, free, k0, length, *delay_scale = parts
    stand_in = (c, sig, yv, th0, sc, np.zeros(n_max), np.ones(n_max), free, k0, length,
                *delay_scale)
    key = (jax.tree.structure(stand_in), bound, tuple(
        (np.shape(x), getattr(x, "dtype", type(x))) for x in jax.tree.leaves(stand_in)))
    if key in _REHEARSED:
        return None
    _REHEARSED.add(key)

    def rehearse():
        try:
            residual = _Residual(*jax.device_put(stand_in[:10]), bound,
                                 *jax.device_put(stand_in[10:]))
            _lm(residual, *_lm_arguments(residual.size, 0, *limits[1:]))
        except Exception:  # noqa: BLE001 (speculative: the real call compiles what it missed)
            pass

    return rehearse


def _lm_arguments(size: int, max_steps, rtol, atol):
    """z0 = 0 and the limits as device values (a new limit is not a new program; put, not
    computed, so that no eager program runs either)."""
    return jax.device_put((np.zeros(size), np.asarray(max_steps), np.asarray(rtol, np.float64),
                           np.asarray(atol, np.float64)))


def _prepare(signals: Signals, model: Model, window, n_max: int | None = None,
             rehearse: tuple | None = None, bucket: int | None = None,
             fit_delays=False):
    """The scaled residual of `output_error` at its start (the initial state from the
    observer, eq. 14) and what `_finish` needs. The model is zero-padded to order `n_max` with
    numerators of order n_max (every structure of that order: one program), or by default to
    its own n and largest m_k (no padded unknowns in the forward-mode Jacobian, whose cost
    grows with their count). Raises ValueError when the start's simulation overflows or its
    state is unobservable on the window. `rehearse` (`output_error`'s limits): on a layout's
    first call, `_lm` compiles while the observer runs (`_rehearsal`). `fit_delays` (True, or
    one bool per input): z ends with a delay entry per input, in samples, free where asked
    for and the start's delay is nonzero."""
    from ._batch import overlapped
    from ._observers import checked, padded_window, validation_window

    _b.start_layout("output_error", model, signals)
    original = model
    model, was_unstable = stabilised(model)
    k0, length = validation_window(signals, window, None, model.n, "output_error", "window")[:2]
    n_max, m_max = (model.n, max(model.m, default=0)) if n_max is None else (n_max, n_max)
    c = padded.padded_model(model, n_max, m_max)
    # the window padded to its bucket and the record to hold it (`padded_window`; only the
    # window's own samples count): windows and records of every length in a bucket share
    # the programs
    y, u, bound = padded_window(signals, k0, length, bucket)
    sig = replace_fields(signals.unlabelled(), y=y, u=u)
    yv = sig.y[k0 : k0 + bound]
    yw = yv[:length]
    names, theta0 = free_parameters(model)
    idx = padded.indices(model, n_max, m_max + 1)
    p = n_max + model.n_inputs * (m_max + 1) + int(model.has_offset)
    scale = np.maximum(np.abs(theta0), 1e-8 * max(np.max(np.abs(theta0)), 1e-300))
    fit = np.broadcast_to(np.asarray(fit_delays, bool), (model.n_inputs,))
    slots = bool(np.any(fit))  # the delays' entries of z (free where asked for and nonzero)
    free = np.concatenate([padded.free(c, model.has_offset), np.arange(n_max) < model.n]
                          + ([fit & (np.asarray(model.delays, np.float64) > 0)] if slots else []))
    dscale = (np.full(model.n_inputs, float(signals.dt)),) if slots else ()
    th0, sc, xs = np.zeros(p), np.ones(p), np.ones(n_max)
    th0[idx], sc[idx] = theta0, scale
    # the zero-padded observer: one program for every structure of this padded shape
    obs = checked(overlapped(lambda: padded.observe_candidate(
        sig, c, np.int32(k0), bound, np.int32(length), np.int32(length)), None if rehearse is None
        else _rehearsal((c, sig, yv, th0, sc, free, np.int32(k0), np.int32(length), *dscale),
                        n_max, bound, rehearse)), "output_error")
    x_init = np.asarray(obs.x_initial)  # zero beyond n
    x_scale = np.maximum(np.abs(x_init[: model.n]), 1e-6 * float(np.std(yw)) + 1e-300)
    xs[: model.n] = x_scale
    residual = _Residual(*jax.device_put((c, sig, yv, th0, sc, x_init, xs, free, np.int32(k0),
                                          np.int32(length))), bound, *jax.device_put(dscale))
    return residual, (original, model, was_unstable, names, theta0, scale, x_scale,
                      x_init[: model.n], idx)


def gauss_newton_covariance(J, sigma2: float) -> np.ndarray:
    r"""$\sigma^2 (J^T J)^{-1}$ through the SVD of J with unit-norm columns. A parameter the
    data cannot determine (a zero column, or a component above 1e-8 in J's numerical null
    space: singular values below numpy's `matrix_rank` tolerance, max(s) max(T, p) eps) gets
    an infinite variance and NaN covariances, where a pseudo-inverse gave 0, i.e. "perfectly
    determined"."""
    J = np.asarray(J, dtype=np.float64)
    if J.shape[0] < J.shape[1]:  # fewer rows than unknowns: zero rows give the thin SVD's Vt
        # the whole null space (without them no parameter came out undetermined)
        J = np.concatenate([J, np.zeros((J.shape[1] - J.shape[0], J.shape[1]))])
    peak = np.max(np.abs(J), axis=0, initial=0.0)  # the norm after scaling by it: a column of
    # 1e-155 had a squared norm of 0 (underflow) and came out "undetermined"
    scale = peak * np.linalg.norm(J / np.where(peak > 0, peak, 1.0), axis=0)
    dead = ~(scale > 0)
    scale = np.where(dead, 1.0, scale)
    _, s, Vt = np.linalg.svd(J / scale, full_matrices=False)
    keep = s > (s.max() if s.size else 0.0) * max(J.shape) * np.finfo(np.float64).eps
    W = Vt.T[:, keep] / s[keep] / scale[:, None]
    cov = sigma2 * (W @ W.T)
    undetermined = dead | (np.max(np.abs(Vt.T[:, ~keep]), axis=1, initial=0.0) > 1e-8)
    cov[undetermined, :] = np.nan
    cov[:, undetermined] = np.nan
    cov[undetermined, undetermined] = np.inf
    return cov


@jit
def _delay_jacobian(residual: _Residual, z):
    """d residual / d tau_k at z (forward mode through the simulation): (length, K)."""
    def r(d):
        return eqx.tree_at(lambda q: q.c, residual, dict(residual.c, delays=d))(z, None)

    return jax.jacfwd(r)(residual.c["delays"])


def _finish(residual, meta, solved, delay_uncertainty: bool = False) -> OutputErrorFit:
    """`OutputErrorFit` from the solver's point (`_lm`'s outputs, with the residual and its
    Jacobian at the start and at that point): kept if usable and no worse than the start, the
    Gauss-Newton covariance there (with a column per nonzero delay where `delay_uncertainty`);
    warns when not converged."""
    original, model, was_unstable, names, theta0, scale, x_scale, x_init, idx = meta
    z, result, n_steps, r0, J0, r, J = jax.device_get(solved)
    p_theta, length, dt = theta0.size, int(residual.valid), float(residual.signals.dt)
    live = np.concatenate([idx, residual.theta0.shape[0] + np.arange(model.n)])
    code = LM_CODES[int(result)]
    E0 = float(np.sum(r0**2)) * dt
    E1 = float(np.sum(r**2)) * dt
    # out of steps but better than the start: kept (the code says so); otherwise the start
    ok = code in USABLE and math.isfinite(E1) and E1 <= E0
    if not ok:
        z, E1, r, J = np.zeros_like(z), E0, r0, J0
    z_host = z[live]  # the structure's parameters and states
    theta = np.asarray(theta0 + scale * z_host[:p_theta])
    x0 = device(np.asarray(x_init) + x_scale * z_host[p_theta:])
    # J = d r / d z; parameters = theta0 + scale * z
    Jp = J[:, live] / np.concatenate([scale, x_scale])[None, :]
    delays = np.asarray(residual.c["delays"])
    fitted = residual.delay_scale is not None
    timed = np.flatnonzero(delays > 0) if delay_uncertainty else np.zeros(0, int)
    if fitted:  # their columns are z's last K (d residual / d z_k, z_k in delay_scale units)
        K, d_scale = delays.size, np.asarray(residual.delay_scale)
        timed = np.flatnonzero(np.asarray(residual.free)[-K:])
        delays = np.asarray(delays_at(delays, d_scale, z[-K:]))
        Jp = np.concatenate([Jp, J[:, z.size - K + timed] / d_scale[timed]], axis=1)
    elif timed.size:  # the delays' columns, at the point returned (z, or the start's zeros)
        Jd = np.asarray(_delay_jacobian(residual, device(z)))[:, timed]
        Jp = np.concatenate([Jp, Jd], axis=1)
    dof = max(length - Jp.shape[1], 1)
    sigma2 = float(np.sum(r**2)) / dof
    cov = gauss_newton_covariance(Jp, sigma2)
    delay_std = joint = None
    if delay_uncertainty or fitted:
        delay_std = np.full(delays.shape, np.nan)
        delay_std[timed] = np.sqrt(np.diag(cov)[Jp.shape[1] - timed.size :])
        K = delays.size
        at = np.concatenate([np.arange(p_theta), Jp.shape[1] - timed.size + np.arange(
            timed.size)])  # theta's and the timed delays' rows of cov (x0's left out)
        to = np.concatenate([np.arange(p_theta), p_theta + timed])
        joint = np.zeros((p_theta + K, p_theta + K))
        joint[np.ix_(to, to)] = cov[np.ix_(at, at)]
    new = _fitted(model, theta)  # theta: the start's own parameters when not `ok`
    if fitted:  # (the start's delays where not `ok`: z is zero there)
        new = replace_fields(new, delays=device(delays))
        bound = [model.input_names[k] if model.input_names else f"u{k + 1}" for k in timed
                 if delays[k] == 0.0]
        if bound:  # its Jacobian column vanishes there: infinite std error, said
            warnings.warn(f"output_error(): the fitted delays of inputs {bound} reached 0, "
                          "their bound (no dead time): the data prefer none; their std errors "
                          "are infinite", stacklevel=3)
    fitted = fitted and bool(timed.size)  # something was fitted (every delay 0: nothing)
    # fitted with the signals' intersample rules: the model carries them (as SRIVC's), so
    # `observe` and `simulate` reproduce the fit's E
    new = replace_fields(new, intersample=tuple(residual.signals.intersample))
    converged = ok and code == "successful"
    lost = [n for n, v in zip(names, np.diag(cov)[:p_theta]) if not np.isfinite(v)]
    if lost:
        warnings.warn(f"output_error(): the data do not determine {', '.join(lost)} (infinite "
                      "std error, the value is arbitrary): use an input that excites them or "
                      "a model without them", stacklevel=3)
    if not converged:
        best = "the best iterate" if ok and int(n_steps) > 0 else "the start"
        warnings.warn(f"output_error(): not converged ({code} after {int(n_steps)} steps); the "
                      f"result is {best}: raise max_steps or "
                      "start from a better model (see OutputErrorFit.converged)", stacklevel=3)
    if int(new.status) & Status.UNSTABLE:  # "converged" alone read as a usable model
        warnings.warn("output_error(): the fitted model is unstable (a root of A(s) with Re >= "
                      "0; see its status): a short or poorly excited window can fit one; check "
                      "the window and the start, or validate it before use", stacklevel=3)
    return OutputErrorFit(new, original, x0, names, theta, np.sqrt(np.diag(cov))[:p_theta],
                          cov[:p_theta, :p_theta], sigma2, E0, E1, code, int(n_steps),
                          bool(converged), bool(was_unstable), delay_std, fitted, joint)


def output_error_many(records, models, *, n_max: int | None = None, max_steps: int = 100,
                      rtol: float = 1e-10, atol: float = 1e-12,
                      bucket: int | None = None, fit_delays=False) -> list:
    """`output_error(records[i], models[i])` for every pair (whole records), the
    Levenberg-Marquardt iterations of each chunk of pairs of one padded shape in one compiled
    call (`lax.map`, chunks as in `_batch.groups`); with `n_max` every structure of order
    <= n_max has that shape (`_prepare`); `bucket`: the records' padded length (at least
    theirs; default their `record_bucket`). An entry is None where the start could not be
    simulated (overflow, unobservable). `fit_delays` as in `output_error`, or one bool per
    input (the inputs whose nonzero delays are fitted)."""
    from ._batch import groups, in_parallel, stack, unstack

    prepared = []
    for sig, model in zip(records, models):
        try:
            prepared.append(_prepare(sig, model, None, n_max, bucket=bucket,
                                     fit_delays=fit_delays))
        except ValueError:
            prepared.append(None)
    out = [None] * len(prepared)
    live = [i for i, p in enumerate(prepared) if p is not None]

    def run(idx):
        idx = [live[j] for j in idx]
        z0, *limits = _lm_arguments(prepared[idx[0]][0].size, max_steps, rtol, atol)
        if len(idx) == 1:  # a single pair: the program `output_error` uses
            solved = [_lm(prepared[idx[0]][0], z0, *limits)]
        else:
            solved = zip(*(unstack(x, device=False) for x in _lm_many(
                stack([prepared[i][0] for i in idx]), *limits)))
        return [(i, _finish(prepared[i][0], prepared[i][1], one)) for i, one in zip(idx, solved)]

    for pairs in in_parallel(run, groups([prepared[i][0] for i in live])):
        for i, fit in pairs:
            out[i] = fit
    return out


@jit
def _lm_many(residuals, max_steps, rtol, atol):
    return jax.lax.map(lambda res: _lm(res, jnp.zeros(res.size), max_steps, rtol, atol),
                       residuals)


LM_CODES = ("successful", "nonlinear_max_steps_reached", "nonlinear_divergence")


@jit
def _lm(residual, z0, max_steps, rtol, atol):
    r"""Levenberg-Marquardt with Marquardt's diagonal scaling and Nielsen's damping update,
    one compiled loop. Each trial point costs one forward-mode pass that gives the residual
    and its materialised Jacobian together (optimistix's LM re-linearised and re-materialised
    the scan several times a step: 10x slower here). Stops when a trial step moves z and the
    cost by less than `atol + rtol |.|` (max norm, as optimistix's Cauchy test; at the minimum
    the last trial is rejected by rounding, and z stays at the better point). Returns
    (z, code index into `LM_CODES`, steps, r and J at z0, r and J at z): `_finish` needs no
    program of its own."""
    def rj(z):
        J, r = jax.jacfwd(lambda v: (residual(v, None),) * 2, has_aux=True)(z)
        return r, J

    r0, J0 = rj(z0)
    c0 = 0.5 * jnp.sum(r0**2)
    fixed = jnp.where(residual.free, 0.0, 1.0)
    D0 = jnp.where(residual.free, jnp.sum(J0**2, axis=0), 0.0)

    def cond(s):
        return (s["step"] < max_steps) & ~s["done"]

    def body(s):
        z, r, J, cost, lam, nu = s["z"], s["r"], s["J"], s["cost"], s["lam"], s["nu"]
        D = jnp.maximum(s["D"], jnp.sum(J**2, axis=0))  # Marquardt scaling (Moré: running max)
        g = J.T @ r
        A = J.T @ J + lam * jnp.diag(D) + jnp.diag(fixed)  # padding: a unit block, delta 0
        delta = -jnp.linalg.solve(A, g)
        z_new = z + delta
        r_new, J_new = rj(z_new)
        cost_new = 0.5 * jnp.sum(r_new**2)
        predicted = 0.5 * delta @ (lam * D * delta - g)
        rho = (cost - cost_new) / jnp.maximum(predicted, 1e-300)
        accept = jnp.isfinite(cost_new) & jnp.all(jnp.isfinite(J_new)) & (cost_new < cost)
        small_z = jnp.max(jnp.abs(delta) / (atol + rtol * jnp.abs(z_new))) < 1
        small_f = jnp.abs(cost - cost_new) / (atol + rtol * jnp.abs(cost_new)) < 1
        pick = lambda a, b: jnp.where(accept, a, b)  # noqa: E731
        return dict(
            z=pick(z_new, z), r=pick(r_new, r), J=pick(J_new, J), cost=pick(cost_new, cost),
            lam=jnp.clip(pick(lam * jnp.maximum(1 / 3, 1 - (2 * rho - 1) ** 3), lam * nu),
                         1e-30, 1e30),
            nu=pick(2.0, 2 * nu), D=D, step=s["step"] + 1,
            done=jnp.isfinite(cost_new) & small_z & small_f)

    start = dict(z=z0, r=r0, J=J0, cost=c0, lam=jnp.asarray(1e-3), nu=jnp.asarray(2.0),
                 D=jnp.where(residual.free, jnp.maximum(D0, 1e-12 * jnp.max(D0)), 0.0),
                 step=jnp.asarray(0),
                 done=jnp.asarray(False))
    finite = jnp.isfinite(c0) & jnp.all(jnp.isfinite(J0))
    s = jax.lax.while_loop(lambda s: cond(s) & finite, body, start)
    code = jnp.where(~finite, 2, jnp.where(s["done"], 0, 1))
    return s["z"], code, s["step"], r0, J0, s["r"], s["J"]
