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
import jax
import numpy as np

from . import _boundary as _b
from ._analysis import RESIDUAL_LAGS, exact_floor
from ._batch import as_records, map_pairs, overlapped
from ._boundary import check_search
from ._model import Model, is_stable
from ._observers import fit_percent, validation_window
from ._output_error import (
    OutputErrorFit,
    free_parameters,
    output_error,
    output_error_many,
    stabilised,
)
from ._padded import observe_candidate, padded_model
from ._pytree import replace_fields
from ._quadrature import record_bucket
from ._search import SearchResult, plan_search, run_plan
from ._search._grid import CHUNK_SETTINGS, delay_edge_notes, delay_grids, grid_values, structures
from ._selection import OBSERVER_FRACTION, HoldoutSearch, holdout_folds, holdout_search, rank_by
from ._signals import (
    Signals,
    dependent_inputs,
    held_inputs_note,
    nearly_dependent_inputs,
    offset_undecided,
    output_start,
)
from ._srivc import MAX_ITER_LIMIT, SrivcFit, srivc, srivc_many
from ._status import Status, describe


class Estimate(eqx.Module):
    """Result of `estimate`: the model, the path that produced it and its uncertainty."""

    model: Model  # the returned model
    start: Model  # the search's winner (the MFM estimate)
    search: SearchResult  # ranked by the selection rule (hold-out E: its E_holdout column, or BIC)
    srivc: SrivcFit | None
    output_error: OutputErrorFit | None
    names: tuple  # free parameters, ordered as std_errors
    std_errors: np.ndarray
    covariance: np.ndarray  # of the free parameters, ordered as names (the last stage's)
    converged: bool  # the returned stage met its tolerance and its model is not flagged
    stabilised: bool  # the MFM winner had right-half-plane poles, mirrored before SRIVC
    method: str  # "mfm", "srivc", "srivc + output error" or "output error"
    selection: str  # how the structure was chosen, in words
    holdout: dict  # hold-out fit % of each stage tried ({} with selection="bic")
    notes: tuple  # data decisions (offset rule) and fallbacks, in words
    score: float = float("nan")  # the chosen stage's hold-out E x FPE factor (`parsimonious`)
    # each input's delay std error where its delay was picked from a grid and then fitted
    # (`_delays_fitted`; NaN for an input whose delay was held, inf for one fitted down to
    # its bound 0); None: the delays are held
    delay_std_errors: np.ndarray | None = None
    # with `delay_std_errors`: the covariance of (names..., every input's delay) (p + K, p + K),
    # held delays with zero rows (`OutputErrorFit.joint_covariance`; the bands read it)
    joint_covariance: np.ndarray | None = None

    def summary(self) -> str:
        """The model, the standard errors, how it was reached and whether it converged."""
        lines = [self.model.summary(), f"method: MFM search -> {self.method}",
                 f"selection: {self.selection}"]
        if self.holdout:
            lines.append("hold-out fit %: " + ", ".join(  # -1e25 % reads as "< -1000"
                f"{k} {v:.1f}" if v >= -1000 else f"{k} not usable" if v != v else f"{k} < -1000"
                for k, v in self.holdout.items()))
        lines.append(f"{'parameter':<12}{'std error':>14}")
        lines += [f"{k:<12}{float(v):>14.3e}" for k, v in zip(self.names, self.std_errors)]
        if self.delay_std_errors is not None:
            lines += [f"{'delay ' + k:<12}{float(e):>14.3e}  (fitted: {float(d):.6g})"
                      for k, d, e in zip(self.model.input_names, np.asarray(self.model.delays),
                                         self.delay_std_errors) if not np.isnan(e)]
        lines += list(self.notes)
        if self.stabilised:
            lines.append("the MFM winner was unstable: its right-half-plane poles were mirrored")
        flags = int(self.model.status) & FLAGGED
        lines.append(f"NOT USABLE: the model is flagged ({describe(flags)})" if flags else
                     # (it read "converged" beside NaN standard errors, after SRIVC had failed)
                     "plain MFM estimate: a closed form (nothing to converge), without "
                     "standard errors" if self.method == "mfm" and self.converged else
                     "converged" if self.converged else
                     "NOT CONVERGED: the estimate is the best iterate; its standard errors are "
                     "not trustworthy" + (f" (SRIVC: {self.srivc.describe()})"
                                          if self.srivc is not None else ""))
        return "\n".join(lines)


SELECTIONS = ("holdout", "bic")
# status bits that make the returned model unusable (unstable and ill-conditioned models are
# returned with their own notes)
FLAGGED = (Status.NONFINITE | Status.NO_EXCITATION | Status.A_N_ZERO | Status.UNOBSERVABLE
           | Status.OVERFLOW | Status.OUT_OF_BOUNDS)
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
      output-error fit too and keeps it when it lowers SRIVC's hold-out E by `POLISH_GAIN`
      (5 %), or unless plain MFM's is 5 % lower (where it does not converge on all
      estimation data, the MFM estimate is returned).
      The best `STRUCTURES` (8) structures of the search, and at most `NESTED` (8) structures
      nested in them (one numerator order lower, level by level), each with its best setting at
      each of its grid delays (at most `DELAYS`, 12), go through SRIVC; the plain MFM
      estimate is kept only where it predicts the hold-out 5 % better than every SRIVC fit
      and than the output-error polish (real data whose noise is not white can favour it).
      Structures compete on the hold-out E times Akaike's FPE factor $(1 + 2k/N_h)$ (k free
      parameters, $N_h$ hold-out samples; `parsimonious`), so a structure nesting a smaller
      one must predict measurably better; SRIVC structures within `HOLDOUT_TIE` (5 %) of
      the best are near ties, decided by BIC over all estimation data (fit parts' simulation
      error, every parameter paying ln T, plus the hold-out blocks'; `near_tie_by_bic`).
      Where the winner's SRIVC does not converge on all estimation data, the next-ranked SRIVC
      candidate that converges is returned (up to `FALLBACKS` tries), else output error from
      SRIVC's best iterate where it converges, else that iterate (said in `notes`). Each
      stage's hold-out fit is in `holdout`. `polish=True`/`False` forces the polish.
      With `polish=None`, a record that does not start at rest (`residual_notes`) gets output
      error from SRIVC's estimate where it converges (`_from_rest_to_output_error`).
    - `folds=2` holds out the first third too (fitted on the last two thirds): on plant data
      it chose better (benchmarks/real_data.py uses it), but SRIVC's filters start from rest,
      so on a fit part that starts mid-record SRIVC is penalised by its start-up transient;
      the default `folds=1` fits from the record's start.
    - An offset term the default rule cannot decide (`offset_undecided`: the output starts
      away from zero with an input away from zero, e.g. a heater on from the first sample)
      is chosen like a structure (`selection="holdout"`; with "bic" the rule's choice, off,
      stands, and a warning says so): the hold-out search and the stages run with it too,
      and it is kept where the returned stage's hold-out E times the FPE factor is
      `OFFSET_GAIN` (5 %) lower, or within `HOLDOUT_TIE` (5 %) with fewer free parameters;
      `notes` gives both. A record with an offset term runs its
      SRIVC and output-error stages on data shifted by their starting levels and by their
      means, and keeps the better on the held-back data (`_holdout_variants`). A batch
      decides per record.
    - Grid arguments are those of `search`, except the default `m`: with hold-out selection
      it is m_k = 0..n for every input (direct feed-through, m_k = n, included; a strictly
      proper model wins unless the lag-0 term predicts the held-back data better); with
      `selection="bic"` it is search's 0..n-1.

    - A delay grid (`delays=` with more than one value for an input): the chosen SRIVC or
      output-error estimate is refitted by output error with those delays fitted too
      (`_delays_fitted`, unless `polish=False`), so the delays leave the grid and the standard
      errors count their uncertainty (`delay_std_errors`); where that fit does not converge
      or comes out unstable, the grid's delays stay and a note says the standard errors hold
      them known.

    **Returns:** `Estimate`: `model`, `std_errors` and `covariance` (SRIVC's IV covariance,
    or output error's Gauss-Newton covariance; NaN for the plain MFM stage),
    `delay_std_errors` (fitted delays), `converged`, `selection`, `holdout` and every stage's
    result. A stage that did not converge says so
    in `converged` and `summary()`, and warns.
    """
    records, single = as_records("estimate", signals)
    _b.eager_only("estimate", records, h, n, N, M, m, delays, identify, validate)
    for r, rec in enumerate(records):  # (it reached fit_percent's error, named "y")
        y = np.asarray(rec.y)
        if y.size and np.all(y == y[0]):
            raise ValueError(f"estimate(): the output {rec.output_name!r}"
                             f"{'' if single else f' of record {r}'} is constant ({y[0]:.6g}) "
                             "over the whole record: there is no response to identify; check "
                             "the column (a frozen or disconnected sensor?)")
    if delays is None:  # the batch is planned once: record 0's delays served every record
        for i, r in enumerate(records[1:], 1):
            if not np.array_equal(np.asarray(r.delays), np.asarray(records[0].delays)):
                raise ValueError(f"estimate(): record {i} has the input delays "
                                 f"{np.asarray(r.delays).tolist()} and record 0 "
                                 f"{np.asarray(records[0].delays).tolist()}; a batch uses one "
                                 "set: give a delay grid (delays=...) to search them, or call "
                                 "estimate on each record")
    if polish is not None and not isinstance(polish, bool):
        raise TypeError(f"estimate(): polish must be True or False (or None: decided on the "
                        f"hold-out data), got {polish!r}")
    if selection not in SELECTIONS:
        raise ValueError(f"estimate(): selection must be one of {SELECTIONS} "
                         f"(got {selection!r})")
    max_iter = _b.integer("estimate", "max_iter", max_iter, lo=1, hi=MAX_ITER_LIMIT,
                          fix="give the largest number of SRIVC solves")
    tol = _b.number("estimate", "tol", tol, lo=0, lo_open=True,
                    fix="give a relative parameter change such as 1e-8")
    first = records[0]
    if selection == "bic":
        if identify is not None:
            raise ValueError("estimate(): identify windows need selection='holdout'")
        kw = dict(n=n, N=N, M=M, h=h, m=m, delays=delays, score=score, validate=validate,
                  observer_window=None, eta=None, chunk_size=CHUNK_SETTINGS, simulate=True)
        check_search(first, progress=None, fn="estimate", **kw)
        plan = plan_search(first, **kw)
        stages = dict(polish=bool(polish), max_iter=max_iter, tol=tol)
        results = overlapped(lambda: run_plan(plan, first, records=records),
                             _rehearsal(records, kw, stages))
        if validate is not None:  # the window its E is of (refine of `Estimate.search`
            # scores there: it scored the whole record, 0.0338 for the table's 0.0112)
            window = (float(validate[0]), float(validate[1]))
            results = [replace_fields(r, validate=window) for r in results]
        outs = _from_search(records, results, **stages)
        for r, rec in enumerate(records):
            if offset_undecided(rec):  # no held-back data to decide it on
                which = "" if single else f" (record {r})"
                text = ("the default rule left the offset term off, but the data do not say "
                        "whether the output at zero input is zero (see the note above); "
                        "selection='bic' keeps the rule's choice: pass offset=True if the "
                        "output has a level of its own, or use selection='holdout', which "
                        "decides it on held-back data")
                outs[r] = replace_fields(outs[r], notes=outs[r].notes + (text,))
                warnings.warn(f"estimate(){which}: {text}", stacklevel=2)
    else:
        n_grid = _b.integers("estimate", "n", n, lo=1,
                             fix="orders are whole numbers, e.g. n=(1, 2, 3)")
        if m is None:  # feed-through (m_k = n) in the grid: the held-back data decide
            m = [list(range(max(n_grid) + 1))] * first.n_inputs
        grid = dict(n=n, N=N, M=M, h=h, m=m, delays=delays)
        # the grid's kinds and ranges as `search` checks them (h='25' ran: read as 25.0)
        check_search(first, score="E", validate=None, observer_window=None, eta=None,
                     chunk_size=CHUNK_SETTINGS, simulate=True, progress=None, identify=identify,
                     fn="estimate", **grid)
        if polish is True and identify is not None and len(_b.window_list(identify)) > 1:
            warnings.warn("estimate(): polish=True is not applied: with several estimation "
                          "windows the MFM estimate of their summed Grams is returned (SRIVC "
                          "and output error need one record)", stacklevel=2)
        stages = dict(holdout=holdout, polish=polish, max_iter=max_iter, tol=tol)
        sels = holdout_search(first, estimation=identify, holdout=holdout, folds=folds,
                              records=records, meanwhile=_rehearsal(
                                  records, grid, stages, holdout_folds(first, identify,
                                                                       holdout, folds)),
                              **grid)
        records, outs = _holdout_variants(records, sels, stages, dict(
            estimation=identify, holdout=holdout, folds=folds, **grid))
    outs = [replace_fields(o, notes=((r.offset_note,) if r.offset_note else ())
                           + held_inputs_note(r) + o.notes) for o, r in zip(outs, records)]
    edges = [] if delays is None else delay_grids(delays)
    doubtful = {}  # warned once per batch: {first record's text: records}
    n_top = max(grid_values(n, "n"))
    if identify is None:
        checked = residual_notes(records, outs, n_top)
    elif len(_b.window_list(identify)) == 1:  # on the estimation window only (on the record
        # they read the data the user kept back, and across a concatenated record's junctions)
        window = _b.window_list(identify)[0]
        checked = residual_notes([rec.window(*window) for rec in records], outs, n_top)
    else:  # several windows (experiments laid end to end?): no residual test across them
        checked = [(("residual tests not run: several estimation windows (run residuals("
                     "model, record.window(t0, t1)) on each)",), False, False)] * len(outs)
    # the stages after MFM fit the estimation data (one window, else the record)
    est_records = records if identify is None or len(_b.window_list(identify)) > 1 else [
        rec.window(*_b.window_list(identify)[0]) for rec in records]
    tested = [o.model for o in outs]  # the models `checked` describes
    if polish is None:  # not at rest: output error (it fits x0) where it converges
        outs = _from_rest_to_output_error(est_records, outs, checked, n_top)
    grid_mask = tuple(len(set(v)) > 1 for v in edges)  # the inputs whose delays were searched
    if polish is not False and any(grid_mask):
        outs = _delays_fitted(est_records, outs, grid_mask, n_top)
    # the residual tests of the models those stages replaced described SRIVC's: test the new
    changed = [r for r, o in enumerate(outs) if o.model is not tested[r]]
    for r, again in zip(changed, residual_notes([est_records[r] for r in changed],
                                                [outs[r] for r in changed], n_top)
                        if changed else ()):
        checked[r] = again
    # the returned models' own checks, after every stage (an output-error refit can move them)
    outs = [replace_fields(o, notes=o.notes + unstable_note(o.model)) for o in outs]
    unstable = [r for r, o in enumerate(outs) if unstable_note(o.model)]
    if unstable:  # in the notes and the summary, and said where the user looks first
        warnings.warn(f"estimate(){_which(unstable, len(outs), single)}: "
                      f"{unstable_note(outs[unstable[0]].model)[0]}", stacklevel=2)
    for r, (o, rec) in enumerate(zip(outs, records)):
        dependent = dependent_inputs(rec, o.model.delays)  # under the model's own delays
        if dependent:  # the gains and their standard errors are meaningless
            which = "" if single else f" (record {r})"
            text = (f"the inputs {list(dependent)} are linearly dependent (one is a multiple "
                    "of the others): their gains and standard errors are meaningless; drop all "
                    "but one of them")
            status = np.int32(int(o.model.status) | Status.ILL_CONDITIONED)
            outs[r] = replace_fields(o, model=replace_fields(o.model, status=status),
                                     notes=o.notes + (text,))
            warnings.warn(f"estimate(){which}: {text}", stacklevel=2)
            continue
        nearly, ratio = nearly_dependent_inputs(rec, o.model.delays)
        if nearly:  # not singular, but the held-back data are as collinear as the rest
            which = "" if single else f" (record {r})"
            text = (f"the inputs {list(nearly)} are nearly collinear (the least singular value "
                    f"of their unit columns is {ratio:.2g} of the largest): the data hardly tell "
                    "their paths apart, so each input's gain and numerator can be far off "
                    "while their sum fits (check their standard errors); excite the inputs "
                    "separately, or identify their sum")
            outs[r] = replace_fields(o, notes=o.notes + (text,))
            warnings.warn(f"estimate(){which}: {text}", stacklevel=2)
    for r, (o, (notes, serious, _)) in enumerate(zip(outs, checked)):
        # the grid's choice (the chosen candidate's; `_delays_fitted` may have moved it)
        fitted = None if o.delay_std_errors is None else [
            float(d) if not np.isnan(e) else None  # (inf: fitted down to its bound 0)
            for d, e in zip(np.asarray(o.model.delays), o.delay_std_errors)]
        texts = delay_edge_notes(o.start.delays, o.model.input_names, edges, fitted)
        held = [k for k, g in enumerate(grid_mask) if g and (  # gridded, not fitted
            o.delay_std_errors is None or np.isnan(o.delay_std_errors[k]))]
        zero = all(float(np.asarray(o.model.delays)[k]) == 0.0 for k in held)
        quiet = ()  # noted, not warned (every estimate with a delay grid has it; the warning
        # names the first doubtful finding, which this note hid)
        if held and o.method != "mfm":  # (the MFM stage has no std errors to qualify; a
            # delay `_delays_fitted` fitted is counted, one chosen at 0 is held)
            quiet = (f"the delays of {', '.join(repr(o.model.input_names[k]) for k in held)} "
                      "were chosen from their "
                      "grid: the standard errors count them as known and are too small where "
                      "they are uncertain (0.38-0.59 of the spread in two studies of a 0.47 s "
                      "delay on a 0.1 s grid at 10 dB)" + (
                          ": a delay of 0 is held, not fitted" if zero else
                          "; for std errors that include them, fit output_error(..., "
                          "fit_delays=True) from this model"),)
        warn = list(texts) + list(notes[:1] if serious else ())
        outs[r] = replace_fields(o, notes=o.notes + texts + notes + quiet)
        if warn:
            doubtful.setdefault(warn[0], []).append(r)
    for text, rs in doubtful.items():
        warnings.warn(f"estimate(){_which(rs, len(outs), single)}: {text}", stacklevel=2)
    for r, o in enumerate(outs):
        flags = (int(o.model.status) | _search_flags(o.search)) & FLAGGED
        if flags:  # every candidate was flagged, or the stage's model is: not a usable answer
            which = "" if single else f" (record {r})"
            o = replace_fields(o, model=replace_fields(o.model, status=np.int32(
                int(o.model.status) | flags)))  # kept with the model (summary, JSON, CLI)
            text = (f"the returned model is flagged ({describe(flags)}): it is not a usable "
                    "model of these data; check the data (a level that swamps the variation: "
                    "subtract it; a constant input: drop it) and the grid")
            outs[r] = replace_fields(o, converged=False, notes=o.notes + (text,))
            warnings.warn(f"estimate(){which}: {text}", stacklevel=2)
            continue
        if not o.converged:
            which = "" if single else f" (record {r})"
            unstable = ("; the MFM winner or SRIVC's filter was unstable, so the plant itself "
                        "may be: fits that simulate (SRIVC, output error) cannot follow a "
                        "response that grows by orders of magnitude over the record; identify "
                        "it on a shorter record (a few of its growth times) or in closed loop"
                        if o.stabilised or "unstable_filter" in _reason(o) else "")
            warnings.warn(f"estimate(){which}: {o.method} did not converge ({_reason(o)}); the "
                          "estimate is its best iterate and its standard errors are not "
                          f"trustworthy: check the grid or raise max_iter{unstable}",
                          stacklevel=2)
    return outs[0] if single else tuple(outs)


def _which(records: list, total: int, single: bool) -> str:
    """' (k of R records: [...])' for a batch warning, '' for one record."""
    return "" if single else (f" ({len(records)} of {total} records: {records[:10]}"
                              f"{'...' if len(records) > 10 else ''})")


# SRIVC's from-rest residual variance over the observer-started one above 1 + START_RATIO / T
# (T samples): the record does not start at rest. At rest it was 1 + (3-9) / T (45 records of
# 400 and 1500 samples at noise 0.3); a window starting mid-transient, 1.02-4.6 (1.2 flat let
# a fifth of them through with std errors 1.4x too small)
START_RATIO = 20.0


def residual_notes(records: list, outs: list, n_max: int, rehearsal: bool = False) -> list:
    """(notes, serious: the first note is warned, not at rest) per record. First the
    residual tests of `residuals` (Box-Pierce whiteness, and independence from each input,
    1 % level) of each returned model on its
    record (the estimation window's samples: `records` as the model was fitted on them), the
    state from the observer over the record (`residuals`' default), by the
    hold-out's padded observer program (`observe_candidate`, one for every order up to
    `n_max`; rehearsed with the stages). Residuals correlated with an input mean unmodelled
    dynamics or a wrong delay (serious: warned); coloured residuals alone mean noise that is
    not white, under which the standard errors (which assume white noise) are too small:
    3.4-5.3x with AR(1) noise of pole 0.98. Then, where SRIVC is the returned stage: its
    residual variance (its simulation from rest) over the observer-started one above
    1 + `START_RATIO` / T: the record does not start at rest, and SRIVC's standard errors leave out
    that start-up transient (1.4-2.1x too small on records cut 2 s after an input switch,
    ratios 1.37-2.2 there against 1.002-1.007 from rest; the threshold is 1 + 20 / T).
    Nothing for a flagged or unstable model, nor where the returned stage did not converge
    (its summary already says so; the `rehearsal` compiles the program whatever its stand-in's stages did)."""
    from ._analysis import residual_tests

    T = records[0].n_samples
    lags = min(RESIDUAL_LAGS, T // 4)
    todo = [r for r, o in enumerate(outs)  # not where the summary already says NOT ...
            if (o.converged or rehearsal)
            and not ((int(o.model.status) | _search_flags(o.search)) & FLAGGED
                     or unstable_note(o.model))]
    out = [((), False, False)] * len(outs)
    if lags < 5 or not todo:
        return out
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        obs = map_pairs(_observed, [records[r] for r in todo],
                        [padded_model(outs[r].model, n_max) for r in todo], device=False,
                        start=np.int32(0), length=record_bucket(T), ob_length=np.int32(T),
                        valid=np.int32(T))
    for r, o in zip(todo, obs):
        if o is None or int(o.status) & (Status.OVERFLOW | Status.UNOBSERVABLE):
            continue
        rec = records[r]
        u = np.asarray(rec.u).reshape(T, -1)
        e = np.asarray(rec.y) - np.asarray(o.y_sim)[:T]
        stats = residual_tests(e, u, lags, y=rec.y)
        bad = [name for name, ok in zip(rec.input_names, stats["independent"]) if ok is False]
        notes = []
        exact = float(e @ e) <= exact_floor(rec.y)  # rounding-level residuals: no test
        if exact:
            notes.append(f"the model reproduces the record to rounding (residual RMS "
                         f"{np.sqrt(np.mean(e * e)):.2g}, output std {np.std(rec.y):.3g}): "
                         "noise-free data, so the residual tests are skipped and the standard "
                         "errors measure rounding only")
        elif bad:
            notes.append(f"the residuals are correlated with the input(s) {bad} (residuals("
                         "model, signals), 1 % level): dynamics or a delay the model misses; "
                         "the model and its standard errors are doubtful: widen the orders or "
                         "the delay grid")
        elif stats["white"] is False:
            notes.append("the residuals are not white (Box-Pierce, 1 % level): the output "
                         "noise is coloured, or the model misses dynamics"
                         + ("" if outs[r].method == "mfm" else  # MFM: no standard errors
                            "; the standard errors assume white noise and are then too small")
                         + " (see residuals(model, signals))")
        fit = outs[r].srivc
        ratio = (float(fit.sigma2) / float(np.mean(e * e))  # SRIVC fitted on the record
                 if outs[r].method == "srivc" and fit is not None and not exact
                 else 0.0)
        moving = ratio > 1.0 + START_RATIO / T
        if moving:
            notes.append(f"SRIVC's simulation from rest leaves {ratio:.3f}x the residual "
                         "variance of the simulation from the observed initial state: the "
                         "record does not start at rest, and SRIVC's standard errors leave "
                         "out that start-up transient (too small)")
        out[r] = tuple(notes), bool(bad), moving
    return out


def _from_rest_to_output_error(records: list, outs: list, checked: list, n_max: int) -> list:
    """Where SRIVC is returned on a record that does not start at rest (`residual_notes`),
    output error from SRIVC's estimate (it fits the initial state) is returned instead where
    it converges, and a note says which. On 30 records cut 2 s after an input switch, its
    standard errors were within 1.00-1.15x of the spread (SRIVC's 1.4-2.1x too small) and the
    spread itself 1.8-2.6x smaller than SRIVC's."""
    redo = [r for r, (_, _, not_at_rest) in enumerate(checked) if not_at_rest]
    if not redo:
        return outs
    with warnings.catch_warnings():  # a stage that did not converge is said below
        warnings.simplefilter("ignore")
        oes = _staged_many(output_error, [records[r] for r in redo],
                           [outs[r].model for r in redo], n_max=n_max)
    outs = list(outs)
    for r, oe in zip(redo, oes):
        o, rec = outs[r], records[r]
        failed = ("did not converge" if oe is None or not oe.converged else
                  "came out unstable" if unstable_note(oe.model) and not unstable_note(o.model)
                  else "")
        text = ("output error from SRIVC's estimate " + (
            f"{failed}: SRIVC's fit is returned, its standard errors not trustworthy" if failed
            else "is returned: it fits the initial state, so the start-up transient neither "
            "biases it nor its standard errors"))
        # the not-at-rest note (the last of `checked`'s) goes with the decision, into the
        # estimate's notes: `estimate` tests a model a later stage returns anew
        notes = o.notes + (checked[r][0][-1], text)
        checked[r] = (checked[r][0][:-1], *checked[r][1:])
        outs[r] = replace_fields(o, notes=notes) if failed else replace_fields(
            o, model=oe.model.labelled(rec.output_name, rec.input_names), output_error=oe,
            names=tuple(oe.names), std_errors=np.asarray(oe.std_errors),
            covariance=np.asarray(oe.covariance), method="srivc + output error",
            converged=True, notes=notes)
    return outs


def _delays_fitted(records: list, outs: list, gridded: tuple, n_max: int) -> list:
    """Where a delay was picked from its grid and SRIVC or output error is returned: output
    error from that estimate with those delays fitted too (`output_error(fit_delays=...)`),
    returned where it converges, so the delays leave the grid and the standard errors count
    their uncertainty (`delay_std_errors`). Held at the grid value, a 0.47 s delay on a 0.1 s
    grid at 10 dB gave std errors of 0.38-0.59 of the estimates' spread (coverage 50-73 %,
    two studies of 40 records); fitted, 0.99-1.03 (coverage 95-98 %). A delay the grid put at
    0 is held (no dead time); a refit that does not converge, or comes out unstable where the
    estimate was not, is not returned (a note says so)."""
    redo = [r for r, o in enumerate(outs) if o.method != "mfm" and any(
        g and d > 0 for g, d in zip(gridded, np.asarray(o.model.delays)))]
    if not redo:
        return outs
    with warnings.catch_warnings():  # one that does not converge is said in the notes
        warnings.simplefilter("ignore")
        oes = _staged_many(output_error, [records[r] for r in redo],
                           [outs[r].model for r in redo], n_max=n_max, fit_delays=gridded)
    outs = list(outs)
    for r, oe in zip(redo, oes):
        o, rec = outs[r], records[r]
        fitted = [k for k, (g, d) in enumerate(zip(gridded, np.asarray(o.model.delays)))
                  if g and d > 0]
        names = ", ".join(repr(rec.input_names[k]) for k in fitted)
        was = ", ".join(f"{float(np.asarray(o.model.delays)[k]):.6g}" for k in fitted)
        failed = ("did not converge" if oe is None or not oe.converged else
                  "came out unstable" if unstable_note(oe.model) and not unstable_note(o.model)
                  else "")
        if failed:
            outs[r] = replace_fields(o, notes=o.notes + (
                f"output error with the delays of {names} fitted {failed}: they stay at their "
                "grid values",))
            continue
        zero = [repr(rec.input_names[k]) for k in fitted
                if float(np.asarray(oe.model.delays)[k]) == 0.0]
        outs[r] = replace_fields(
            o, model=oe.model.labelled(rec.output_name, rec.input_names), output_error=oe,
            names=tuple(oe.names), std_errors=np.asarray(oe.std_errors),
            covariance=np.asarray(oe.covariance), delay_std_errors=oe.delay_std_errors,
            joint_covariance=oe.joint_covariance,
            method=o.method if o.method.endswith("output error") else o.method
            + " + output error", converged=True, notes=o.notes + (
                f"the delays of {names} were fitted by output error from the grid's choice "
                f"({was}), with the parameters: the standard errors count their uncertainty",)
            + ((f"the delays of {', '.join(zero)} were fitted down to 0, their bound: the data "
                "prefer no dead time there (infinite std error)",) if zero else ()))
    return outs


def _search_flags(res: SearchResult) -> int:
    """The best candidate's flags where every candidate of the search is flagged, else 0: no
    candidate is a model of the data (a constant input: `no_excitation` on every row), so no
    stage started from one is, however its own fit looks (SRIVC and output error from such a
    start came back at 1e12 with status ok and converged on a heater record whose lamp never
    moved)."""
    status = np.asarray(res.columns["status"])[np.asarray(res.rank)] if len(res) else None
    if status is None or not np.all(status.astype(np.int64) & int(FLAGGED)):
        return 0
    return int(status[0]) & int(FLAGGED)


_REHEARSED: set = set()  # stage layouts whose programs this process has compiled


def _rehearsal(records: list, grid: dict, stages: dict, windows=None):
    """On a stage layout's first call (record length, rules, largest order, stage settings;
    `windows`: the hold-out path's (folds, estimation windows) from `holdout_folds`, None for
    `selection="bic"`): a function that runs the stages after the search (`_from_holdout`, or
    `_from_search`) on the first record from a stand-in search result, one stable candidate
    per structure of the grid, its results discarded. The search runs on a second thread
    meanwhile (`overlapped`), so the stages' programs (the hold-out observer, SRIVC, output
    error) compile on the other core while its chunks compile: the same calls on the same
    layout, hence the programs the real stages then find compiled. A batch shares one
    record's programs (its candidates go through the per-fold stages in chunks of 8 pairs,
    remainders singly); its chunks of records in the last stage compile after the search.
    Nothing is rehearsed for a layout seen before or several estimation windows (no stages).
    None as well for a grid the search will refuse (its own error then says why), so a
    warm call runs its search on the calling thread."""
    first = records[0]
    if windows is not None and len(windows[1]) > 1:
        return None
    try:  # a grid the search will refuse: nothing to rehearse, the search says why
        structs = structures(grid_values(grid["n"], "n"), grid["m"], first.n_inputs)
        h = float(grid_values(grid["h"], "h")[0])
        n_max = max(s[0] for s in structs)
    except Exception:  # noqa: BLE001
        return None
    start = lambda w: round((w - first.t0) / first.dt)  # noqa: E731 (t0 enters no program)
    key = (first.n_samples, first.n_inputs, first.intersample, first.offset, n_max,
           tuple(sorted(stages.items())), None if windows is None else tuple(
               start(x) for x in np.hstack([np.ravel(w) for fit, hold in windows[0]
                                            for w in (*fit, hold)] + [np.ravel(windows[1])])))
    if key in _REHEARSED:
        return None  # a warm call: the search runs on this thread

    def rehearse():
        _REHEARSED.add(key)
        res = _stand_in(first, structs, h)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                if windows is None:
                    outs = _from_search([first], [res], **stages)
                else:
                    folds, est = windows
                    outs = _from_holdout([first], [HoldoutSearch(tuple(res for _ in folds),
                                                                 np.ones(len(res)), res, folds,
                                                                 est)], rehearsal=True, **stages)
                residual_notes([first], outs, n_max, rehearsal=True)
            except Exception:  # noqa: BLE001 (speculative: the real stages compile what it missed)
                pass

    return rehearse


def _stand_in(first: Signals, structs: list, h: float) -> SearchResult:
    """A search result on `first`'s layout holding one candidate per structure: poles at
    -1/h, unit static gain from every input, arrays of the search's dtypes and padded layout
    (N = M = n_max: the stages do not read them)."""
    K, C = first.n_inputs, len(structs)
    n_max = max(s[0] for s in structs)
    m_max = tuple(max(s[1][k] for s in structs) for k in range(K))
    a = np.zeros((C, n_max + 1))
    b = np.zeros((C, K, max(m_max, default=0) + 1))
    theta = np.zeros((C, n_max + 1 + sum(mk + 1 for mk in m_max) + int(first.offset)))
    for j, (n, _) in enumerate(structs):
        a[j, : n + 1] = np.poly(np.full(n, -1.0 / h))[::-1]  # ascending, a_n = 1
        b[j, :, 0] = a[j, 0]
        theta[j, : n + 1] = a[j, : n + 1]
        if K:
            theta[j, n_max + 1 + np.cumsum((0, *(mk + 1 for mk in m_max[:-1])))] = a[j, 0]
    one = np.ones(C)
    cols = dict(n=np.asarray([s[0] for s in structs]),
                m=np.asarray([s[1] for s in structs]).reshape(C, K), N=one * n_max,
                M=one * n_max, h=one * h,
                delays=np.tile(np.asarray(first.delays, np.float64).reshape(1, K), (C, 1)),
                J=one, J_raw=one, E=one, fit=one, aic=one, bic=one, cond=one,
                status=np.zeros(C, np.int32), theta=theta, a=a, b=b, offset=np.zeros(C))
    # ranked largest structures first, as MFM's bias ranks them under noise: the structures
    # nested in the best `STRUCTURES` then join them (`_best_per_structure`) as in a real
    # search, and the stages' chunks (and single pairs beyond them) are those of the real call
    return SearchResult(columns=cols, rank=np.arange(C)[::-1], score="E", n_max=n_max,
                        m_max=m_max,
                        intersample=first.intersample, has_offset=first.offset,
                        output_name=first.output_name, input_names=first.input_names,
                        compile_s=0.0, run_s=0.0)


def _reason(est: Estimate) -> str:
    if est.output_error is not None and est.method.endswith("output error"):
        return est.output_error.result
    return est.srivc.describe() if est.srivc is not None else "no stage ran"


def _observed(signals: Signals, candidate: dict, n_samples=None, **kw):
    """The hold-out observer (`observe_candidate`) of a padded candidate; `n_samples` (the
    record's own length, `map_pairs`) is not needed: the window lies inside the record."""
    return observe_candidate(signals.unlabelled(), candidate, **kw)


def _from_holdout(records, sels, *, holdout, polish, max_iter, tol, rehearsal=False,
                  shift: str = "start") -> list:
    """The stages of `estimate` after its hold-out search, every stage over all records and
    candidates in chunks of one compiled call, every structure zero-padded to the grid's
    largest order (SRIVC, the observers, and output error for a batch). `rehearsal`
    (`_rehearsal`'s stand-in run) takes the path most records take: the output-error polish
    replaces SRIVC only with `polish=True`, and SRIVC that did not converge is not rescued
    (no fallback candidates, no output error from its best iterate), so that programs a
    record rarely needs (output error on all estimation data) compile only when one does."""
    rescue = not rehearsal
    R, sel0 = len(records), sels[0]
    if len(sel0.refit) == 0:
        raise ValueError("estimate(): the search grid has no feasible candidate; widen N, M or h")
    blocks = " and ".join(f"[{w[0]:.15g}, {w[1]:.15g}]" for _, w in sel0.folds)
    several = len(sel0.estimation) > 1  # the share is of the last window, and no SRIVC runs
    texts = []
    for sel in sels:
        j = int(rank_by(sel.refit, "bic")[0])
        by_bic = (int(sel.refit.columns["n"][j]), [int(v) for v in sel.refit.columns["m"][j]])
        each = " each" if len(sel0.folds) > 1 else ""  # ("each" of a single block misread)
        texts.append(f"{'mean ' if each else ''}hold-out E over {blocks} ({holdout:.0%} of the "
                     + (f"last estimation window{each}, " if several else
                        f"estimation data{each}, ")
                     + "fitted on the rest)"
                     + ("" if several else
                        f", SRIVC structures within {HOLDOUT_TIE:.0%} of the best decided by "
                        "their BIC over all estimation data")
                     + f"; the MFM search's BIC on the estimation data would pick "
                     f"n={by_bic[0]} m={by_bic[1]}"
                     + ("; no candidate was free of flags (an integrator, or an unstable "
                        "plant), so those whose only flag is a pole at Re >= 0 were ranked"
                        if sel.unstable_ranked else ""))
    if len(sel0.estimation) > 1:
        # several experiments: the stages after MFM simulate one record; keep MFM
        out = []
        for r, sel in enumerate(sels):
            start = sel.refit.best(0)
            model = start.labelled(records[r].output_name, records[r].input_names)
            names = free_parameters(start)[0]
            nan = np.full(len(names), np.nan)
            out.append(Estimate(model, start, sel.refit, None, None, names, nan, np.diag(nan),
                                True, False, "mfm", texts[r], {}, (
                                    "several estimation windows: the MFM estimate of their "
                                    "summed Grams is returned (SRIVC and output error need one "
                                    "record)",)))
        return out
    est_sigs = [rec.window(*sel0.estimation[0]) for rec in records]
    # every stage's data (estimation data, fit parts, hold-out windows) padded to the whole
    # record's `record_bucket`, only its own samples counting: one program per stage, not one
    # per share of the record (fit part, hold-out block, estimation data): a first call
    # compiled 6 programs instead of 9, 10.1-10.4 s against 12.6-12.8 s, warm calls alike
    # (139-154 against 140-147 ms; `python benchmarks/estimate_first_call.py --compare DIR`);
    # results bitwise equal
    T = records[0].n_samples
    est_bucket = record_bucket(T)
    folds = []  # (fit part per record, hold-out window, observer length, y_hold per record)
    for (fit_w,), hold in sel0.folds:
        folds.append(([rec.window(*fit_w) for rec in records], hold,
                      OBSERVER_FRACTION * (hold[1] - hold[0]),
                      [np.asarray(rec.window(*hold).y) for rec in records]))

    n_max = max(int(np.max(sel.refit.columns["n"])) for sel in sels)  # one observer program
    # output error pads every structure to n_max too, one record as well as a batch: no
    # program per structure chosen (one record in its own shape was faster warm, 9.5 against
    # 11.0 ms per record on Table 3 model 1, but a record choosing a new structure compiled
    # for about 1.3 s)

    def hold_scores(pairs):
        """(mean hold-out E over the folds, mean fit %) of each (record, models per fold)."""
        E = np.zeros((len(pairs), len(folds)))
        fit = np.zeros_like(E)
        for f, (_, hold, ob, y_hold) in enumerate(folds):
            start, length, ob = validation_window(records[0], hold, ob, n_max, "estimate")
            # the window padded to the record's bucket (only its own samples count; past the
            # record's end the last sample is held)
            obs = map_pairs(_observed, [records[r] for r, _ in pairs],
                            [padded_model(ms[f], n_max) for _, ms in pairs],
                            device=False, start=np.int32(start), length=est_bucket,
                            ob_length=np.int32(ob), valid=np.int32(length))
            for k, ((r, _), o) in enumerate(zip(pairs, obs)):
                if o is None or int(o.status) & (Status.OVERFLOW | Status.UNOBSERVABLE):
                    E[k, f], fit[k, f] = np.inf, np.nan  # not usable on the hold-out
                else:  # errors at rounding level tie (`EXACT_FIT`): fewer parameters win
                    E[k, f] = max(float(o.E), exact_floor(y_hold[r], records[0].dt))
                    fit[k, f] = float(fit_percent(y_hold[r], o.y_sim[:length]))
        return [(float(np.mean(e)), float(np.mean(q))) if np.all(np.isfinite(e))
                else (np.inf, np.nan) for e, q in zip(E, fit)]

    def per_fold(stage, pairs, **kw):
        """The stage's result on each fold for each (record, starts per fold) (its best iterate
        when it stopped early: the hold-out E judges it); None where it could not run."""
        # each fit part padded to the record's bucket (`est_bucket`)
        outs = [_staged_many(stage, [folds[f][0][r] for r, _ in pairs],
                             [ms[f] for _, ms in pairs], shift=shift, bucket=est_bucket, **kw)
                for f in range(len(folds))]
        return [None if any(o[k] is None for o in outs) else [o[k] for o in outs]
                for k in range(len(pairs))]

    n_hold = [round((h[1] - h[0]) / records[0].dt) + 1 for _, h, _, _ in folds]

    def bic(r, fits, E_hold: float) -> float:
        """BIC of a stage on record `r`'s estimation data: over the folds, its fit part's
        T_f ln(E_f / (T_f dt)) + k ln T_f (E the simulation error of eq. 17 from rest, at
        least `exact_floor`) and its hold-out block's N_h ln(E_h / (N_h dt)) (predicted, so
        no parameter term)."""
        N_h = sum(n_hold)
        out = N_h * np.log(max(E_hold / (N_h / len(folds) * records[0].dt), 1e-300))
        for (parts, _, _, _), fit in zip(folds, fits):
            T_f = parts[r].n_samples
            k = fit.model.structure.n_params - 1 + fit.model.has_offset
            E = max(float(fit.E), exact_floor(parts[r].y, records[0].dt))
            out += T_f * np.log(max(E / (T_f * records[0].dt), 1e-300)) + k * np.log(T_f) \
                if np.isfinite(E) else np.inf
        return out

    # every stage fitted on each fold's fit part and compared on its hold-out block: the MFM
    # winner of each of the best `STRUCTURES` structures, and SRIVC from it; then output
    # error on the best
    cand = [(r, i) for r in range(R) for i in _best_per_structure(sels[r].refit, STRUCTURES)]
    firsts = [[x.best(i, device=False) for x in sels[r].fitted] for r, i in cand]
    tried = [[] for _ in range(R)]  # (mean hold-out E, fit, rank, stage, per-fold models, BIC)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        mfm = hold_scores([(r, fs) for (r, _), fs in zip(cand, firsts)])
        sv_fits = per_fold(srivc, [(r, [stabilised(x)[0] for x in fs])
                                   for (r, _), fs in zip(cand, firsts)], n_max=n_max,
                           max_iter=max_iter, tol=tol)
        sv = [None if v is None else [f.model for f in v] for v in sv_fits]
        # SRIVC fits that stopped unconverged on a fold (their best iterate, maybe the start):
        # said in `Estimate.holdout`'s keys
        stalled = {id(m) for v in sv_fits if v is not None for f in v if not bool(f.converged)
                   for m in (f.model,)}

        def unsettled(x) -> bool:  # a SRIVC entry whose fit stopped unconverged on a fold: its
            # fold models are iterates (often the MFM start itself), not the consistent
            # estimator, so they get no preference over MFM, no BIC tie and no fallback (a
            # stalled SRIVC equal to its MFM start tied MFM and took SRIVC's stage)
            return x[3] == "srivc" and any(id(m) in stalled for m in x[4])

        live = [k for k, v in enumerate(sv) if v is not None]
        sv_score = dict(zip(live, hold_scores([(cand[k][0], sv[k]) for k in live])))
        for k, (r, i) in enumerate(cand):
            tried[r].append((*mfm[k], i, "mfm", firsts[k], np.inf))
            if k in sv_score:
                tried[r].append((*sv_score[k], i, "srivc", sv[k], bic(r, sv_fits[k],
                                                                          sv_score[k][0])))
        # the consistent estimator is preferred: plain MFM (biased under output noise) must
        # predict the hold-out better by POLISH_GAIN, as output error must to replace SRIVC;
        # a larger structure must beat a smaller one by Akaike's FPE factor (parsimony), and
        # SRIVC structures within the hold-out's resolution are told apart by their BIC
        key = lambda x: parsimonious(x[0], x[4][0], min(n_hold))  # noqa: E731
        best = [min(t, key=lambda x: key(x) / ((1 - POLISH_GAIN) if x[3] == "mfm" or
                                                unsettled(x) else 1.0)) for t in tried]
        best = [b if b[3] == "mfm" or unsettled(b) else near_tie_by_bic(
            [x for x in t if not unsettled(x)], key) for b, t in zip(best, tried)]
        if polish is not False:
            bases = [b[4] if b[3] == "srivc" else [stabilised(x.best(b[2], device=False))[0]
                                                   for x in sels[r].fitted]
                     for r, b in enumerate(best)]
            oe = [None if v is None else [f.model for f in v]
                  for v in per_fold(output_error, list(enumerate(bases)), n_max=n_max)]
            live = [r for r in range(R) if oe[r] is not None]
            for r, (E_oe, fit_oe) in zip(live, hold_scores([(r, oe[r]) for r in live])):
                stage = "srivc + output error" if best[r][3] == "srivc" else "output error"
                # output error (consistent, and it fits the initial state) replaces SRIVC
                # where it predicts the hold-out POLISH_GAIN better, and replaces plain MFM
                # unless MFM predicts it POLISH_GAIN better, as SRIVC does: on records that
                # do not start at rest, SRIVC's start-up transient on the fit parts let MFM
                # win, and only a 5 % gain of output error over MFM replaced it (plain MFM
                # on 19 of 30 records, bias 0.5-0.6 of its spread, no std errors)
                vs_mfm = best[r][3] == "mfm" or unsettled(best[r])
                if polish or rescue and np.isfinite(E_oe) and (
                        E_oe <= best[r][0] / (1 - POLISH_GAIN) if vs_mfm
                        else E_oe < (1 - POLISH_GAIN) * best[r][0]):
                    best[r] = (E_oe, fit_oe, best[r][2], stage, oe[r])
    # the chosen stage on all estimation data, from the same candidate re-identified there
    starts = [sels[r].refit.best(best[r][2]) for r in range(R)]
    seeds = [stabilised(s) for s in starts]
    methods = [b[3] for b in best]
    sv_rec = [r for r in range(R) if methods[r] not in ("mfm", "output error")]
    oe_rec = [r for r in range(R) if methods[r].endswith("output error")]
    with warnings.catch_warnings():  # `estimate` warns itself for a stage that did not converge
        warnings.simplefilter("ignore")
        fits = dict(zip(sv_rec, _staged_many(srivc, [est_sigs[r] for r in sv_rec],
                                             [seeds[r][0] for r in sv_rec], n_max=n_max,
                                             max_iter=max_iter, tol=tol, bucket=est_bucket,
                                             shift=shift)))
        # SRIVC that did not converge on all estimation data: the next SRIVC candidate in the
        # hold-out ranking that converges replaces it (at most FALLBACKS tries per record)
        ranked = [sorted((x for x in t if x[3] == "srivc" and x[2] != best[r][2]
                          and not unsettled(x)), key=key) for r, t in enumerate(tried)]
        fell = {}
        for attempt in range(FALLBACKS if rescue else 0):
            redo = [r for r in sv_rec if methods[r] == "srivc" and len(ranked[r]) > attempt
                    and fits[r] is not None and not fits[r].converged]
            alt = [stabilised(sels[r].refit.best(ranked[r][attempt][2])) for r in redo]
            for r, a, fit in zip(redo, alt, _staged_many(
                    srivc, [est_sigs[r] for r in redo], [a[0] for a in alt], n_max=n_max,
                    max_iter=max_iter, tol=tol, bucket=est_bucket, shift=shift)):
                if fit is not None and fit.converged:
                    m0 = fits[r].model
                    fell[r] = (f"SRIVC from the hold-out winner n={m0.n} m={list(m0.m)} did "
                               f"not converge on all estimation data ({fits[r].describe()}); "
                               "the next SRIVC candidate of the hold-out ranking that did "
                               "is returned")
                    best[r], starts[r], seeds[r], fits[r] = ranked[r][attempt], \
                        sels[r].refit.best(ranked[r][attempt][2]), a, fit
        for r in sv_rec:  # none converged: output error from SRIVC's best iterate
            if rescue and methods[r] == "srivc" and fits[r] is not None and \
                    not fits[r].converged:
                methods[r] = "srivc + output error"
                oe_rec.append(r)
                fell[r] = (f"SRIVC did not converge on all estimation data "
                           f"({fits[r].describe()}), nor did the next {FALLBACKS} candidates "
                           "of the hold-out ranking: output error from its best iterate is "
                           "returned")
        oes = dict(zip(oe_rec, _staged_many(
            output_error, [est_sigs[r] for r in oe_rec],
            [fits[r].model if fits.get(r) is not None else seeds[r][0] for r in oe_rec],
            n_max=n_max, bucket=est_bucket, shift=shift)))
        for r in [r for r in fell if methods[r] == "srivc + output error"]:
            if oes[r] is None or not oes[r].converged:  # no better: SRIVC's best iterate
                methods[r] = "srivc"
                del oes[r]
                fell[r] += ("; output error did not converge either, so SRIVC's best iterate "
                            "is returned")
        for r in [r for r in oe_rec if methods[r] == "output error"]:
            if oes[r] is None or not oes[r].converged:  # the MFM estimate it replaced, which
                methods[r] = "mfm"  # has no iterations to stop short (it was returned
                del oes[r]  # unconverged, since output error no longer needs a 5 % gain)
                best[r] = next((x for x in tried[r] if x[3] == "mfm" and x[2] == best[r][2]),
                               best[r])
                fell[r] = ("output error, chosen on the held-back data, did not converge on "
                           "all estimation data: the MFM estimate is returned")
        for r in [r for r in oe_rec if r not in fell and methods[r] == "srivc + output error"]:
            if (oes[r] is None or not oes[r].converged) and fits.get(r) is not None \
                    and fits[r].converged:  # a converged fit over an unconverged polish
                methods[r] = "srivc"
                del oes[r]
                # its hold-out entry and score are SRIVC's again (they were the polish's,
                # which then also decided `_holdout_variants` for a model it did not return)
                best[r] = next((x for x in tried[r] if x[3] == "srivc" and x[2] == best[r][2]),
                               best[r])
                fell[r] = ("the output-error polish, chosen on the held-back data, did not "
                           "converge on all estimation data: the converged SRIVC fit is "
                           "returned")
    out = []
    for r in range(R):
        tr, b, method = tried[r], best[r], methods[r]
        gridded = len({tuple(np.asarray(x[4][0].delays).tolist()) for x in tr}) > 1
        held = {f"{x[3]} n={x[4][0].n} m={list(x[4][0].m)}" + (
            f" delays={[float(d) for d in np.asarray(x[4][0].delays)]}" if gridded else "") + (
            " (not converged on a fold)" if any(id(m) in stalled for m in x[4]) else ""): x[1]
            for x in tr}  # (with a delay grid, one entry per delay: they overwrote each other)
        # the stage chosen on the held-back data, with its fit there: where a rescue returns
        # output error from SRIVC's best iterate (`notes`), that stage is SRIVC's
        held[f"chosen: {b[3]}"] = b[1]
        fit, oe, start = fits.get(r), oes.get(r), starts[r]
        model, names, cov, converged, notes = start, (), None, True, ()
        if fit is not None:
            model, names, cov = fit.model, fit.names, np.asarray(fit.covariance)
            converged = bool(fit.converged)
        if oe is not None:
            model, names, cov, converged = oe.model, oe.names, np.asarray(oe.covariance), \
                oe.converged
        if r in fell:
            notes += (fell[r],)
        if method != "mfm" and cov is None:
            notes += (f"{method} could not simulate on all estimation data: the MFM estimate "
                      "is returned",)
            method, converged = "mfm", True
        if cov is None:
            model, names = start, free_parameters(start)[0]
            cov = np.full((len(names), len(names)), np.nan)
            notes += ("no standard errors: the plain MFM estimate is returned (it predicted "
                      "the held-back data best, or the stages after it failed)",)
        std = np.sqrt(np.abs(np.diagonal(cov)))
        model = model.labelled(records[r].output_name, records[r].input_names)
        if method != "mfm" and records[r].offset:
            notes += (f"SRIVC / output error ran on data with their {SHIFTS[shift]} removed; "
                      "the offset term is mapped back to the original levels",)
        notes += _flat_holdout(folds, r, est_sigs[r])
        out.append(Estimate(model, start, sels[r].refit, fit, oe, tuple(names), std, cov,
                            converged, seeds[r][1], method, texts[r], held, notes,
                            key(b)))
    return out


FLAT_HOLDOUT = 0.1  # a held-back block whose output's std is below this share of the
# estimation data's says little: its fit % divides by that small spread


def _flat_holdout(folds: list, r: int, est) -> tuple:
    """A note where every held-back block's output barely moves (a single step's settled
    tail: a model fitting the step at 99.8 % read "chosen: srivc 0.1" there, unsaid)."""
    spread = float(np.std(np.asarray(est.y)))
    held = [float(np.std(f[3][r])) for f in folds]
    if not spread > 0 or max(held) >= FLAT_HOLDOUT * spread:
        return ()
    return (f"the held-back block(s) barely move the output (std {max(held):.3g} against "
            f"{spread:.3g} over the estimation data): their fit % says little about the model "
            "(its denominator is that small spread), and the structure was chosen on them; "
            "hold back data where the output moves (identify=, holdout=)",)


def _holdout_variants(records: list, sels: list, stages: dict, search: dict):
    """`_from_holdout` for each record in every variant the data leave open, the one that
    predicts the held-back data best kept (its chosen stage's hold-out E times the FPE factor,
    `Estimate.score`). Returns (records, with the offset and its note as decided; estimates).

    - An offset record's SRIVC and output-error stages run on data shifted by their starting
      levels (`_start_levels`: right where the plant rests at the first sample, e.g. a step
      test from steady state) and by their means (better where the record starts mid-
      transient): the better on the held-back data is kept (`_by_shift`).
    - An offset term the default rule cannot decide (`offset_undecided`: the output starts
      away from zero with an input away from zero) is chosen like a structure: the hold-out
      search runs again with the term, its stages too, and the term is kept where its chosen
      stage is `OFFSET_GAIN` better, or within `HOLDOUT_TIE` with fewer free parameters.
      Compared on the returned stage, not on the MFM search: at 10 % noise the MFM winners'
      equation-error bias had dropped a needed term."""
    R = len(records)
    runs = [(list(range(R)), records, sels, "start")]
    if records[0].offset:  # one layout per batch
        runs.append((list(range(R)), records, sels, "mean"))
    undecided = [r for r, rec in enumerate(records) if offset_undecided(rec)]
    if undecided:
        on = [replace_fields(records[r], offset=True) for r in undecided]
        with warnings.catch_warnings():  # the first search's candidates warned already
            warnings.simplefilter("ignore")
            sels_on = holdout_search(on[0], records=on, **search)
        runs += [(undecided, on, sels_on, "start"), (undecided, on, sels_on, "mean")]
    got = [{} for _ in range(R)]  # per record: (offset, shift) -> Estimate
    for idx, recs, ss, shift in runs:
        for r, est in zip(idx, _from_holdout(recs, ss, shift=shift, **stages)):
            got[r][(recs[0].offset, shift)] = est
    score = lambda e: e.score if np.isfinite(e.score) else np.inf  # noqa: E731
    records, outs = list(records), []
    for r, tried in enumerate(got):
        flag = records[r].offset
        best = _by_shift(tried, flag, score)
        if r in undecided:
            alt = _by_shift(tried, True, score)
            # the term must predict better by OFFSET_GAIN, or as well (within HOLDOUT_TIE) with
            # fewer free parameters: without it, n = 3 with a pole and a zero near s = 0
            # carried a heater's ambient level as a state, predicting as well as n = 2 with the
            # term (6.34 against 6.31) with a static gain of 1.19 for 0.6
            keep = score(alt) < (1 - OFFSET_GAIN) * score(best) or (
                score(alt) <= (1 + HOLDOUT_TIE) * score(best) and len(alt.names) < len(best.names))
            start = output_start(np.asarray(records[r].y))  # as the rule read it
            why = (f"auto, decided on held-back data: the output starts at {start:.4g} with "
                   "an input away from zero, where the data alone do not say whether the "
                   "output at zero input is zero; the returned stage's hold-out E x FPE is "
                   f"{score(alt):.4g} with the term and {score(best):.4g} without it")
            records[r] = replace_fields(records[r], offset=True, offset_note=(
                f"offset term estimated ({why})")) if keep else replace_fields(
                records[r], offset_note=f"no offset term ({why})")
            best = alt if keep else best
        outs.append(best)
    return records, outs


def _by_shift(tried: dict, offset: bool, score):
    """Of a record's estimates with the offset flag `offset`: the shift whose returned stage
    predicts the held-back data best. No margin for either: preferring the starting levels
    within 5 % returned a validation fit of 73 % against 89.6 % on a record that starts
    mid-transient (5 % noise, `folds=2`), for 68.7 against 67.1 % on the DaISy heating system,
    whose two shifts tie on the held-back data."""
    return min((e for (o, _), e in tried.items() if o == offset), key=score)


def parsimonious(E: float, model: Model, n_hold: int) -> float:
    """Hold-out E times Akaike's final-prediction-error factor (1 + 2k/N_h), k the model's free
    parameters, N_h the hold-out samples. On the hold-out E alone a structure that nests the
    true one won 37 of 100 noisy records by fitting noise; with this margin (0.1 % per
    parameter on 2,000 samples) the smaller structure wins unless the larger predicts
    measurably better (benchmarks/noise_montecarlo.py)."""
    k = model.structure.n_params - 1 + model.has_offset  # as `free_parameters` (a_n = 1)
    return E * (1.0 + 2.0 * k / n_hold)


def near_tie_by_bic(tried: list, key) -> tuple:
    """The SRIVC entry of `tried` (hold-out E, fit, rank, stage, per-fold models, BIC) chosen
    among those whose `key` (parsimonious hold-out E) is within `HOLDOUT_TIE` of the best: the
    one of least BIC over all estimation data (fit parts and hold-out blocks). A hold-out block
    of a few hundred noisy samples alone cannot separate structures whose predictions differ by
    less than the noise (n = 3 and 4 on the lightly damped system at 10 dB: 15 of 100 wrong);
    with the fit parts' evidence added, and every parameter paying ln T, it can. The hold-out
    still rules out any structure that predicts the held-back data measurably worse."""
    sv = [x for x in tried if x[3] == "srivc"]
    top = min(key(x) for x in sv)
    return min((x for x in sv if key(x) <= (1.0 + HOLDOUT_TIE) * top), key=lambda x: x[5])


HOLDOUT_TIE = 0.05  # hold-out E within 5 % (as POLISH_GAIN): a tie, decided by BIC on all data
FALLBACKS = 2  # next-ranked SRIVC candidates tried where the chosen one did not converge
STRUCTURES = 8  # structures whose best setting goes on to SRIVC in the hold-out comparison
NESTED = 8  # at most this many structures nested in those go on to SRIVC too
DELAYS = 12  # per structure, the best setting of at most this many of the grid's delays
OFFSET_GAIN = 0.05  # an undecided offset term must lower the hold-out E x FPE by 5 % to be kept


def _best_per_structure(res: SearchResult, count: int) -> list[int]:
    """Ranks (in `res`) of the best candidate of each of the first `count` structures, then of
    the structures nested in them that the search tried, one numerator order lower (one m_k
    less by one) level by level, at most `NESTED` more: MFM's equation-error bias under output
    noise can rank a structure below its over-parameterised neighbours, and SRIVC and the
    parsimony rules can only choose a structure that reaches them (a 2-input plant, n = 3,
    m = (1, 0), at 26 dB: the truth ranked 15th-21st among the structures, never chosen)."""
    c, ranked = res.columns, np.asarray(res.rank)
    usable = np.flatnonzero(np.asarray(c["status"])[ranked] == 0)  # ranks of usable candidates
    keys = np.column_stack([c["n"], np.asarray(c["m"]).reshape(len(c["n"]), -1)])[ranked]
    _, at = np.unique(keys[usable], axis=0, return_index=True)
    # structure -> rank of its best usable candidate, in rank order
    first = {(int(keys[i][0]), tuple(int(v) for v in keys[i][1:])): int(i)
             for i in np.sort(usable[at])}
    chosen = list(first)[:count]
    level, most = chosen, len(chosen) + NESTED
    while level and len(chosen) < most:  # one numerator order lower, level by level
        nested = [(n, m[:k] + (m[k] - 1,) + m[k + 1:]) for n, m in level
                  for k in range(len(m)) if m[k] > 0]
        level = [key for key in dict.fromkeys(nested) if key in first and key not in chosen]
        chosen += level[: most - len(chosen)]
    # with a delay grid, each structure's best setting at each of its delays (at most DELAYS,
    # by rank): MFM's equation-error bias under noise also biases the delay it ranks first,
    # and SRIVC at that delay fitted the wrong model with tight std errors (0.47 s searched
    # on 0, 0.1, .., 1 at 10 dB: 0.7 or 0.8 on 37 of 40 records, never 0.4 or 0.5, a_0 up to
    # 4.4 std errors off, unsaid); the hold-out comparison chooses among SRIVC's fits
    delays = np.round(np.asarray(c["delays"], dtype=np.float64).reshape(len(c["n"]), -1)[ranked],
                      12)
    per = {}  # structure -> ranks of its best candidate at each delay vector, in rank order
    for i in usable:
        key = (int(keys[i][0]), tuple(int(v) for v in keys[i][1:]))
        seen = per.setdefault(key, {})
        seen.setdefault(tuple(delays[i]), int(i))
    out = [r for key in chosen for r in list(per[key].values())[:DELAYS]]
    return out or [0]


SHIFTS = {"start": "starting levels", "mean": "means"}


def _staged_many(stage, records, models, shift: str = "start", **kw) -> list:
    r"""`stage` (srivc or output_error) from each model with its delays on its record, each
    chunk of pairs in one compiled call (SRIVC: every structure padded to `n_max`, default the
    largest order among the models; output error: padded only with `n_max`), on data with
    their starting levels (`shift="start"`, `_start_levels`) or their means (`"mean"`)
    removed where the model has an offset term: the free parameters are scaled by their
    magnitude, so a level far from zero (97 degC on the heat exchanger) would swamp them, and
    SRIVC's filters start from rest, which the data then do where the plant is at rest at the
    first sample with the starting levels removed (with the means, a heater switched on at the
    first sample from an ambient 20 degC left a start-up transient as large as the data's
    swing, and SRIVC preferred n = 3, m = 2 with standard errors of 80-190 % to the true
    n = 2, m = 0), while a record that starts mid-transient fits better with the means
    (`_holdout_variants` keeps the better). The offset maps exactly between the two levels:
    $b_{off}' = b_{off} + \sum_k b_{k0} \bar u_k - a_0 \bar y$. An entry is None where the
    stage could not run (e.g. an overflowing simulation)."""
    shifted, sigs, starts = [], [], []
    for signals, model in zip(records, models):
        signals = _with(signals, model)
        ybar, ubar = (0.0, np.zeros(signals.n_inputs))
        if model.has_offset:
            ybar, ubar = _start_levels(signals) if shift == "start" else (
                float(np.mean(np.asarray(signals.y))),
                np.mean(np.asarray(signals.u).reshape(signals.n_samples, -1), axis=0))
            signals = eqx.tree_at(lambda q: (q.y, q.u), signals, jax.device_put(
                (np.asarray(signals.y) - ybar, np.asarray(signals.u) - ubar)))  # no program
            model = _shift_offset(model, ybar, ubar, +1.0)
        shifted.append((ybar, ubar))
        sigs.append(signals)
        starts.append(model)
    if not sigs:
        return []
    if stage is srivc:  # every structure zero-padded to one order: one SRIVC program
        kw.setdefault("n_max", max(m.n for m in starts))
    outs = {output_error: output_error_many, srivc: srivc_many}[stage](sigs, starts, **kw)
    return [out if out is None or not model.has_offset else _shifted_back(out, ybar, ubar)
            for out, model, (ybar, ubar) in zip(outs, models, shifted)]


def _start_levels(signals: Signals):
    """(y, u) at the record's first sample: y read from its first samples (up to 10) as the
    value there of their least-squares line (`output_start`: output noise), u as given (an
    input often steps within those samples). Shifted by them, the data start from rest where
    the plant rests at the first sample with the inputs at their first values. Where an input
    instead steps there from another level (a heater switched on at t = 0), structures with
    m_k = 0 are unaffected (b_k0 times the step's height goes into the offset), while b_kj
    (j >= 1) miss the step's derivative at t = 0 and only such structures see a transient."""
    u = np.asarray(signals.u).reshape(signals.n_samples, -1)
    return output_start(np.asarray(signals.y)), np.array(u[0], dtype=np.float64)


def _shifted_back(out, ybar, ubar):
    """A stage's result on shifted data (`_staged_many`) at the original levels, with its
    covariance."""
    back = _shift_offset(out.model, ybar, ubar, -1.0)
    theta = np.array(jax.device_get(back.theta), dtype=np.float64)
    if theta.shape == (len(out.names),):  # the fitted free parameters: their offset too
        theta[out.names.index("offset")] = float(back.offset)
        back = eqx.tree_at(lambda q: q.theta, back, jax.device_put(theta))
        out = replace_fields(out, theta=jax.device_put(theta))  # the fit's own theta too
    # covariance of (.., b_k0, .., offset): d offset / d a_0 = ybar, d / d b_k0 = -ubar_k
    J = np.eye(len(out.names))
    row = out.names.index("offset")
    for name, val in [("a_0", ybar)] + [(f"b_{k + 1}0", -ubar[k]) for k in range(len(ubar))]:
        if name in out.names:
            J[row, out.names.index(name)] = val
    cov = np.asarray(out.covariance)
    lost = ~np.isfinite(np.diagonal(cov))  # undetermined (`gauss_newton_covariance`)
    cov = J @ np.where(lost[:, None] | lost[None, :], 0.0, cov) @ J.T
    lost = np.any(J[:, lost] != 0, axis=1)  # ... and every parameter mapped from them
    cov[lost, :], cov[:, lost] = np.nan, np.nan
    cov[lost, lost] = np.inf
    return replace_fields(out, model=back, covariance=cov,
                          std_errors=np.sqrt(np.abs(np.diagonal(cov))))


def _shift_offset(model: Model, ybar: float, ubar, sign: float) -> Model:
    """The same model with the offset term for data shifted by -(ybar, ubar) (sign +1) or back."""
    a, b, offset = jax.device_get((model.a, model.b, model.offset))  # host: no eager programs
    shift = sum(float(bk[0]) * float(ubar[k]) for k, bk in enumerate(b)) - float(a[0]) * ybar
    return eqx.tree_at(lambda q: q.offset, model,
                       jax.device_put(np.float64(offset) + sign * shift))


def _with(signals: Signals, model: Model) -> Signals:
    return eqx.tree_at(lambda q: q.delays, signals, model.delays)


def estimate_from_search(signals: Signals, res: SearchResult, *, polish: bool = False,
                         max_iter: int = 30, tol: float = 1e-8) -> Estimate:
    """The stages of `estimate` after its search, from a `SearchResult` of `signals` (the
    winner's delays are used)."""
    return _from_search([signals], [res], polish=polish, max_iter=max_iter, tol=tol)[0]


def _from_search(records, results, *, polish, max_iter, tol) -> list:
    """SRIVC (and output error) from each record's search winner, batched by structure."""
    starts = []
    for r, res in enumerate(results):
        if len(res) == 0:
            raise ValueError("estimate(): the search grid has no feasible candidate; widen N, "
                             "M or h")
        start = res.best(0)
        if int(start.status) != 0:
            warnings.warn(f"estimate(): every candidate{'' if len(results) == 1 else f' of record {r}'} "
                          f"is flagged; starting from the best one ({describe(int(start.status))})",
                          stacklevel=3)
        starts.append(start)
    seeds = [stabilised(s) for s in starts]
    # every winner zero-padded to the grid's largest order: one SRIVC and one output-error
    # program per grid, whatever order each record's winner has (one record as well as a batch)
    n_max = max(res.n_max for res in results)
    fits = _staged_many(srivc, records, [s for s, _ in seeds], n_max=n_max, max_iter=max_iter,
                        tol=tol)
    if any(f is None for f in fits):
        raise ValueError("estimate(): SRIVC could not simulate the search's winner on this "
                         "record; try selection='holdout' or a smaller grid")
    with warnings.catch_warnings():  # `estimate` warns itself for a stage that did not converge
        warnings.simplefilter("ignore")
        oes = _staged_many(output_error, records, [f.model for f in fits], n_max=n_max) \
            if polish else [None] * len(fits)
    out = []
    for rec, res, start, (_, unstable), fit, oe in zip(records, results, starts, seeds, fits,
                                                        oes):
        stage = fit if oe is None else oe
        model = stage.model.labelled(rec.output_name, rec.input_names)
        converged = bool(fit.converged) if oe is None else oe.converged
        out.append(Estimate(model, start, res, fit, oe, tuple(stage.names),
                            np.asarray(stage.std_errors), np.asarray(stage.covariance),
                            converged, unstable, "srivc" if oe is None else
                            "srivc + output error", f"{res.score.upper()} on the estimation "
                            "data", {}, ()))
    return out


def unstable_note(model) -> tuple:
    """A note (in a tuple) when `model`'s A(s) has a root with Re >= 0, else ()."""
    if is_stable(model.a):
        return ()
    return ("the model has a pole with Re >= 0 (unstable): an unstable plant, or a record that "
            "drifts (a trend, integrating behaviour); check `detrend`, a lower n or a longer "
            "record before predicting far ahead" + ("" if model.has_offset else
                                                     "; signals at a level of their own (an "
                                                     "output far from zero at zero input) "
                                                     "need the offset term (offset=True)"),)


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
        if not same:  # what differs (a NaN row dropped by resample= shortens one output)
            def shown(x):
                return (f"{x.output_name!r}: {x.n_samples} samples from t0 = {x.t0:.15g}, "
                        f"dt = {x.dt:.15g}, inputs {list(x.input_names)}")
            crossed = sorted(set(r.input_names) & {x.output_name for x in records})
            raise ValueError(
                f"estimate_outputs(): record {i} ({shown(r)}) does not share record 0's inputs "
                f"and sampling ({shown(first)}"
                + ("" if r.n_samples != first.n_samples or r.u.shape != first.u.shape
                   or r.dt != first.dt else "; the inputs' values differ")
                + (f"; {crossed} is an output of this list and an input of record {i}"
                   if crossed else "")
                + "); give one Signals per output of one experiment, on one time grid")
        for what, mine, theirs in [("intersample rules", r.intersample, first.intersample),
                                   ("input names", r.input_names, first.input_names),
                                   ("start time t0", r.t0, first.t0)]:
            if mine != theirs:  # t0 places identify= windows given in absolute time
                raise ValueError(f"estimate_outputs(): record {i} has other {what} than "
                                 f"record 0 ({mine!r} against {theirs!r}); build every output's "
                                 "record from one experiment with the same settings")
    names = [r.output_name for r in records]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:  # the results could not be told apart (each is labelled by its output's name)
        raise ValueError(f"estimate_outputs(): the output name(s) {twice} are given to more "
                         "than one record; name each output (Signals(..., output_name=...)) or "
                         "drop the repeated record")
    out, caught = [], []
    for r in records:
        with warnings.catch_warnings(record=True) as mine:
            warnings.simplefilter("always")
            out.append(estimate(r, **kwargs))
        caught.append(mine)
    # a warning every output raised (an argument's: polish with several windows) is said once;
    # the others name their output (the same text came once per output, unnamed)
    every = set.intersection(*({str(w.message) for w in c} for c in caught)) \
        if len(records) > 1 else set()
    said = set()
    for r, mine in zip(records, caught):
        for w in mine:
            text = str(w.message)
            if text in every:
                if text in said:
                    continue
                said.add(text)
                who = f"estimate_outputs(), all {len(records)} outputs"
            else:
                who = f"estimate_outputs(), output {r.output_name!r}"
            if text.startswith("estimate()"):
                text = who + text[len("estimate()"):]
            warnings.warn_explicit(text, w.category, w.filename, w.lineno)
    return tuple(out)
