r"""`estimate`: one call from data to a consistent model with its uncertainty.

search (MFM over every structure and modulating-function setting of a grid, eq. 1-17), the
structure chosen on held-back data (`_selection`) or by BIC
-> SRIVC from the winner (`srivc`: consistent under output noise, CRB-level spread)
-> an output-error polish (`output_error`) when it predicts the held-back data better.
The MFM closed form stays the initialiser: it is fast and exact on noise-free data, but its
equation error is biased under output noise; SRIVC removes that bias at a few ms per fit.
"""

from __future__ import annotations

import warnings

import equinox as eqx
import numpy as np

from ._model import Model
from ._observers import fit_percent, observe
from ._output_error import OutputErrorFit, free_parameters, output_error, stabilised
from ._pytree import replace_fields
from ._search import SearchResult, search
from ._selection import OBSERVER_FRACTION, holdout_search, rank_by
from ._signals import Signals
from ._srivc import SrivcFit, srivc
from ._status import describe


class Estimate(eqx.Module):
    """Result of `estimate`: the model, the path that produced it and its uncertainty."""

    model: Model  # the returned model
    start: Model  # the search's winner (the MFM estimate)
    search: SearchResult  # ranked by the selection rule (hold-out E or BIC)
    srivc: SrivcFit | None
    output_error: OutputErrorFit | None
    names: tuple  # free parameters, ordered as std_errors
    std_errors: np.ndarray
    covariance: np.ndarray  # of the free parameters, ordered as names (the last stage's)
    converged: bool  # the returned stage met its tolerance
    stabilised: bool  # the MFM winner had right-half-plane poles, mirrored before SRIVC
    method: str  # "mfm", "srivc", "srivc + output error" or "output error"
    selection: str  # how the structure was chosen, in words
    holdout: dict  # hold-out fit % of each stage tried ({} with selection="bic")
    notes: tuple  # data decisions (offset rule) and fallbacks, in words

    def summary(self) -> str:
        """The model, the standard errors, how it was reached and whether it converged."""
        lines = [self.model.summary(), f"method: MFM search -> {self.method}",
                 f"selection: {self.selection}"]
        if self.holdout:
            lines.append("hold-out fit %: " + ", ".join(
                f"{k} {v:.1f}" for k, v in self.holdout.items()))
        lines.append(f"{'parameter':<12}{'std error':>14}")
        lines += [f"{k:<12}{float(v):>14.3e}" for k, v in zip(self.names, self.std_errors)]
        lines += list(self.notes)
        if self.stabilised:
            lines.append("the MFM winner was unstable: its right-half-plane poles were mirrored")
        lines.append("converged" if self.converged else
                     "NOT CONVERGED: the estimate is the best iterate; its standard errors are "
                     "not trustworthy" + (f" (SRIVC: {self.srivc.describe()})"
                                          if self.srivc is not None else ""))
        return "\n".join(lines)


SELECTIONS = ("holdout", "bic")
POLISH_GAIN = 0.05  # a stage must lower the hold-out E by 5 % to replace a more robust one


def estimate(
    signals: Signals, *, h, n=(1, 2, 3), N=(3, 4, 5), M=(3, 4, 5), m=None, delays=None,
    selection: str = "holdout", holdout: float = 1 / 3, folds: int = 1, identify=None,
    score: str = "bic",
    validate=None, polish: bool | None = None, max_iter: int = 30, tol: float = 1e-8,
) -> Estimate:
    r"""Identification in one call: `search` -> `srivc` -> (`output_error`), every choice made
    on data the candidate was not fitted on.

    - `selection="holdout"` (default): the last `holdout` share (1/3) of the estimation data
      (`identify`: a window or a list of windows, default the record) is left out of the Gram,
      and with `folds=2` (one estimation window) the first share too, in turn; every
      candidate of the grid is scored by its mean simulation error E (eq. 17) on the blocks
      it was not fitted on, the state from the initial-state observer over each block's first
      20 %; the winner is re-identified on all estimation data. `selection="bic"`: BIC
      ($N \ln(E/T) + k \ln N$, `score` and `validate` as in `search`) on the estimation
      data, the previous default.
    - Stages: the winner (stabilised: right-half-plane poles mirrored) starts SRIVC (exact
      prefilters, instruments from the noise-free auxiliary model), which removes the
      equation-error bias of MFM under output noise. `polish=None` (default) tries an
      output-error fit too and keeps it when it lowers the hold-out E by `POLISH_GAIN` (5 %).
      The best `STRUCTURES` (8) structures of the search go through SRIVC; the plain MFM
      estimate is kept only where it predicts the hold-out 5 % better than every SRIVC fit
      (real data whose noise is not white can favour it); a stage that did not converge is
      not kept (each stage's hold-out fit is in `holdout`). `polish=True`/`False` forces it.
    - `folds=2` holds out the first third too (fitted on the last two thirds): on plant data
      it chose better (benchmarks/real_data.py uses it), but SRIVC's filters start from rest,
      so on a fit part that starts mid-record SRIVC is penalised by its start-up transient;
      the default `folds=1` fits from the record's start.
    - Grid arguments are those of `search`, except the default `m`: with hold-out selection
      it is m_k = 0..n for every input (direct feed-through, m_k = n, included; a strictly
      proper model wins unless the lag-0 term predicts the held-back data better); with
      `selection="bic"` it is search's 0..n-1.

    **Returns:** `Estimate`: `model`, `std_errors` and `covariance` (SRIVC's IV covariance,
    or output error's Gauss-Newton covariance; NaN for the plain MFM stage), `converged`,
    `selection`, `holdout` and every stage's result. A stage that did not converge says so
    in `converged` and `summary()`, and warns.
    """
    if polish is not None and not isinstance(polish, bool):
        raise TypeError(f"estimate(): polish must be True or False (or None: decided on the "
                        f"hold-out data), got {polish!r}")
    if selection not in SELECTIONS:
        raise ValueError(f"estimate(): selection must be one of {SELECTIONS} "
                         f"(got {selection!r})")
    notes = (signals.offset_note,) if signals.offset_note else ()
    if selection == "bic":
        if identify is not None:
            raise ValueError("estimate(): identify windows need selection='holdout'")
        res = search(signals, n=n, N=N, M=M, h=h, m=m, delays=delays, score=score,
                     validate=validate)
        out = estimate_from_search(signals, res, polish=bool(polish), max_iter=max_iter,
                                   tol=tol)
        return replace_fields(out, notes=notes + out.notes)
    if m is None:  # feed-through (m_k = n) in the grid: the held-back data decide if it is used
        m = [list(range(int(np.max(n)) + 1))] * signals.n_inputs
    sel = holdout_search(signals, estimation=identify, holdout=holdout, folds=folds, n=n, N=N,
                         M=M, h=h, m=m, delays=delays)
    if len(sel.refit) == 0:
        raise ValueError("estimate(): the search grid has no feasible candidate; widen N, M or h")
    j_bic = int(rank_by(sel.refit, "bic")[0])
    by_bic = (int(sel.refit.columns["n"][j_bic]), [int(v) for v in sel.refit.columns["m"][j_bic]])
    blocks = " and ".join(f"[{w[0]:g}, {w[1]:g}]" for _, w in sel.folds)
    selection_text = (f"mean hold-out E over {blocks} ({holdout:.0%} of the estimation data "
                      f"each, fitted on the rest); BIC on the estimation data would pick "
                      f"n={by_bic[0]} m={by_bic[1]}")
    if len(sel.estimation) > 1:
        # several experiments: the stages after MFM simulate one record; keep MFM
        start = sel.refit.best(0)
        model = start.labelled(signals.output_name, signals.input_names)
        names = free_parameters(start)[0]
        nan = np.full(len(names), np.nan)
        return Estimate(model, start, sel.refit, None, None, names, nan, np.diag(nan), True,
                        False, "mfm", selection_text, {}, notes + (
                            "several estimation windows: the MFM estimate of their summed "
                            "Grams is returned (SRIVC and output error need one record)",))
    est_sig = signals.window(*sel.estimation[0])
    folds_data = []
    for (fit_w,), hold in sel.folds:
        ob = OBSERVER_FRACTION * (hold[1] - hold[0])
        folds_data.append((signals.window(*fit_w), hold, ob, np.asarray(signals.window(*hold).y)))

    def hold_score(models):
        """Mean hold-out E over the folds and the mean fit % (one model per fold)."""
        Es, fits = [], []
        for model, (_, hold, ob, y_hold) in zip(models, folds_data):
            try:
                o = observe(model, signals, hold, observer_window=ob)
            except ValueError:  # overflow / unobservable on the hold-out: not usable
                return np.inf, np.nan
            Es.append(float(o.E))
            fits.append(float(fit_percent(y_hold, o.y_sim)))
        return float(np.mean(Es)), float(np.mean(fits))

    def per_fold(stage, starts, **kw):
        """The stage's model on each fold (its best iterate when it stopped early: the
        hold-out E judges it), or None when it could not run on a fold."""
        outs = [_staged(stage, f[0], s0, **kw) for s0, f in zip(starts, folds_data)]
        return [o.model for o in outs] if all(o is not None for o in outs) else None

    # every stage fitted on each fold's fit part and compared on its hold-out block: the MFM
    # winner of each of the best `STRUCTURES` structures, and SRIVC from it; then output
    # error on the best
    tried = []  # (mean hold-out E, mean hold-out fit, rank, stage, per-fold models)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for i in _best_per_structure(sel.refit, STRUCTURES):
            firsts = [r.best(i) for r in sel.fitted]
            tried.append((*hold_score(firsts), i, "mfm", firsts))
            seeds = [stabilised(f)[0] for f in firsts]
            sv = per_fold(srivc, seeds, max_iter=max_iter, tol=tol)
            if sv is not None:
                tried.append((*hold_score(sv), i, "srivc", sv))
        # the consistent estimator is preferred: plain MFM (biased under output noise) must
        # predict the hold-out better by POLISH_GAIN, as output error must to replace SRIVC
        best = min(tried, key=lambda r: r[0] / (1 - POLISH_GAIN) if r[3] == "mfm" else r[0])
        if polish is not False:
            bases = best[4] if best[3] == "srivc" else [
                stabilised(r.best(best[2]))[0] for r in sel.fitted]
            oe = per_fold(output_error, bases)
            if oe is not None:
                stage = "srivc + output error" if best[3] == "srivc" else "output error"
                E_oe, fit_oe = hold_score(oe)
                if polish or E_oe < (1 - POLISH_GAIN) * best[0]:
                    best = (E_oe, fit_oe, best[2], stage, oe)
    i, method = best[2], best[3]
    held = {f"{r[3]} n={r[4][0].n} m={list(r[4][0].m)}": r[1] for r in tried}
    held[f"chosen: {method}"] = best[1]
    # the chosen stage on all estimation data, from the same candidate re-identified there
    start = sel.refit.best(i)
    seed, was_unstable = stabilised(start)
    fit, oe, cov, model, names, converged = None, None, None, start, (), True
    if method != "mfm":
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            if method != "output error":
                fit = _staged(srivc, est_sig, seed, max_iter=max_iter, tol=tol)
                if fit is not None:
                    model, names, cov = fit.model, fit.names, np.asarray(fit.covariance)
                    converged = bool(fit.converged)
            if method.endswith("output error"):
                oe = _staged(output_error, est_sig, model if fit is not None else seed)
                if oe is not None:
                    model, names, cov, converged = oe.model, oe.names, \
                        np.asarray(oe.covariance), oe.converged
        if cov is None:
            notes = notes + (f"{method} could not simulate on all estimation data: the MFM "
                             "estimate is returned",)
            method = "mfm"
        if not converged:
            for w in caught:
                warnings.warn(str(w.message), stacklevel=2)
    if cov is None:
        model, names = start, free_parameters(start)[0]
        cov = np.full((len(names), len(names)), np.nan)
        notes = notes + ("no standard errors: the plain MFM estimate is returned (it predicted "
                         "the held-back data best, or the stages after it failed)",)
    std = np.sqrt(np.abs(np.diagonal(cov)))
    model = model.labelled(signals.output_name, signals.input_names)
    if method != "mfm" and signals.offset:
        notes = notes + ("SRIVC / output error ran on data with the estimation means removed; "
                         "the offset term is mapped back to the original levels",)
    return Estimate(model, start, sel.refit, fit, oe, tuple(names), std, cov, converged,
                    was_unstable, method, selection_text, held, notes)


STRUCTURES = 8  # structures whose best setting goes on to SRIVC in the hold-out comparison


def _best_per_structure(res: SearchResult, count: int) -> list[int]:
    """Ranks (in `res`) of the best candidate of each of the first `count` structures."""
    seen, out = set(), []
    c = res.columns
    for i in range(len(res)):
        j = int(res.rank[i])
        key = (int(c["n"][j]), tuple(int(v) for v in c["m"][j]))
        if key not in seen and int(c["status"][j]) == 0:
            seen.add(key)
            out.append(i)
            if len(out) == count:
                break
    return out or [0]


def _staged(stage, signals: Signals, model: Model, **kw):
    r"""`stage` (srivc or output_error) from `model` with its delays, on data with the means
    removed when the model has an offset term: the filters and simulations start from rest
    and the free parameters are scaled by their magnitude, so a level far from zero (97 degC
    on the heat exchanger) would swamp them. The offset maps exactly between the two levels:
    $b_{off}' = b_{off} + \sum_k b_{k0} \bar u_k - a_0 \bar y$. Returns None if the stage
    raised (e.g. an overflowing simulation)."""
    signals = _with(signals, model)
    ybar, ubar = (0.0, np.zeros(signals.n_inputs))
    if model.has_offset:
        ybar, ubar = float(np.mean(signals.y)), np.asarray(np.mean(signals.u, axis=0))
        signals = eqx.tree_at(lambda q: (q.y, q.u), signals,
                              (signals.y - ybar, signals.u - ubar))
        model = _shift_offset(model, ybar, ubar, +1.0)
    try:
        out = stage(signals, model, **kw)
    except ValueError:
        return None
    if not model.has_offset:
        return out
    back = _shift_offset(out.model, ybar, ubar, -1.0)
    # covariance of (.., b_k0, .., offset): d offset / d a_0 = ybar, d / d b_k0 = -ubar_k
    J = np.eye(len(out.names))
    row = out.names.index("offset")
    for name, val in [("a_0", ybar)] + [(f"b_{k + 1}0", -ubar[k]) for k in range(len(ubar))]:
        if name in out.names:
            J[row, out.names.index(name)] = val
    cov = J @ np.asarray(out.covariance) @ J.T
    return replace_fields(out, model=back, covariance=cov,
                          std_errors=np.sqrt(np.abs(np.diagonal(cov))))


def _shift_offset(model: Model, ybar: float, ubar, sign: float) -> Model:
    """The same model with the offset term for data shifted by -(ybar, ubar) (sign +1) or back."""
    shift = sum(float(bk[0]) * float(ubar[k]) for k, bk in enumerate(model.b)) - \
        float(model.a[0]) * ybar
    return eqx.tree_at(lambda q: q.offset, model, model.offset + sign * shift)


def _with(signals: Signals, model: Model) -> Signals:
    return eqx.tree_at(lambda q: q.delays, signals, model.delays)


def estimate_from_search(signals: Signals, res: SearchResult, *, polish: bool = False,
                         max_iter: int = 30, tol: float = 1e-8) -> Estimate:
    """The stages of `estimate` after its search, from a `SearchResult` of `signals` (the
    winner's delays are used)."""
    if len(res) == 0:
        raise ValueError("estimate(): the search grid has no feasible candidate; widen N, M or h")
    start = res.best(0)
    signals = eqx.tree_at(lambda q: q.delays, signals, start.delays)  # the winner's delays
    if int(start.status) != 0:
        warnings.warn(f"estimate(): every candidate is flagged; starting from the best one "
                      f"({describe(int(start.status))})", stacklevel=2)
    seed, was_unstable = stabilised(start)
    fit = _staged(srivc, signals, seed, max_iter=max_iter, tol=tol)
    if fit is None:
        raise ValueError("estimate(): SRIVC could not simulate the search's winner on this "
                         "record; try selection='holdout' or a smaller grid")
    model, names, std = fit.model, fit.names, np.asarray(fit.std_errors)
    cov = np.asarray(fit.covariance)
    converged, method, oe = bool(fit.converged), "srivc", None
    if polish:
        oe = _staged(output_error, signals, model)
        model, names, std = oe.model, oe.names, np.asarray(oe.std_errors)
        cov = np.asarray(oe.covariance)
        converged, method = oe.converged, "srivc + output error"
    model = model.labelled(signals.output_name, signals.input_names)
    return Estimate(model, start, res, fit, oe, tuple(names), std, cov, converged, was_unstable,
                    method, f"{res.score.upper()} on the estimation data", {}, ())


def estimate_outputs(records, **kwargs) -> tuple[Estimate, ...]:
    """Multi-output data: one MISO model (eq. 1) per output, each by `estimate`.

    `records`: one `Signals` per output, with the same inputs, sampling and rules (e.g.
    `Signals.from_columns(cols, output=name, ...)` for each output column). Each output gets
    its own denominator A(s): outputs of a plant measured at different places (the glass
    furnace's six temperatures) have different dominant dynamics, and a common denominator
    would force one set of poles on all of them (a state-space method such as N4SID shares
    them). The records have equal shapes, so all outputs share the compiled programs.
    `kwargs` are those of `estimate`. **Returns:** one `Estimate` per record, in order.
    """
    if isinstance(records, Signals):
        records = [records]
    if not isinstance(records, list | tuple) or not records or \
            not all(isinstance(r, Signals) for r in records):
        raise TypeError("estimate_outputs(): records must be a list of Signals, one per output")
    first = records[0]
    for i, r in enumerate(records[1:], 1):
        same = (r.dt == first.dt and r.n_samples == first.n_samples
                and r.u.shape == first.u.shape and bool(np.array_equal(r.u, first.u)))
        if not same:
            raise ValueError(f"estimate_outputs(): record {i} does not share record 0's inputs "
                             "and sampling; give one Signals per output of one experiment")
    return tuple(estimate(r, **kwargs) for r in records)
