r"""`estimate`: one call from noisy data to a consistent model with its uncertainty.

search (MFM over every structure and modulating-function setting of a grid, eq. 1-17)
-> SRIVC from the winner (`srivc`: consistent under output noise, CRB-level spread)
-> optionally an output-error polish (`output_error`).
The MFM closed form stays the initialiser: it is fast and exact on noise-free data, but its
equation error is biased under output noise; SRIVC removes that bias at a few ms per fit.
"""

from __future__ import annotations

import warnings

import equinox as eqx
import numpy as np

from ._model import Model
from ._output_error import OutputErrorFit, output_error, stabilised
from ._search import SearchResult, search
from ._signals import Signals
from ._srivc import SrivcFit, srivc
from ._status import describe


class Estimate(eqx.Module):
    """Result of `estimate`: the model, the path that produced it and its uncertainty."""

    model: Model  # the returned model (SRIVC, or output error when polished)
    start: Model  # the search's winner (the MFM estimate)
    search: SearchResult
    srivc: SrivcFit
    output_error: OutputErrorFit | None
    names: tuple  # free parameters, ordered as std_errors
    std_errors: np.ndarray
    covariance: np.ndarray  # of the free parameters, ordered as names (the last stage's)
    converged: bool  # the last stage met its tolerance
    stabilised: bool  # the MFM winner had right-half-plane poles, mirrored before SRIVC
    method: str  # "srivc" or "srivc + output error"

    def summary(self) -> str:
        """The model, the standard errors, how it was reached and whether it converged."""
        lines = [self.model.summary(), f"method: MFM search -> {self.method}",
                 f"{'parameter':<12}{'std error':>14}"]
        lines += [f"{k:<12}{float(v):>14.3e}" for k, v in zip(self.names, self.std_errors)]
        if self.stabilised:
            lines.append("the MFM winner was unstable: its right-half-plane poles were mirrored")
        lines.append("converged" if self.converged else
                     "NOT CONVERGED: the estimate is the best iterate; its standard errors are "
                     f"not trustworthy (SRIVC: {self.srivc.describe()})")
        return "\n".join(lines)


def estimate(
    signals: Signals, *, h, n=(1, 2, 3), N=(3, 4, 5), M=(3, 4, 5), m=None, delays=None,
    score: str = "bic", validate=None, polish: bool = False, max_iter: int = 30,
    tol: float = 1e-8,
) -> Estimate:
    r"""Noise-robust identification in one call: `search` -> `srivc` -> (`output_error`).

    The batched MFM search ranks every structure (n, m) and setting (N, M, h, delays) of the
    grid by `score`, default BIC (E of eq. 17 on `validate` plus $k \ln N_v$): under output
    noise E on the fitted data rewards extra parameters (a 2nd-order plant at 10 dB SNR: E picked
    n = 3 with standard errors of the size of the parameters, BIC n = 2). Its winner, with any
    right-half-plane
    poles mirrored, starts SRIVC (exact prefilters, instruments from the noise-free auxiliary
    model), which removes the equation-error bias of MFM under output noise. `polish=True`
    adds an output-error fit from the SRIVC model (useful when the noise is not white or the
    record short). Grid arguments are those of `search`.

    **Returns:** `Estimate`: `model`, `std_errors` (SRIVC's IV covariance, or output error's
    Gauss-Newton covariance when polished), `converged`, and every stage's result. A stage that
    did not converge says so in `converged` and `summary()`, and warns.
    """
    if not isinstance(polish, bool):
        raise TypeError(f"estimate(): polish must be True or False (got {polish!r})")
    res = search(signals, n=n, N=N, M=M, h=h, m=m, delays=delays, score=score,
                 validate=validate)
    return estimate_from_search(signals, res, polish=polish, max_iter=max_iter, tol=tol)


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
    fit = srivc(signals, seed, max_iter=max_iter, tol=tol)
    model, names, std = fit.model, fit.names, np.asarray(fit.std_errors)
    cov = np.asarray(fit.covariance)
    converged, method, oe = bool(fit.converged), "srivc", None
    if polish:
        oe = output_error(signals, model)
        model, names, std = oe.model, oe.names, np.asarray(oe.std_errors)
        cov = np.asarray(oe.covariance)
        converged, method = oe.converged, "srivc + output error"
    model = model.labelled(signals.output_name, signals.input_names)
    return Estimate(model, start, res, fit, oe, tuple(names), std, cov, converged, was_unstable,
                    method)
