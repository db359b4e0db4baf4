"""The NumPy/SciPy SRIVC peer of the benchmarks: the test twin (tests/reference_srivc.py,
`scipy.signal.cont2discrete` + `lfilter`), fed from mfmjax objects. Not duplicated here."""

from __future__ import annotations

import os
import sys

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tests"))
import reference_srivc  # noqa: E402


def theta_of(model) -> np.ndarray:
    """[a_0..a_{n-1}, b_1, .., b_K, (offset)] of a Model, a_n = 1."""
    an = float(np.asarray(model.a)[model.n])
    parts = [np.asarray(model.a)[: model.n] / an] + [np.asarray(b) / an for b in model.b]
    if model.has_offset:
        parts.append(np.atleast_1d(np.asarray(model.offset)) / an)
    return np.concatenate(parts)


def fit(signals, start, *, max_iter: int = 30, tol: float = 1e-8) -> dict:
    """SRIVC of `signals` from the `start` Model (whole-sample delays only)."""
    lags = np.round(np.asarray(start.delays) / signals.dt).astype(int)
    if not np.allclose(lags * signals.dt, np.asarray(start.delays)):
        raise ValueError("srivc_peer.fit(): the peer takes whole-sample delays only")
    return reference_srivc.srivc(
        theta_of(start), np.asarray(signals.y), np.asarray(signals.u), start.n, tuple(start.m),
        tuple(signals.intersample), signals.dt, lags=lags, has_offset=start.has_offset,
        max_iter=max_iter, tol=tol)
