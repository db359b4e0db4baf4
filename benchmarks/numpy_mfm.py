"""A careful per-candidate NumPy/SciPy implementation of the same MFM: the benchmark peer.

Exact kernel weights (12-point Gauss-Legendre per sampling cell against the zoh / foh / cubic
interpolant, as mfmjax), `scipy.signal.fftconvolve`, Gregory rule for G, eq. (12) closed form.
Written independently of mfmjax's code (NumPy only), one candidate at a time.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.signal import fftconvolve

_GX, _GW = np.polynomial.legendre.leggauss(12)


def _p(r, N, M, i):
    out = np.zeros_like(r)
    for j in range(i + 1):
        ffN = np.prod([N - q for q in range(j)]) if j else 1.0
        ffM = np.prod([M - q for q in range(i - j)]) if i - j else 1.0
        out += math.comb(i, j) * ffN * (-1.0) ** (i - j) * ffM * r ** (N - j) * (1 - r) ** (M - i + j)
    return out


def weights(N, M, h, i, dt, rule, tau=0.0):
    cap = math.ceil((tau + h) / dt - 1e-9)
    L = cap + 1
    cell = np.arange(L - 1, dtype=float)
    lo = np.clip(tau, cell * dt, (cell + 1) * dt)
    hi = np.clip(tau + h, cell * dt, (cell + 1) * dt)
    half = (hi - lo) / 2
    s = (hi + lo)[:, None] / 2 + half[:, None] * _GX[None, :]
    r = np.clip((s - tau) / h, 0.0, 1.0)
    kern = _p(r, N, M, i) * half[:, None] * _GW[None, :] / h
    x = s / dt
    w = np.zeros(L)
    if rule == "zoh":
        np.add.at(w, (cell + 1).astype(int), kern.sum(1))
    elif rule == "foh":
        sig = x - cell[:, None]
        np.add.at(w, cell.astype(int), (kern * (1 - sig)).sum(1))
        np.add.at(w, (cell + 1).astype(int), (kern * sig).sum(1))
    else:
        start = np.clip(cell.astype(int) - 1, 0, max(cap - 3, 0))
        z = x - start[:, None]
        basis = [-(z - 1) * (z - 2) * (z - 3) / 6, z * (z - 2) * (z - 3) / 2,
                 -z * (z - 1) * (z - 3) / 2, z * (z - 1) * (z - 2) / 6]
        for q in range(4):
            np.add.at(w, np.minimum(start + q, L - 1), (kern * basis[q]).sum(1))
    return w


def identify(y, u, dt, modes, n, m, N, M, h):
    """a (a_n = 1) and b of one candidate, eq. (12)."""
    T = len(y)
    cols = [fftconvolve(y, weights(N, M, h, i, dt, "cubic"))[:T] * h ** (-i) for i in range(n + 1)]
    for k, mk in enumerate(m):
        cols += [-fftconvolve(u[:, k], weights(N, M, h, j, dt, modes[k]))[:T] * h ** (-j)
                 for j in range(mk + 1)]
    C = np.stack(cols, 1)
    first = math.ceil(h / dt - 1e-9)
    q = np.zeros(T)
    q[first:] = 1.0
    for j, e in enumerate((3 / 8, 7 / 6, 23 / 24)):
        q[first + j] *= e
        q[T - 1 - j] *= e
    G = C.T @ (q[:, None] * C) * dt
    eta = np.ones(G.shape[0])
    g = np.linalg.solve(G, eta)
    theta = g / (eta @ g)
    return theta / theta[n]
