r"""Model selection on held-back data: every candidate of a search scored on samples it was not
fitted on.

The search's Gram integral (eq. 9-10) sums only the identification windows' samples, so a
candidate's E (eq. 17) on a window outside them, with the state from the initial-state
observer (eq. 14) over the first `OBSERVER_FRACTION` of that window, is a hold-out score. The
windows are values of the compiled search: the hold-out run and the refit on all estimation
data share one program.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from ._pytree import replace_fields
from ._search import SearchResult, plan_search, run_plan
from ._search._grid import identification_segments
from ._search._result import ranking
from ._signals import Signals

OBSERVER_FRACTION = 0.2  # initial-state observer over this share of a hold-out window


class HoldoutSearch(NamedTuple):
    """`holdout_search`'s result: `fitted` (candidates identified without the hold-out window,
    ranked by their E on it), `refit` (the same candidates identified on all estimation
    windows, in the same ranking), and the windows in time units."""

    fitted: SearchResult
    refit: SearchResult
    fit_windows: tuple
    holdout: tuple
    estimation: tuple


def holdout_windows(signals: Signals, estimation, holdout: float):
    """(fit windows, hold-out window, estimation windows) in time units: the last `holdout`
    share of the last estimation window is held back."""
    if not (isinstance(holdout, float | int) and 0.05 <= holdout <= 0.5):
        raise ValueError(f"estimate(): holdout must be a share between 0.05 and 0.5 of the "
                         f"estimation data (got {holdout!r})")
    dt, t0 = signals.dt, signals.t0
    segs = identification_segments(signals, estimation, "estimate")
    a, b = segs[-1]  # [start, end) samples
    cut = b - max(round(holdout * (b - a)), 1)
    t = lambda k: t0 + k * dt  # noqa: E731
    fit = tuple((t(s), t(e - 1)) for s, e in segs[:-1]) + ((t(a), t(cut - 1)),)
    return fit, (t(cut), t(b - 1)), tuple((t(s), t(e - 1)) for s, e in segs)


def holdout_search(signals: Signals, *, estimation=None, holdout: float = 1 / 3, n, N, M, h,
                   m=None, delays=None, chunk_size: int = 8) -> HoldoutSearch:
    """Search the grid with the hold-out window left out of the Gram, rank by E on it, then
    identify the same candidates on all estimation windows (same compiled program)."""
    fit, hold, est = holdout_windows(signals, estimation, holdout)
    plan = plan_search(signals, n=n, N=N, M=M, h=h, m=m, delays=delays, score="E",
                       validate=hold, identify=list(fit),
                       observer_window=OBSERVER_FRACTION * (hold[1] - hold[0]), eta=None,
                       chunk_size=chunk_size, simulate=True)
    fitted = run_plan(plan, signals)
    # the refit: the estimation windows (padded to the same number of windows: same program)
    segs = identification_segments(signals, list(est))
    segs = segs + ((0, 0),) * (len(plan.where["segments"]) - len(segs))
    where = dict(plan.where, segments=jnp.asarray(segs, dtype=jnp.int32))
    refit = run_plan(plan._replace(where=where), signals)
    refit = replace_fields(refit, rank=fitted.rank)
    return HoldoutSearch(fitted, refit, fit, hold, est)


def rank_by(res: SearchResult, key: str) -> np.ndarray:
    """The ranking of a search's candidates by another of its columns ("bic", "aic", ...)."""
    c = res.columns
    vals = np.where(np.isfinite(c[key]), c[key], np.inf)
    n_par = c["n"] + np.sum(c["m"] + 1, axis=1)
    return ranking(vals, n_par, c["status"] != 0, None)
