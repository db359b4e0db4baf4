r"""Differentiable scores and refinement of the modulating-function settings.

- `scores`: J, J_rel (eq. 8), E (eq. 17) and fit of the MFM estimate as smooth functions of the
  modulating-function settings h, N, M (real N, M >= n), the delays, eta and the data: jax.grad
  and jax.jacfwd work through the whole chain (weights, Gram, KKT solve, observer, simulation).
  The cubic output rule switches its one-sided stencil where tau + h crosses a sample, so the
  weights, hence the scores, have O(dt^4) kinks there: derivatives are exact between them.
- `refine`: minimises log E (or log J_rel) over (h, N, M, delays) with `optimistix.BFGS`; every
  setting is a smooth map of an unconstrained variable into its box, so bounds always hold.

Output error and the Cramer-Rao bound live in `_output_error` and `_cramer_rao`.
"""

from __future__ import annotations

import functools
import math
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import _boundary as _b
from ._gram import MIN_VALID, TRACED_DELAYS
from ._identify import identify_model
from ._jit import device, jit
from ._model import Model
from ._modulating import ModulatingFunction, as_values
from ._observers import (
    fit_percent,
    masked_fit_percent,
    observation,
    observe_forced,
    padded_window,
    validation_window,
)
from ._optim import USABLE, solver_code
from ._pytree import replace_fields
from ._quadrature import kernel_bucket, kernel_length
from ._signals import Signals
from ._simulate import forced_response
from ._solve import default_eta
from ._status import describe
from ._structure import Structure

SETTINGS = ("h", "N", "M", "delays")
MAX_EXPONENT = 12.0  # default upper bound of N and M in refine


def _scores(signals, structure, h, N, M, delays, eta, kernel: int, v0, length, ob, end=None,
            valid=None):
    """Scores of one setting; `kernel` is the static kernel length, everything else a value.
    With `end` and `valid` (a padded record, `scores`), the record's own length and the
    validation window's: only their samples count."""
    sig = eqx.tree_at(lambda s: s.delays, signals, jnp.asarray(delays, dtype=jnp.float64))
    model = identify_model(sig, structure, as_values(ModulatingFunction(N, M, h)), eta, kernel,
                           end)
    obs = observe_forced(forced_response(model, sig.u, sig.dt), sig.y, sig.dt, v0, length, ob,
                         None, valid)
    yv = jax.lax.dynamic_slice_in_dim(sig.y, v0, length)
    out = {"J": model.J, "J_rel": model.J_rel, "E": obs.E,
           "fit": fit_percent(yv, obs.y_sim) if valid is None else masked_fit_percent(
               yv, obs.y_sim, valid), "status": model.status | obs.status}
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
    eta = _value(default_eta(p, signals.offset) if eta is None else eta)
    if eta.shape != (p,):
        raise ValueError(f"scores(): eta must have {p} entries, got shape {eta.shape}")
    delays = signals.delays if delays is None else _value(delays)
    if h_max is None:
        if _b.is_traced(h):
            raise ValueError("scores(): h is traced (jax.jit/jax.vmap/jax.grad) but no static "
                             "bound is known; pass h_max=... (it fixes the kernel length)")
        h_max = float(h)
    if delay_max is None:
        if _b.is_traced(delays):
            raise ValueError(f"scores(): delays are traced but no static bound is known; {TRACED_DELAYS}")
        delay_max = float(np.max(np.asarray(delays), initial=0.0))
    kernel = kernel_bucket(kernel_length(float(h_max) + float(delay_max), signals.host_dt))
    sig = signals.unlabelled()
    setting = (structure, _value(h), _value(N), _value(M), delays, eta, kernel)
    if _b.is_traced(sig.y) or _b.is_traced(sig.u):
        return _scores_jit(sig, *setting, jnp.asarray(v0, dtype=jnp.int32), length, ob)[0]
    padded, bound, end, valid = _padded_window(sig, v0, length)
    return _scores_jit(padded, *setting, np.int32(v0), bound, np.int32(ob), end, valid)[0]


def _padded_window(sig: Signals, v0: int, length: int):
    """(`sig` padded by `padded_window`, the window's static bound, the record's and the
    window's own lengths as values: `_scores`' `end` and `valid`)."""
    y, u, bound = padded_window(sig, v0, length)
    return replace_fields(sig, y=y, u=u), bound, np.int32(sig.n_samples), np.int32(length)


_scores_jit = jit(_scores)


# -- hyperparameter refinement ---------------------------------------------------------------


class Refinement(eqx.Module):
    """Result of `refine`: the refined model and settings, the score path and the solver code."""

    model: Model
    start: Model
    settings: dict
    start_settings: dict
    path: np.ndarray  # score of the iterate after each BFGS step, line-search trials that
    # were not accepted included (first entry: the start moved into the box)
    result: str  # optimistix result name ("successful", "max_steps_reached", ...)
    steps: int
    value: float  # the score (E or J_rel) of `model`, the model returned
    score: str = eqx.field(static=True)
    start_value: float = math.nan  # the start's own score on these signals (inf: unusable)

    @property
    def converged(self) -> bool:
        """BFGS met its tolerances (a result that ran out of steps is not converged)."""
        return self.result == "successful"

    @property
    def improved(self) -> bool:
        """The model returned scores below the start's own score (by more than 1e-9 of it)."""
        return bool(self.value < self.start_value * (1 - IMPROVEMENT))


def _value(x):
    """A setting as a float64 device value: traced as it is (under `jit`/`grad`), a concrete
    one put on the device without compiling anything (`device`)."""
    return jnp.asarray(x, dtype=jnp.float64) if _b.is_traced(x) else device(x, np.float64)


def _host_settings(x0: dict, box: dict, z) -> dict:
    """`_Objective.settings` on the host (NumPy: no eager program): lo + (hi - lo) sigmoid(z)."""
    s = dict(x0)
    for k, v in jax.device_get(z).items():
        lo, hi = (np.asarray(b, dtype=np.float64) for b in box[k])
        s[k] = lo + (hi - lo) / (1.0 + np.exp(-np.asarray(v, dtype=np.float64)))
    return s


EDGE = 0.02  # a start nearer its box's edge (share of the range) starts this far inside
IMPROVEMENT = 1e-9  # a score below the start's by less than this share is no improvement (a
# stalled BFGS "improved" 0.12445271758566176 to ...043)
AT_BOUND = 1e-3  # a refined setting this near (share of its range) a box edge ended there


def _logit(x, lo, hi):
    """z of the setting x in [lo, hi] (its sigmoid's inverse), at least `EDGE` of the range
    inside the box: at the edge the sigmoid's slope vanishes (a start at delay 0 or N = n,
    clipped to 1e-6 of the range, had a gradient 1e-6 of its size and BFGS stopped there after
    2 steps, "successful")."""
    r = np.clip((np.asarray(x, dtype=np.float64) - lo) / (hi - lo), EDGE, 1 - EDGE)
    return np.log(r / (1 - r))


def _moved(x, lo, hi) -> bool:
    """Whether `_logit` moves the start x inside the box."""
    r = (np.asarray(x, dtype=np.float64) - lo) / (hi - lo)
    return bool(np.any((r < EDGE) | (r > 1 - EDGE)))


class _Objective(eqx.Module):
    """log score of the settings lo + (hi - lo) sigmoid(z) (a pytree: one compilation)."""

    signals: Signals
    x0: dict
    lo: dict
    hi: dict
    eta: jax.Array
    start: jax.Array  # first sample of the validation window (a value)
    lengths: tuple  # (observer, record, window) lengths in samples (values: `_padded_window`)
    structure: Structure = eqx.field(static=True)
    vary: tuple = eqx.field(static=True)
    kernel: int = eqx.field(static=True)  # kernel length bucket of the largest h + delay allowed
    window: int = eqx.field(static=True)  # the validation window's bucket in samples
    key: str = eqx.field(static=True)

    def settings(self, z):
        s = dict(self.x0)
        for k in self.vary:
            s[k] = self.lo[k] + (self.hi[k] - self.lo[k]) * jax.nn.sigmoid(z[k])
        return s

    def __call__(self, z, args):
        s = self.settings(z)
        out, _ = _scores(self.signals, self.structure, s["h"], s["N"], s["M"], s["delays"],
                         self.eta, self.kernel, self.start, self.window, *self.lengths)
        val = out[self.key]
        ok = jnp.isfinite(val) & (val > 0) & (out["status"] == 0)
        return jnp.where(ok, jnp.log(jnp.where(ok, val, 1.0)), jnp.inf), None


def refine(
    signals: Signals, start: Model, *, score: str = "E", vary=SETTINGS, bounds: dict | None = None,
    validate=None, observer_window=None, max_steps: int = 40, rtol: float = 1e-6,
    atol: float = 1e-8, top: int = 3, eta=None, _span: float = 0.0,
) -> Refinement:
    r"""Refine the modulating-function settings (and delays) of `start` by gradient descent.

    Minimises $\log E$ (score "E", on `validate` with the initial-state observer, default) or
    $\log J_{rel}$ (score "J") with `optimistix.BFGS` over the settings named in `vary` (any of
    "h", "N", "M", "delays"). Default bounds: h in [h0/4, min(4 h0, record/3)], N and M in
    [n, 12], delays in [0, max(2 tau0, tau0 + 20 dt)] (and below record/4); `bounds` overrides
    any of them as {"h": (lo, hi), ...}. Every setting is a sigmoid of an unconstrained
    variable, so the iterates never leave the box; a start within `EDGE` (2 %) of the range
    from an edge (a delay of 0, N = n) begins that far inside, where the sigmoid has a slope,
    and the path's best is compared with the start's own score.

    `start` may be a `SearchResult`: its best `top` candidates are refined and the refinement
    with the lowest score is returned, scored on the search's `validate` window and
    `observer_window` where none is given (its table's E is of them); their kernels are
    sized for the largest of their boxes (h + delays), so candidates of one structure share
    one compiled program. A refinement
    that fails (solver error, non-finite score, or no improvement) returns the starting
    model, with the solver's code in `result`; where the start is not the model its settings
    give on these signals (identified on other data), that model instead, whose score
    `value` is, unless the start scores better there; score "E" never returns a model
    scoring worse than the start (`start_value`). `eta`: the constraint of eq. (11) the
    start was identified with (default: `identify`'s); a start identified with another eta
    is re-identified with this one along the path. A refined setting that ends at an edge
    of its box that is not a physical limit (h's, N's and M's upper, h's lower, a delay's
    upper) is warned: the optimum may lie beyond it. (`_span`: internal, that shared size.)
    """
    from ._boundary import check_refine
    from ._search import SearchResult

    _b.eager_only("refine", start)
    check_refine(signals, score=score, vary=vary, bounds=bounds, validate=validate,
                 observer_window=observer_window, max_steps=max_steps, rtol=rtol, atol=atol,
                 top=top)

    if isinstance(start, SearchResult):  # refine the best `top` candidates, keep the best
        if len(start) == 0:
            raise ValueError("refine(): the search result is empty")
        if start.identify is not None:  # the model came back fitted on the validation data too
            warnings.warn(f"refine(): the search identified on the windows "
                          f"{list(start.identify)}, but refine identifies on all of `signals` "
                          "(its E on a validation window inside them is then no held-out "
                          "score); give refine the identification data (signals.window(t0, "
                          "t1)) to keep it apart", stacklevel=2)
        # scored where the search scored (its E, and the table's, were of its validate
        # window; refine scored the whole record: value and the table's E disagreed)
        if validate is None and start.validate is not None:
            end = signals.t0 + (signals.n_samples - 1) * signals.host_dt
            half = 0.5 * signals.host_dt
            if signals.t0 - half <= start.validate[0] and start.validate[1] <= end + half:
                validate = start.validate
                if observer_window is None:
                    observer_window = start.observer_window
            else:  # the identification data alone, as the identify warning advises
                warnings.warn(f"refine(): the search's validate window {start.validate} "
                              f"lies outside these signals [{signals.t0:g}, {end:g}]: scored "
                              "on refine's default window instead (give validate= to "
                              "choose)", stacklevel=2)
        elif observer_window is None and validate is None:
            observer_window = start.observer_window
        starts = [start.best(i) for i in range(min(top, len(start)))]
        span = max(_kernel_span(_box(signals, s, bounds), vary, s) for s in starts)
        runs = []
        for s in starts:  # each run's warnings kept apart: those of the run returned are said
            with warnings.catch_warnings(record=True) as caught:  # (every run's were, each
                warnings.simplefilter("always")  # pointing into this file)
                runs.append((refine(signals, s, score=score, vary=vary, bounds=bounds,
                                    validate=validate, observer_window=observer_window,
                                    max_steps=max_steps, rtol=rtol, atol=atol, eta=eta,
                                    _span=span),
                             caught))
        best, caught = min(runs, key=lambda r: r[0].value)  # the returned model's score
        for w in caught:
            warnings.warn(str(w.message), w.category, stacklevel=2)
        return best
    if not isinstance(start, Model) or start.mf is None:
        raise TypeError("refine(): start must be a Model from identify or a SearchResult")
    _b.start_layout("refine", start, signals)
    _b.start_notes("refine", start, signals)
    if score not in ("E", "J"):
        raise ValueError(f"refine(): score must be 'E' or 'J' (got {score!r})")
    bad = sorted(set(vary) - set(SETTINGS))
    if bad or not vary:
        raise ValueError(f"refine(): vary must name some of {SETTINGS} (got {list(vary)})")
    K, dt = signals.n_inputs, signals.dt
    if "delays" in vary and K == 0:
        raise ValueError("refine(): no inputs, nothing to delay")
    box = _box(signals, start, bounds)
    h0, N0, M0 = float(start.mf.h), float(start.mf.N), float(start.mf.M)
    d0 = np.asarray(start.delays, dtype=np.float64).reshape(K)
    x0 = {"h": h0, "N": N0, "M": M0, "delays": d0}
    for key in ("N", "M"):  # eq. 5: an MF of exponent below n has too few derivatives
        if key in vary and float(box[key][0]) < start.structure.n:
            raise ValueError(f"refine(): bounds[{key!r}] must start at n={start.structure.n} or "
                             f"above (got {float(box[key][0]):g}): the modulating function "
                             f"needs {key} >= n; give bounds={{{key!r}: "
                             f"({start.structure.n}, {float(box[key][1]):g})}}")
    for key in vary:
        lo, hi = box[key]
        if np.any(np.asarray(lo) >= np.asarray(hi)) or np.any(x0[key] < lo) or np.any(
                x0[key] > hi):
            raise ValueError(f"refine(): the start {key}={x0[key]} must lie in its bounds "
                             f"[{lo}, {hi}] with lo < hi")
    v0, length, ob = validation_window(signals, validate, observer_window, start.structure.n,
                                       "refine")
    p = start.structure.n_params + int(signals.offset)
    eta = default_eta(p, signals.offset) if eta is None else _b.array(
        "refine", "eta", eta, ndim=1, fix="give the constraint vector the start was identified "
        "with, one entry per parameter")
    if np.shape(eta) != (p,) or not np.any(np.asarray(eta) != 0):
        raise ValueError(f"refine(): eta must have one entry per parameter ({p}), not all zero "
                         f"(got {np.asarray(eta).tolist()})")
    span = _kernel_span(box, vary, start)
    first = kernel_length(span, signals.host_dt) - 1
    need = max(MIN_VALID, 2 * p)
    if signals.n_samples - first < need:  # (the box's far end scored inf, silently unusable)
        raise ValueError(f"refine(): the bounds let h plus the delays reach {span:g}, which "
                         f"leaves the record ({signals.duration:g} time units) "
                         f"{max(signals.n_samples - first, 0)} valid samples, need {need}; "
                         "lower the upper bound of bounds['h'] or bounds['delays']")
    padded, bound, end, valid = _padded_window(signals.unlabelled(), v0, length)
    objective = _Objective(
        signals=padded, lengths=(np.int32(ob), end, valid),
        x0={k: device(v, np.float64) for k, v in x0.items()},
        lo={k: device(box[k][0], np.float64) for k in vary},
        hi={k: device(box[k][1], np.float64) for k in vary},
        eta=device(np.asarray(eta, dtype=np.float64)),
        start=device(v0, np.int32), structure=start.structure, vary=tuple(vary),
        kernel=kernel_bucket(kernel_length(max(_kernel_span(box, vary, start), _span), dt)),
        window=bound, key={"E": "E", "J": "J_rel"}[score],
    )
    z0 = {key: device(_logit(x0[key], *box[key])) for key in vary}
    import optimistix as optx  # here: importing it costs 0.13 s at every CLI start

    # the tolerances as values: Python floats would be static, a program per tolerance
    solver = optx.BFGS(rtol=np.float64(rtol), atol=np.float64(atol))
    # optimistix's first step evaluates the objective at z0 only (and keeps z0); every step
    # returns the last accepted iterate with its value in `state.f_info` (no program of its own)
    z, state = _bfgs_step(solver, objective, z0, _bfgs_init(solver, objective, z0))
    path, result, steps = [float(state.f_info.f)], optx.RESULTS.successful, 0
    best_z, best_f = z0, path[0]
    for steps in range(1, max_steps + 1):
        if steps > 1:  # the first step is the one taken above
            z, state = _bfgs_step(solver, objective, z, state)
        f = float(state.f_info.f)  # the iterate's (a line-search trial may be worse)
        path.append(f)
        if math.isfinite(f) and f < best_f:
            best_z, best_f = z, f
        done, result = _bfgs_terminate(solver, objective, z, state)
        if bool(done):
            break
    else:
        result = optx.RESULTS.max_steps_reached
    code = solver_code(result)
    s_start = {k: _plain(v) for k, v in x0.items()}
    from ._identify import identify

    def at(s):  # the model the objective scored at settings s: identified on these signals
        sig = eqx.tree_at(lambda q: q.delays, signals, device(np.reshape(s["delays"], K)))
        return identify(sig, start.structure, ModulatingFunction(s["N"], s["M"], s["h"]),
                        eta=eta)

    def own(model) -> float:  # the objective's score of `model` itself (the path's first point
        # is that of the start moved into the box, and of its settings' round trip through
        # the sigmoid, which can put a delay on a sample's other side: 5e-6 apart)
        if score == "J":
            val, status = float(model.J_rel), int(model.status)
        else:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                obs = observation(model, signals, validate, observer_window=observer_window)
            val, status = float(obs.E), int(model.status) | int(obs.status)
        return val if status == 0 and math.isfinite(val) and val > 0 else math.inf

    gain = math.log1p(-IMPROVEMENT)  # (log space: a share of the score)
    fresh = at(s_start)  # a search's candidate equals identify's to 1e-8 (tests)
    x, y = (np.concatenate([np.ravel(v) for v in jax.tree.leaves((m.a, m.b, m.offset))])
            for m in (fresh, start))
    same = bool(np.all(np.abs(x - y) <= 1e-8 * np.max(np.abs(y), initial=1e-300)))
    moved = any(_moved(x0[k], *box[k]) for k in vary)
    own_fresh = functools.cache(lambda: own(fresh))  # one observation, where it is needed
    # the start itself, as given (its own eta, its own data); the path's first point where
    # that is the start (no observation program to compile: 0.6 s of a first call)
    # (score "J": a start's own J_rel is of the data it was identified on: its settings' J_rel
    # on these signals stands for it)
    here = math.exp(path[0]) if math.isfinite(path[0]) else math.inf
    start_value = (here if not moved else own_fresh()) if score == "J" else (
        own(start) if moved or not same else here)
    failed = not math.isfinite(path[0]) or best_f >= path[0] + gain or code not in USABLE
    if not failed and moved:  # no better than the start?
        failed = best_f >= math.log(own_fresh()) + gain
    if not failed and score == "E" and best_f >= math.log(start_value) + gain:
        failed = True  # (a start of another eta scored 1.2426; the path's best 1.2440)

    if failed:  # the start, when it is the model its settings give on these signals; else
        # that model, whose score `value` is (a start identified on other data was returned
        # beside the score of another model: 0.00997 against its own 3.73), unless the
        # start itself scores better there
        better = score == "E" and start_value <= own_fresh()
        model, what = (start, "the start") if same or better else (
            fresh, "the start's settings identified on these signals (the start differs: "
                   "identified on other data, another window or another eta)")
    if not (math.isfinite(path[0]) or math.isfinite(best_f)):  # nothing to refine from (it
        # said "not converged (max_steps_reached)" of a start flagged no_excitation)
        warnings.warn(f"refine(): the start scores {score} = inf on these signals (status "
                      f"{describe(int(fresh.status))}: a flagged model, or one whose simulation "
                      "failed), and so did every point tried: nothing to refine; returning "
                      f"{what} (check the data, e.g. an input that is constant, and the start)",
                      stacklevel=2)
    elif code != "successful":
        warnings.warn(f"refine(): not converged ({code} after {steps} steps); returning "
                      f"{what if failed else 'the best point of the path'} (see "
                      "Refinement.converged)", stacklevel=2)
    elif failed:  # converged without improving: still say it (a BFGS that rejected every
        # step from h on a sample multiple, where E jumps, returned "successful", unsaid)
        warnings.warn(f"refine(): no improvement on the start (BFGS stopped at it, or scored "
                      f"every step it tried worse); returning {what}", stacklevel=2)
    if failed:
        return Refinement(model, start, s_start, s_start, np.exp(np.asarray(path)), code, steps,
                          own(model), score, start_value)
    s = {k: _plain(v) for k, v in _host_settings(x0, box, best_z).items()}
    _edges("refine", s, box, vary, start.structure.n, set(bounds or {}))
    return Refinement(at(s), start, s, s_start, np.exp(np.asarray(path)), code, steps,
                      math.exp(best_f), score, start_value)


def _edges(fn: str, s: dict, box: dict, vary, n: int, given=frozenset()) -> None:
    """Warn of refined settings that ended at an edge of their box that is not a physical
    limit (a delay of 0 and N = n or M = n are: nothing lies beyond them); an edge of the
    default box (keys not in `given`) is named as refine's own."""
    ends = []
    for key in vary:
        lo, hi = (np.broadcast_to(np.asarray(b, dtype=np.float64), np.shape(s[key]))
                  for b in box[key])
        v, tol = np.asarray(s[key], dtype=np.float64), AT_BOUND * (hi - lo)
        for i in np.ndindex(v.shape):
            name = key if v.ndim == 0 else f"{key}[{i[0]}]"
            own = "" if key in given else " (refine's default box)"
            physical_lo = key == "delays" and lo[i] <= 0 or key in ("N", "M") and lo[i] <= n
            if v[i] >= hi[i] - tol[i]:
                ends.append(f"{name} = {float(v[i]):.6g} at its upper bound "
                            f"{float(hi[i]):.6g}{own}")
            elif v[i] <= lo[i] + tol[i] and not physical_lo:
                ends.append(f"{name} = {float(v[i]):.6g} at its lower bound "
                            f"{float(lo[i]):.6g}{own}")
    if ends:
        warnings.warn(f"{fn}(): {'; '.join(ends)}: the optimum may lie beyond the box; widen "
                      "it with bounds={...} (or accept the edge)", stacklevel=3)


def _box(signals: Signals, start: Model, bounds) -> dict:
    """The settings' box: `refine`'s defaults around `start`, overridden by `bounds`."""
    K, n, dt, duration = signals.n_inputs, start.n, signals.dt, signals.duration
    h0 = float(start.mf.h)
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
    return box


def _kernel_span(box: dict, vary, start: Model) -> float:
    """The largest h + delay the box lets the kernels meet (fixes their static length)."""
    d0 = np.asarray(start.delays, dtype=np.float64)
    h_top = float(np.max(box["h"][1]) if "h" in vary else float(start.mf.h))
    return h_top + float(np.max(box["delays"][1]) if "delays" in vary
                         else np.max(d0, initial=0.0))


def _plain(v):
    v = np.asarray(v, dtype=np.float64)
    return float(v) if v.ndim == 0 else [float(x) for x in v]


@jit
def _bfgs_init(solver, fn, y):
    f_struct = jax.ShapeDtypeStruct((), jnp.float64)
    return solver.init(fn, y, None, {}, f_struct, None, frozenset())


@jit
def _bfgs_step(solver, fn, y, state):
    y, state, _ = solver.step(fn, y, None, {}, state, frozenset())
    return y, state


@jit
def _bfgs_terminate(solver, fn, y, state):
    return solver.terminate(fn, y, None, {}, state, frozenset())
