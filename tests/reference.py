"""Plain NumPy/SciPy float64 twins of the paper's closed forms: the references for the tests.

Written independently of mfmjax's algorithms: monomial polynomials and exact antiderivatives
(numpy.polynomial) instead of the Leibniz form and Gauss rules; scipy for matrix exponentials.
"""

from __future__ import annotations

import math
from fractions import Fraction

import numpy as np
from numpy.polynomial import Polynomial as P
from scipy import linalg, signal


def phi_poly(N: int, M: int, i: int) -> P:
    """p_i(r) = d^i/dr^i r^N (1-r)^M as a monomial polynomial in r."""
    return (P([0, 1]) ** N * P([1, -1]) ** M).deriv(i) if i else P([0, 1]) ** N * P([1, -1]) ** M


def phi(t, N, M, h, i):
    """phi^(i)(t) = h^(N+M-i) p_i(t/h) on [0, h], 0 outside; exact rational evaluation."""
    coeffs = _phi_exact(N, M, i)
    hf = Fraction(h)

    def one(tv):
        r = Fraction(float(tv)) / hf
        if r < 0 or r > 1:
            return 0.0
        return float(hf ** (N + M - i) * sum(c * r**k for k, c in enumerate(coeffs)))

    return np.vectorize(one, otypes=[float])(np.asarray(t, dtype=float))


# -- exact rational polynomial arithmetic (lists of Fractions, lowest degree first) ----------
def _mul(p, q):
    out = [Fraction(0)] * (len(p) + len(q) - 1)
    for i, pi in enumerate(p):
        for j, qj in enumerate(q):
            out[i + j] += pi * qj
    return out


def _add(p, q):
    n = max(len(p), len(q))
    return [(p[i] if i < len(p) else 0) + (q[i] if i < len(q) else 0) for i in range(n)]


def _deriv(p):
    return [i * c for i, c in enumerate(p)][1:] or [Fraction(0)]


def _compose_affine(p, c0, c1):
    """p(c0 + c1 x)."""
    out, power = [Fraction(0)], [Fraction(1)]
    for c in p:
        out = _add(out, [c * v for v in power])
        power = _mul(power, [c0, c1])
    return out


def _integral(p, lo, hi):
    return sum(c * (hi ** (i + 1) - lo ** (i + 1)) / (i + 1) for i, c in enumerate(p))


def _phi_exact(N, M, i):
    p = [Fraction(1)]
    for _ in range(N):
        p = _mul(p, [Fraction(0), Fraction(1)])
    for _ in range(M):
        p = _mul(p, [Fraction(1), Fraction(-1)])
    for _ in range(i):
        p = _deriv(p)
    return p


def _basis(rule: str, cell: int, cap: int):
    """[(sample offset, polynomial in xi = s/dt - cell)] of the interpolant on the cell."""
    one = Fraction(1)
    if rule == "zoh":
        return [(cell + 1, [one])]
    if rule == "foh":
        return [(cell, [one, -one]), (cell + 1, [Fraction(0), one])]
    start = min(max(cell - 1, 0), max(cap - 3, 0))
    # node positions in the local variable xi: 4 (a cubic), 3 (a parabola) where the support
    # holds only 3 samples (cap = 2)
    nodes = [start + q - cell for q in range(4 if cap >= 3 else 3)]
    out = []
    for m, xm in enumerate(nodes):
        poly = [one]
        for q, xq in enumerate(nodes):
            if q != m:
                poly = [c / (xm - xq) for c in _mul(poly, [Fraction(-xq), one])]
        out.append((xm + cell, poly))
    return out


def kernel_weights(N, M, h, i, dt, rule, delay, length):
    """w_l = (1/h) int_tau^{tau+h} beta_l(s) p_i((s - tau)/h) ds in exact rational arithmetic.

    dt, h and delay are converted exactly from their float64 values; the result is rounded
    once to float64, so it is exact to the last bit (integer N, M).
    """
    dtf, hf, tf = Fraction(dt), Fraction(h), Fraction(delay)
    cap = math.ceil((delay + h) / dt - 1e-9)
    w = [Fraction(0)] * length
    pi = _phi_exact(N, M, i)
    for cell in range(length - 1):
        lo = max(cell * dtf, tf)
        hi = min((cell + 1) * dtf, tf + hf)
        if hi <= lo:
            continue
        p_of_xi = _compose_affine(pi, (cell * dtf - tf) / hf, dtf / hf)
        for idx, b in _basis(rule, cell, cap):
            val = _integral(_mul(b, p_of_xi), lo / dtf - cell, hi / dtf - cell) * dtf / hf
            w[min(idx, length - 1)] += val
    return np.array([float(v) for v in w])


def gregory(n_samples, first, dt):
    w = np.zeros(n_samples)
    w[first:] = 1.0
    ends = [3 / 8, 7 / 6, 23 / 24]
    for q, e in enumerate(ends):
        w[first + q] *= e
        w[n_samples - 1 - q] *= e
    return dt * w


def columns(y, u, dt, n, m, N, M, h, rules, delays, y_rule="cubic"):
    """c(t)/h^(N+M+1) columns (T, p) and the first valid index."""
    spans = [h] + [d + h for d in delays]
    length = math.ceil(max(spans) / dt - 1e-9) + 1
    cols = []
    for i in range(n + 1):
        w = kernel_weights(N, M, h, i, dt, y_rule, 0.0, length) * h ** (-i)
        cols.append(np.convolve(y, w)[: len(y)])
    for k, mk in enumerate(m):
        for j in range(mk + 1):
            w = kernel_weights(N, M, h, j, dt, rules[k], delays[k], length) * h ** (-j)
            cols.append(-np.convolve(u[:, k], w)[: len(y)])
    first = max(math.ceil(s / dt - 1e-9) for s in spans)
    return np.stack(cols, axis=1), first


def gram(y, u, dt, n, m, N, M, h, rules, delays, y_rule="cubic"):
    C, first = columns(y, u, dt, n, m, N, M, h, rules, delays, y_rule)
    q = gregory(len(y), first, dt)
    return C.T @ (q[:, None] * C)


def closed_form(G, eta):
    """Eq. (12)."""
    g = np.linalg.solve(G, eta)
    return g / (eta @ g)


def state_space(a, b):
    """Eq. (18) with D for m_k = n."""
    a = np.asarray(a, float) / a[-1]
    n = len(a) - 1
    A = np.zeros((n, n))
    A[1:, :-1] = np.eye(n - 1)
    A[:, -1] = -a[:-1]
    B = np.zeros((n, len(b)))
    D = np.zeros((1, len(b)))
    for k, bk in enumerate(b):
        full = np.zeros(n + 1)
        full[: len(bk)] = np.asarray(bk) / np.asarray(a)[-1]
        D[0, k] = full[n]
        B[:, k] = full[:n] - full[n] * a[:n]
    C = np.zeros((1, n))
    C[0, -1] = 1.0
    return A, B, C, D


def lsim(a, b, u, dt, modes, x0=None):
    """Response by scipy.signal.lsim per input (interp=False for zoh, True for foh)."""
    A, B, C, D = state_space(a, b)
    T = u.shape[0]
    t = np.arange(T) * dt
    y = np.zeros(T)
    for k, mode in enumerate(modes):
        _, yk, _ = signal.lsim(
            (A, B[:, [k]], C, D[:, [k]]), u[:, k], t, X0=x0 if k == 0 else None,
            interp=(mode == "foh"),
        )
        y += yk
    return y


def modal_zoh(poles, b, u, dt):
    """Response of b(s) / prod(s - p) (b in descending powers, distinct poles) to a zoh input
    from rest, mode by mode (partial fractions: each mode's exact zoh recursion, no matrix
    exponential): the reference for stiff models, whose canonical forms are badly scaled."""
    r, p, k = signal.residue(b, np.poly(poles))
    z, y = np.zeros(len(p), complex), np.zeros(len(u))
    for j in range(len(u)):
        y[j] = (r @ z).real + (k[0] * u[j] if len(k) else 0.0)
        z = np.exp(p * dt) * z + (np.exp(p * dt) - 1.0) / p * u[j]
    return y


def expm(M):
    return linalg.expm(M)


def final_state_paper(a, b, t, y, u):
    """Eq. (15) literally: x(T) = int G1 y + int G2 u on a fine grid (trapezoid), SISO or MISO,
    G1(t) = e^{AT} M0^{-1} e^{A't} C', G2(t) = e^{AT} M0^{-1} [int_0^t W(s) ds] e^{-At} B (the
    sign as printed; method.md section 6)."""
    from scipy.integrate import cumulative_trapezoid, trapezoid

    A, B, C, _ = state_space(a, b)
    E = np.stack([linalg.expm(A * tk) for tk in t])  # e^{A t}
    W = np.einsum("kji,jl,klm->kim", E, C.T @ C, E)  # e^{A't} C'C e^{At}
    M0 = trapezoid(W, t, axis=0)
    head = cumulative_trapezoid(W, t, axis=0, initial=0.0)  # int_0^t W(s) ds
    Einv = np.stack([linalg.expm(-A * tk) for tk in t])
    front = linalg.expm(A * t[-1]) @ np.linalg.inv(M0)
    g1 = np.einsum("ij,kjl->kil", front, np.einsum("kji,jl->kil", E, C.T))[:, :, 0]
    g2 = np.einsum("ij,kjl,klm,mn->kin", front, head, Einv, B)
    return trapezoid(g1 * y[:, None], t, axis=0) + trapezoid(
        np.einsum("kin,kn->ki", g2, u.reshape(len(t), -1)), t, axis=0
    )


def initial_state_paper(a, b, t, y, u, sign):
    """Eq. (14) literally: x0 = int Gb1 y + int Gb2 u on a fine grid (trapezoid), SISO or MISO.

    Gb2(t) = sign * M0^{-1} [int_t^T W(s) ds] e^{-At} B; the paper prints sign = +1, the correct
    one is -1 (method.md section 6).
    """
    from scipy.integrate import cumulative_trapezoid, trapezoid

    A, B, C, _ = state_space(a, b)
    E = np.stack([linalg.expm(A * tk) for tk in t])  # e^{A t}
    W = np.einsum("kji,jl,klm->kim", E, C.T @ C, E)  # e^{A't} C'C e^{At}
    M0 = trapezoid(W, t, axis=0)
    cum = cumulative_trapezoid(W, t, axis=0, initial=0.0)
    tail = M0[None] - cum  # int_t^T W(s) ds
    Einv = np.stack([linalg.expm(-A * tk) for tk in t])
    Minv = np.linalg.inv(M0)
    g1 = np.einsum("ij,kjl->kil", Minv, np.einsum("kji,jl->kil", E, C.T))[:, :, 0]
    g2 = sign * np.einsum("ij,kjl,klm,mn->kin", Minv, tail, Einv, B)
    return trapezoid(g1 * y[:, None], t, axis=0) + trapezoid(
        np.einsum("kin,kn->ki", g2, u.reshape(len(t), -1)), t, axis=0
    )
