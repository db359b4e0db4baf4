"""The public `search`."""

from __future__ import annotations

import warnings
from collections.abc import Callable, Sequence

import numpy as np

from .._boundary import user_stacklevel, window_list
from .._pytree import replace_fields
from .._signals import Signals, dependent_candidates
from .._status import Status, describe
from ._engine import run_plan
from ._grid import CHUNK_SETTINGS, delay_edge_notes, delay_grids, plan_search
from ._result import SearchResult


def search(
    signals: Signals,
    *,
    n: Sequence[int] | int = (1, 2, 3),
    N: Sequence[float] | float = (3, 4, 5),
    M: Sequence[float] | float = (3, 4, 5),
    h: Sequence[float] | float,
    m: Sequence[Sequence[int]] | None = None,
    delays: Sequence[Sequence[float]] | None = None,
    score: str = "E",
    validate: tuple[float, float] | None = None,
    identify=None,
    observer_window: float | None = None,
    eta=None,
    chunk_size: int = CHUNK_SETTINGS,
    simulate: bool = True,
    progress: Callable[[int, int], None] | None = None,
) -> SearchResult:
    r"""Identify and score every feasible candidate of a grid, batched (see module docstring).

    **Arguments:**

    - `signals`: the experiment. Its own `delays` are ignored when `delays` is given.
    - `n`: output orders; `m`: per input, the allowed numerator orders (default: 0..n-1 for
      each n; values above n are skipped); `N`, `M`, `h`: modulating function settings;
      `delays`: per input, the delays to try. Candidates with N < n or M < n are skipped.
    - `score`: ranking key, one of `"E"` (eq. 17 on the validation window), `"J"` (scale-free
      equation error J_rel), `"fit"` (NRMSE %), `"aic"`, `"bic"` ($N_v \ln(E/T_v) + 2k$ and
      $+ k \ln N_v$, $N_v$ validation samples, $T_v = N_v\,dt$, k = number of free
      parameters, the offset's counted, delays not). Flagged candidates rank after the others;
      ties (for E: differences below 1e-12 of $\int (y - \bar y)^2$; for J: below $\sqrt{p\,\epsilon}$,
      the rounding noise of $\theta^T G \theta$; both matter on noise-free data) go to the
      candidate with fewer parameters.
    - `validate`: (t0, t1) window for E and fit (default: the whole record); the state at its
      start comes from the initial-state observer over `observer_window` (default: the window).
    - `identify`: (t0, t1) window, or a list of windows, whose samples the Gram integral
      (eq. 9-10) sums (default: the record). With `validate` outside it, E, fit, AIC and BIC
      are scores on data the candidates were not fitted on (hold-out model selection).
    - `simulate`: False skips the observer + simulation (E, fit, AIC, BIC are NaN; only the
      `"J"` score is available): the pure equation-error search (the Routh test still flags
      unstable candidates).
    - `chunk_size`: (h, delays) settings per compiled chunk (at most the grid's; rounded up to
      a multiple of the device count), each with every (N, M) and structure: memory grows with
      it (times the chunks in flight: one per core), not with the grid; `progress(done,
      total)` is called after each chunk with counts of (h, delays) settings (from a worker
      thread when chunks run on several cores).

    **Returns:** a `SearchResult`.
    """
    from .._boundary import check_search

    check_search(signals, n=n, N=N, M=M, h=h, m=m, delays=delays, score=score, validate=validate,
                 observer_window=observer_window, eta=eta, chunk_size=chunk_size,
                 simulate=simulate, progress=progress, identify=identify)
    plan = plan_search(signals, n=n, N=N, M=M, h=h, m=m, delays=delays, score=score,
                 validate=validate, observer_window=observer_window, eta=eta,
                 chunk_size=chunk_size, simulate=simulate, identify=identify, split=True,
                 apart=True)
    v_start, v_valid = int(plan.where["v_start"]), int(plan.where["v_valid"])
    y_v = np.asarray(signals.y)[v_start : v_start + v_valid]
    if score == "fit" and simulate and not np.any(y_v != y_v[0]):
        raise ValueError(f"search(): score='fit' is undefined on this validation window: the "
                         f"output is constant there ({float(y_v[0]):.6g}), so every fit % is "
                         "0/0; rank by 'E', or validate on a window where the output moves")
    if simulate:
        _history_note(signals, delays, v_start)
        if validate is None and identify is not None and len(window_list(identify)) > 1:
            warnings.warn("search(): E and fit are measured over the whole record, across the "
                          "gaps between the identify windows: for experiments laid end to end "
                          "(Signals.concatenate) a simulation must stay inside one of them "
                          "(one measured 87.8 % where each window fitted 99.2-99.3 %); give "
                          "validate=(t0, t1) inside one window", stacklevel=user_stacklevel())
    if score == "J" and signals.offset:
        _level_note(np.asarray(signals.y))
    res = run_plan(plan, signals, progress, once=True)
    if identify is not None:  # `refine` of this result says that it re-identifies on all data
        res = replace_fields(res, identify=tuple((float(a), float(b))
                                                 for a, b in window_list(identify)))
    if validate is not None or observer_window is not None:  # `refine` scores there too
        res = replace_fields(res, validate=None if validate is None else (
            float(validate[0]), float(validate[1])), observer_window=None if
            observer_window is None else float(observer_window))
    _doubtful_best(res, delays)
    if not np.any(res.columns["status"] & Status.ILL_CONDITIONED):  # `collect` checked them
        return res
    rows, dependent = dependent_candidates(signals, res.columns["delays"])  # their names
    if dependent:
        warnings.warn(f"search(): the inputs {list(dependent)} are linearly dependent (one is a "
                      f"multiple of the others) under the delays of {int(rows.sum())} of "
                      f"{len(rows)} candidates: their gains are meaningless and they are "
                      "flagged ill_conditioned; drop all but one of them", stacklevel=2)
    return res


LEVEL_RATIO = 1e4  # |mean y| / std y above this: J_rel nears float64 rounding


def _level_note(y) -> None:
    """Warn where score J ranks an output whose level dwarfs its variation: J_rel's
    denominator (the columns' norms) grows with the level while the equation error does not,
    so every J_rel falls towards float64 rounding (6.7e-8 at 5e4-5e5 times the std, against
    2.2e-3 at level 0), where candidates tie and the fewest parameters win (a 62 % fit won at
    5e6)."""
    mean, std = float(np.mean(y)), float(np.std(y))
    if std > 0 and abs(mean) > LEVEL_RATIO * std:
        warnings.warn(f"search(): the output's level ({mean:.6g}) is {abs(mean) / std:.3g} times "
                      "its standard deviation: J_rel is measured against the level and nears "
                      "float64 rounding, where candidates tie; remove the level first (y - its "
                      "mean, or detrend(signals, kind='constant')) or rank by 'E'",
                      stacklevel=user_stacklevel())


def _history_note(signals: Signals, delays, v_start: int) -> None:
    """Warn where candidates with a delay d_k > 0 are scored over the first d_k of the
    validation window with input k from before the record (held at its first value, as
    `observe` warns), while input k varies at the record's start: E then favours the smaller
    delays (a noise-free record with a 5 s delay ranked the true model 21st)."""
    if not signals.n_inputs:
        return
    grids = (delay_grids(delays) if delays is not None
             else [[float(d)] for d in np.asarray(signals.delays)])  # the record's own
    dt, u = signals.host_dt, np.asarray(signals.u)
    held = []
    for name, grid, col in zip(signals.input_names, grids, u.T):
        reach = max(grid, default=0.0) - v_start * dt  # time before the record it reaches
        if reach > 0:
            first = col[: int(np.ceil(reach / dt)) + 1]
            if np.any(first != first[0]):
                held.append((name, max(grid)))
    if held:
        d = max(v for _, v in held)
        warnings.warn(
            f"search(): the delays of {', '.join(repr(n) for n, _ in held)} reach before the "
            f"record from the validation window's start: E and fit there use those inputs from "
            f"before the record, taken as held at their first value, while they vary from the "
            f"record's start, so the ranking favours smaller delays; validate on a window that "
            f"starts {d:g} or more after the record's start (validate=(t0 + {d:g}, t1)), unless "
            "the inputs were steady before the record", stacklevel=user_stacklevel())


def _doubtful_best(res: SearchResult, delays) -> None:
    """Warn when the best candidate cannot be trusted as it stands: every candidate is flagged
    (`best()` then returns a flagged model), or its delay is at an end of its grid."""
    status = res.columns["status"]
    if not len(res):
        return
    if np.all(status != 0):
        best = describe(int(status[res.rank[0]]))
        warnings.warn(f"search(): every one of the {len(res)} candidates is flagged (the best: "
                      f"{best}); best() returns a flagged model: see the status column and "
                      "Status", stacklevel=user_stacklevel())
    elif delays is not None:
        for text in delay_edge_notes(res.row(0)["delays"], res.input_names, delay_grids(delays)):
            warnings.warn(f"search(), best candidate: {text}", stacklevel=user_stacklevel())
