"""Plain NumPy/SciPy float64 SRIVC: the twin of `mfmjax.srivc` for the tests, and the benchmark peer.

Written from the method (Young & Jakeman; Garnier & Wang 2008), not from mfmjax's code: the
prefilters $s^i/A(s)$ are discretised exactly by `scipy.signal.cont2discrete` (zoh, or foh for
piecewise-linear signals) and run by `scipy.signal.lfilter` on their transfer functions, every
column of one rule at once. The output and the auxiliary output are filtered as foh (point
samples of a continuous response), inputs by their own rule; delays whole numbers of samples
(inputs held at their first value before the record); filters start from rest at the first
sample. Same iteration, stopping rules and best-iterate choice as `mfmjax.srivc`.
"""

from __future__ import annotations

import numpy as np
from scipy import signal

DIVERGENCE_FACTOR = 100.0
ROUNDING_FLOOR = 1e-20
MAX_ITER, DIVERGED, UNSTABLE_FILTER, NONFINITE = 1, 2, 4, 8


def _shift(x, lag):
    """x[j - lag] (rows), holding the first / last row outside the record."""
    idx = np.clip(np.arange(x.shape[0]) - lag, 0, x.shape[0] - 1)
    return x[idx]


def _rows(Ad, v, X):
    """States (T, n, S) of z_{j+1} = Ad z_j + v x_j from rest, one lfilter per state row."""
    n = Ad.shape[0]
    num, den = signal.ss2tf(Ad, v.reshape(n, 1), np.eye(n), np.zeros((n, 1)))
    return np.stack([signal.lfilter(num[i], den, X, axis=0) for i in range(n)], axis=1)


def filtered(a, X, mode, dt, lags=None):
    """s^i/A(s) applied to the zoh/foh interpolants of the columns X (T, S): (T, n+1, S)."""
    a = np.asarray(a, dtype=float)
    n = a.size - 1
    lags = np.zeros(X.shape[1], dtype=int) if lags is None else np.asarray(lags, dtype=int)
    Xs = np.stack([_shift(X[:, s], lags[s]) for s in range(X.shape[1])], axis=1)
    Ac = np.diag(np.ones(n - 1), 1)
    Ac[-1] = -a[:n] / a[n]
    en = np.zeros((n, 1))
    en[-1] = 1.0
    if mode == "zoh":
        Ad, Bd, *_ = signal.cont2discrete((Ac, en, np.eye(n), np.zeros((n, 1))), dt, "zoh")
        z = _rows(Ad, Bd, Xs)
    else:  # foh: x_{j+1} = Ad x_j + Q u_j + R u_{j+1}, from scipy's shifted-state form
        Ad, Bd, _, Dd, _ = signal.cont2discrete((Ac, en, np.eye(n), np.zeros((n, 1))), dt, "foh")
        R = Dd
        Q = Bd - Ad @ R
        z = _rows(Ad, Q, Xs) + _rows(Ad, R, _shift(Xs, -1))
    top = Xs - np.einsum("i,tis->ts", a[:n] / a[n], z)
    return np.concatenate([z, top[:, None, :]], axis=1)


def split(theta, n, m, has_offset):
    a = np.append(theta[:n], 1.0)
    pos, bs = n, []
    for mk in m:
        bs.append(theta[pos : pos + mk + 1])
        pos += mk + 1
    return a, bs, (theta[pos] if has_offset else 0.0)


def step(theta, y, u, n, m, modes, dt, lags=None, has_offset=False):
    """One SRIVC pass at theta: (sum of squared simulation errors, next theta, Phi_hat)."""
    a, bs, off = split(np.asarray(theta, dtype=float), n, m, has_offset)
    T, K = y.shape[0], len(m)
    lags = np.zeros(K, dtype=int) if lags is None else np.asarray(lags, dtype=int)
    uf = [None] * K
    for mode in ("zoh", "foh"):
        ks = [k for k in range(K) if modes[k] == mode]
        if ks:
            F = filtered(a, u[:, ks], mode, dt, lags[ks])
            for s, k in enumerate(ks):
                uf[k] = F[:, : m[k] + 1, s]
    yf = filtered(a, y[:, None], "foh", dt)[:, :, 0]
    of = [filtered(a, np.ones((T, 1)), "zoh", dt)[:, :1, 0]] if has_offset else []
    xhat = sum(uf[k] @ bs[k] for k in range(K)) + (of[0][:, 0] * off if has_offset else 0.0)
    xf = filtered(a, xhat[:, None], "foh", dt)[:, :, 0]
    Phi = np.concatenate([-yf[:, :n]] + uf + of, axis=1)
    Phih = np.concatenate([-xf[:, :n]] + uf + of, axis=1)
    c, ch = np.linalg.norm(Phi, axis=0), np.linalg.norm(Phih, axis=0)
    c[c == 0], ch[ch == 0] = 1.0, 1.0
    new = np.linalg.solve((Phih / ch).T @ (Phi / c), (Phih / ch).T @ yf[:, n]) / c
    return float(np.sum((y - xhat) ** 2)), new, Phih


def hurwitz(a):
    r = np.roots(np.asarray(a)[::-1])
    return bool(np.all(np.isfinite(a)) and np.all(r.real < 0))


def srivc(theta0, y, u, n, m, modes, dt, *, lags=None, has_offset=False, max_iter=30,
          tol=1e-8):
    """The iteration of `mfmjax.srivc` (same rules). **Returns:** dict with theta, E (x dt),
    sigma2, cov, std, iterations, status, and `path` (the iterates proposed)."""
    y, u = np.asarray(y, dtype=float), np.asarray(u, dtype=float).reshape(len(y), -1)
    theta = np.asarray(theta0, dtype=float)
    best, E_best, Ph_best, E_last, Ph_last = theta, np.inf, None, np.inf, None
    status, conv, it, path = 0, False, 0, []
    while it < max_iter:
        stable = hurwitz(np.append(theta[:n], 1.0))
        if not stable:
            status |= UNSTABLE_FILTER
            it += 1
            break
        E, new, Ph = step(theta, y, u, n, m, modes, dt, lags, has_offset)
        it += 1
        E_last, Ph_last = E, Ph
        if E < E_best:
            best, E_best, Ph_best = theta, E, Ph
        if not (np.all(np.isfinite(new)) and np.isfinite(E)):
            status |= NONFINITE
            break
        if E > DIVERGENCE_FACTOR * max(E_best, ROUNDING_FLOOR * float(np.sum(y**2))):
            status |= DIVERGED
            break
        scale = np.maximum(np.abs(new), 1e-12 * np.max(np.abs(new)))
        change = np.max(np.abs(new - theta) / scale)
        theta = new
        path.append(new)
        if change < tol:
            conv = True
            break
    if not conv and status == 0:
        status |= MAX_ITER
    if conv:
        out, E, Ph = theta, E_last, Ph_last
    else:
        out, E, Ph = best, E_best, Ph_best
    p = out.size
    sigma2 = E / max(len(y) - p, 1)
    if Ph is None:
        cov = np.full((p, p), np.nan)
    else:
        cov = sigma2 * np.linalg.inv(Ph.T @ Ph)
    return dict(theta=out, E=E * dt, sigma2=sigma2, cov=cov, std=np.sqrt(np.diag(cov)),
                iterations=it, status=status, path=path)
