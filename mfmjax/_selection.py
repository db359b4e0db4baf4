r"""Model selection on held-back data: every candidate of a search scored on samples it was not
fitted on.

The search's Gram integral (eq. 9-10) sums only the identification windows' samples, so a
candidate's E (eq. 17) on a window outside them, with the state from the initial-state
observer (eq. 14) over the first `OBSERVER_FRACTION` of that window, is a hold-out score. The
windows are values of the compiled search: the hold-out run and the refit on all estimation
data share one program.
"""

from __future__ import annotations

import warnings
from typing import NamedTuple

import jax
import numpy as np

from ._batch import overlapped
from ._boundary import user_stacklevel
from ._observers import MIN_WINDOW
from ._pytree import replace_fields
from ._quadrature import window_bucket
from ._search import SearchResult, plan_search, run_plan
from ._search._grid import identification_segments
from ._search._result import ranking
from ._signals import Signals
from ._status import Status

OBSERVER_FRACTION = 0.2  # initial-state observer over this share of a hold-out window


class HoldoutSearch(NamedTuple):
    """`holdout_search`'s result. `fitted`: per fold, the candidates identified without its
    hold-out window (E, fit on that window); `E`: each candidate's mean hold-out E over the
    folds; `refit`: the same candidates identified on all estimation windows, ranked by `E`,
    which its columns `E_holdout` and `fit_holdout` hold (mean hold-out E and fit %; E, fit,
    J, AIC and BIC are the refit's own); `folds`: per fold ((fit windows), hold-out window)
    in time units."""

    fitted: tuple
    E: np.ndarray
    refit: SearchResult
    folds: tuple
    estimation: tuple
    # no candidate was free of flags: those flagged only unstable were ranked by their hold-out E
    # (an integrator's or an unstable plant's record: every candidate was inf, and the first
    # of the grid, n = 1, won by its fewer parameters at a fit of 23 %)
    unstable_ranked: bool = False


FOLDS = 2  # hold-out blocks: the last `holdout` share, and (FOLDS = 2) the first one too


def holdout_folds(signals: Signals, estimation, holdout: float, folds: int = FOLDS):
    """(folds, estimation windows) in time units. Each fold is ((fit windows), hold-out
    window): the last `holdout` share of the last estimation window, and with `folds=2` and a
    single estimation window also the first share (fitted on the rest: every fit part stays
    one contiguous record, so SRIVC and output error can run on it)."""
    if not (isinstance(holdout, float | int) and 0.05 <= holdout <= 0.5):
        raise ValueError(f"estimate(): holdout must be a share between 0.05 and 0.5 of the "
                         f"estimation data (got {holdout!r})")
    if folds not in (1, 2):
        raise ValueError(f"estimate(): folds must be 1 (hold out the end) or 2 (both ends), "
                         f"got {folds!r}")
    dt, t0 = signals.dt, signals.t0
    segs = identification_segments(signals, estimation, "estimate")
    t = lambda k: t0 + k * dt  # noqa: E731
    a, b = segs[-1]  # [start, end) samples
    L = max(round(holdout * (b - a)), 1)
    out = [(tuple((t(s), t(e - 1)) for s, e in segs[:-1]) + ((t(a), t(b - L - 1)),),
            (t(b - L), t(b - 1)))]
    if folds == 2 and len(segs) == 1:
        out.insert(0, (((t(a + L), t(b - 1)),), (t(a), t(a + L - 1))))
    elif folds == 2:  # it became one fold without a word
        warnings.warn("estimate(): folds=2 needs one estimation window (each fit part must stay "
                      "one contiguous record); with several windows one fold is used, the end "
                      "of the last window held out", stacklevel=user_stacklevel())
    return tuple(out), tuple((t(s), t(e - 1)) for s, e in segs)


def holdout_search(signals: Signals, *, estimation=None, holdout: float = 1 / 3,
                   folds: int = FOLDS, n, N, M, h, m=None, delays=None,
                   chunk_size: int = 8, records=None, meanwhile=None):
    """Search the grid once per fold with its hold-out window left out of the Gram, rank by
    the mean E over the hold-out windows, then identify the same candidates on all
    estimation windows. Every run shares one compiled program (windows are values). With
    `records` (`Signals` of `signals`' layout) every run covers all of them in one call and
    one `HoldoutSearch` per record is returned. `meanwhile`: a function called on this
    thread, once the grid is checked, while the runs go on a second thread (`estimate`
    compiles its later stages in it; the runs emit no warnings)."""
    fold_windows, est = holdout_folds(signals, estimation, holdout, folds)
    fit0, hold0 = fold_windows[0]
    # the hold-out blocks must carry an observer (eq. 14) of the largest order: said here in
    # estimate's terms, not as the search's validate/observer_window it is built from
    n_top = max(int(v) for v in np.atleast_1d(n))
    span = min(hw[1] - hw[0] for _, hw in fold_windows)
    block = round(span / signals.dt) + 1
    observer = round(OBSERVER_FRACTION * span / signals.dt) + 1
    need = max(MIN_WINDOW, 2 * n_top)
    if block < need or observer < MIN_WINDOW:
        raise ValueError(
            f"estimate(): holdout={holdout:g} leaves hold-out blocks of {block} samples, "
            f"{observer} of them for the initial-state observer (the first "
            f"{OBSERVER_FRACTION:.0%}); an order-{n_top} model needs at least {need} per block "
            f"and {MIN_WINDOW} for the observer: "
            + ("raise holdout (at most 0.5), " if holdout < 0.5 else "")
            + "lower the largest order n or give a longer record")
    plan = plan_search(signals, n=n, N=N, M=M, h=h, m=m, delays=delays, score="E",
                       validate=hold0, identify=list(fit0),
                       observer_window=OBSERVER_FRACTION * (hold0[1] - hold0[0]), eta=None,
                       chunk_size=chunk_size, simulate=True,
                       # a share of the record: one buffer for every length in its bucket
                       v_bound=window_bucket(round((hold0[1] - hold0[0]) / signals.dt) + 1,
                                             signals.n_samples))
    S = len(plan.where["segments"])
    batch = records if records is not None else [signals]

    def run(windows, hold):
        segs = identification_segments(signals, list(windows))
        segs = segs + ((0, 0),) * (S - len(segs))  # empty windows: same program
        where = dict(plan.where, **jax.device_put({
            "segments": np.asarray(segs, dtype=np.int32),
            "v_start": np.int32(round((hold[0] - signals.t0) / signals.dt))}))
        return run_plan(plan._replace(where=where), signals, records=batch)

    def runs():
        return [run(fw, hw) for fw, hw in fold_windows], run(est, fold_windows[-1][1])

    fitted, refits = overlapped(runs, meanwhile)  # [fold][record], [record]
    out = []
    for r, refit in enumerate(refits):
        per_fold = [f[r] for f in fitted]

        def mean_E(usable):
            E = np.mean([np.where(usable(x.columns["status"]), x.columns["E"], np.inf)
                         for x in per_fold], axis=0)
            return np.where(np.isfinite(E), E, np.inf)

        E = mean_E(lambda st: st == 0)
        unstable = not np.isfinite(E).any()
        if unstable:  # the block's E of a model whose only flag is a pole with Re >= 0 is
            # finite and means what it says: rank those
            E = mean_E(lambda st: (st & ~int(Status.UNSTABLE)) == 0)
            unstable = bool(np.isfinite(E).any())
        fit = np.mean([x.columns["fit"] for x in per_fold], axis=0)
        c = per_fold[-1].columns
        rank = ranking(E, c["n"] + np.sum(c["m"] + 1, axis=1), ~np.isfinite(E), None)
        # the scores it is ranked by, for the table a user reads: the refit's own E and fit %
        # are on a block it was fitted on (rank 1 read E 4861 / fit 87 % under rank 9's
        # 997 / 94 % on the DaISy heating system)
        held = dict(refit.columns, E_holdout=np.where(np.isfinite(E), E, np.nan),
                    fit_holdout=np.where(np.isfinite(E), fit, np.nan))
        out.append(HoldoutSearch(tuple(replace_fields(x, rank=rank) for x in per_fold), E,
                                 replace_fields(refit, rank=rank, columns=held), fold_windows,
                                 est, unstable))
    return out if records is not None else out[0]


def rank_by(res: SearchResult, key: str) -> np.ndarray:
    """The ranking of a search's candidates by another of its columns ("bic", "aic", ...)."""
    c = res.columns
    vals = np.where(np.isfinite(c[key]), c[key], np.inf)
    n_par = c["n"] + np.sum(c["m"] + 1, axis=1)
    return ranking(vals, n_par, c["status"] != 0, None)
