"""Small dense linear algebra in plain XLA ops (no LAPACK custom calls).

jaxlib's batched LAPACK kernels on CPU split a batch over a thread pool and block on it; two
of them running concurrently under `vmap` deadlocked on this 2-core machine (seen with gdb in
`ParallelBatchMap`). The matrices of the method are tiny (p <= ~30), so loops of vectorised
row operations are fast and safe in every batched path; gradients flow through `solve` and
`expm` (`eigvalsh` only feeds conditioning flags).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

BISECTIONS = 64  # halvings of the Gershgorin interval: below eps * ||A|| (2^-64 < 1e-19)
CONDITIONING_BISECTIONS = 20  # log-halvings of 104 octaves: final bracket 1e-4 octaves
_SQUARINGS = 48  # static bound on expm squarings (||A|| up to 2^47): static trip count for grad
_TAYLOR = 18  # Taylor degree on ||A / 2^s|| <= 1/2: truncation < 1e-21
EXPM_RANGE = 2.0 ** (_SQUARINGS - 2)  # |pole| dt beyond which expm's squarings run out (the
# balanced matrix's 1-norm is about 1-2x its largest eigenvalue's magnitude)
_BALANCE_SWEEPS = 8  # balancing steps before expm (a companion matrix of poles 1 to 2e7:
# its 1-norm at dt = 0.1 from 4e13 to 4.7e6 in 8)


def small_matmul(A, x):
    """A (n, n) @ x (n, ...) as n broadcast products summed: inside a `lax.scan` body these
    fuse into one loop, where a dot is a call of its own at every step (and, under
    forward-mode differentiation, one per tangent product). Measured on 8192 samples, n = 4:
    output error's residual with its 10-column Jacobian 2.0 against 8.9 ms."""
    shape = (-1,) + (1,) * (x.ndim - 1)
    return sum(A[:, j].reshape(shape) * x[j] for j in range(A.shape[1]))


def solve(A, b):
    """Solve A x = b (A (n, n), b (n,)) by Gaussian elimination with partial pivoting."""
    n = A.shape[-1]
    idx = jnp.arange(n)
    M = jnp.concatenate([A, b[:, None]], axis=1)

    def eliminate(k, M):
        piv = jnp.argmax(jnp.where(idx >= k, jnp.abs(M[:, k]), -1.0))
        rk, rp = M[k], M[piv]
        M = M.at[k].set(rp).at[piv].set(rk)
        f = jnp.where(idx > k, M[:, k] / M[k, k], 0.0)
        return M - f[:, None] * M[k][None, :]

    M = jax.lax.fori_loop(0, n, eliminate, M)

    def back(i, x):
        k = n - 1 - i
        return x.at[k].set((M[k, n] - M[k, :n] @ x) / M[k, k])

    return jax.lax.fori_loop(0, n, back, jnp.zeros(n, dtype=M.dtype))


def _tridiagonal(A):
    """Householder reduction of a symmetric A to tridiagonal (diagonal d, off-diagonal e).

    Step k reflects column k below the subdiagonal to zero: a rank-2 update of the whole
    (fixed-size) matrix, in a loop (one compiled step for any size)."""
    n = A.shape[-1]
    idx = jnp.arange(n)

    def step(k, carry):
        A, d, e = carry
        col = jax.lax.dynamic_index_in_dim(A, k, axis=1, keepdims=False)
        x = jnp.where(idx > k, col, 0.0)
        sub = jax.lax.dynamic_index_in_dim(col, k + 1, keepdims=False)
        alpha = -jnp.where(sub >= 0, 1.0, -1.0) * jnp.sqrt(x @ x)
        v = x - jnp.where(idx == k + 1, alpha, 0.0)
        vv = v @ v
        beta = jnp.where(vv > 0, 2.0 / jnp.where(vv > 0, vv, 1.0), 0.0)
        pv = beta * (A @ v)
        w = pv - (0.5 * beta * (pv @ v)) * v
        d = d.at[k].set(jax.lax.dynamic_index_in_dim(col, k, keepdims=False))
        return A - jnp.outer(v, w) - jnp.outer(w, v), d, e.at[k].set(alpha)

    A, d, e = jax.lax.fori_loop(0, n - 2, step, (A, jnp.zeros(n, A.dtype), jnp.zeros(n - 1, A.dtype)))
    d = d.at[n - 2].set(A[n - 2, n - 2]).at[n - 1].set(A[n - 1, n - 1])
    return d, e.at[n - 2].set(A[n - 1, n - 2])


def _sturm(A):
    """Tridiagonalise a symmetric A; return (count, lo, hi): count(x) = number of eigenvalues
    below x (negative pivots of the LDL^T of T - x I, Sylvester) and a Gershgorin bracket."""
    n = A.shape[-1]
    d, e = _tridiagonal(A)
    radius = jnp.abs(jnp.append(e, 0.0)) + jnp.abs(jnp.append(0.0, e))
    pivmin = jnp.finfo(A.dtype).tiny / jnp.finfo(A.dtype).eps * jnp.maximum(1.0, jnp.max(e * e))
    e2 = e * e

    def count(x):
        def pivot(i, carry):
            q, below = carry
            q = d[i] - x - e2[i - 1] / q
            q = jnp.where(jnp.abs(q) < pivmin, -pivmin, q)
            return q, below + (q < 0)

        q = d[0] - x
        q = jnp.where(jnp.abs(q) < pivmin, -pivmin, q)
        return jax.lax.fori_loop(1, n, pivot, (q, (q < 0).astype(jnp.int32)))[1]

    return count, jnp.min(d - radius), jnp.max(d + radius)


def _bisect(count, which, lo, hi, steps: int, mid):
    def halve(_, bracket):
        lo, hi = bracket
        x = mid(lo, hi)
        up = count(x) > which
        return jnp.where(up, lo, x), jnp.where(up, x, hi)

    init = (jnp.full(which.shape, lo), jnp.full(which.shape, hi))
    return mid(*jax.lax.fori_loop(0, steps, halve, init))


def eigvalsh(A, which=None):
    """Eigenvalues (ascending) of a symmetric matrix; `which` (int array) selects some by index.

    Householder tridiagonalisation, then bisection on the Sturm count for every wanted index
    at once, `BISECTIONS` halvings of the Gershgorin interval: absolute error ~ n eps ||A||
    (backward stable), a fixed trip count. Not differentiated (`stop_gradient`).
    """
    A = jax.lax.stop_gradient(jnp.asarray(A))
    n = A.shape[-1]
    which = jnp.arange(n) if which is None else jnp.asarray(which)
    if n == 1:
        return jnp.broadcast_to(A.reshape(1), which.shape)
    count, lo, hi = _sturm(A)
    return _bisect(count, which, lo, hi, BISECTIONS, lambda a, b: 0.5 * (a + b))


def conditioning_eigvals(A, which):
    r"""Eigenvalues of a positive semi-definite A at indices `which`, to relative accuracy
    1e-4: bisection on $\log \lambda$ over $[\lambda_{hi}\,\epsilon^2, \lambda_{hi}]$
    ($\lambda_{hi}$ the Gershgorin bound). `CONDITIONING_BISECTIONS` steps instead of
    `BISECTIONS`; values at or below the floor (zero, or negative by rounding) return the
    floor. For condition numbers and the flags on them; not differentiated."""
    A = jax.lax.stop_gradient(jnp.asarray(A))
    which = jnp.asarray(which)
    if A.shape[-1] == 1:
        return jnp.broadcast_to(jnp.maximum(A.reshape(1), 0.0), which.shape)
    count, _, hi = _sturm(A)
    hi = jnp.maximum(hi, jnp.finfo(A.dtype).tiny)
    lo = hi * jnp.finfo(A.dtype).eps ** 2
    return _bisect(count, which, lo, hi, CONDITIONING_BISECTIONS, lambda a, b: jnp.sqrt(a * b))


def balance(A):
    """Powers of 2 d (n,) with D^-1 A D (D = diag(d)) roughly balanced: each off-diagonal row
    and column of about equal 1-norm (Parlett-Reinsch's aim, as LAPACK's gebal; every scaling
    moves at once, half the way to its row's balance, a fixed number of times: no sequential
    loop, no oscillation).
    Exact in floating point; constant in A (no derivative): expm(A) = D expm(D^-1 A D) D^-1.
    The canonical form of a stiff model (poles -1, -1e7, -2e7 at dt = 0.1: 1-norm 4e13) took
    47 squarings where the balanced one (4.7e6) takes 24, and its step response erred by 1e-7
    (scipy: 1e-9; balanced 5e-9)."""
    n = A.shape[-1]
    B = jnp.abs(jax.lax.stop_gradient(A)) * (1.0 - jnp.eye(n, dtype=A.dtype))

    def step(_, e):  # e = log2 d, within +-256 (d and d_j / d_i finite whatever A holds)
        scaled = B * jnp.exp2(e[None, :] - e[:, None])
        r, c = jnp.sum(scaled, axis=1), jnp.sum(scaled, axis=0)
        ok = (r > 0) & (c > 0)
        gap = jnp.log2(jnp.where(ok, r, 1.0)) - jnp.log2(jnp.where(ok, c, 1.0))
        return jnp.clip(e + jnp.where(ok, jnp.round(0.25 * gap), 0.0), -256.0, 256.0)

    return jnp.exp2(jax.lax.fori_loop(0, _BALANCE_SWEEPS, step, jnp.zeros(n, A.dtype)))


def _scaled_taylor(A):
    """(Taylor's e^{A / 2^s}, s) with ||A / 2^s|| <= 1/2 (s <= _SQUARINGS)."""
    n = A.shape[-1]
    norm = jnp.max(jnp.sum(jnp.abs(A), axis=1))
    s = jnp.clip(jnp.ceil(jnp.log2(jnp.maximum(norm, 1e-300) / 0.5)), 0, _SQUARINGS)
    X = A / (2.0**s)
    eye = jnp.eye(n, dtype=A.dtype)

    def horner(i, E):  # I + X/1 (I + X/2 (I + ...)), k = _TAYLOR .. 1 (a loop: one copy)
        return eye + (X @ E) / (_TAYLOR - i).astype(A.dtype)

    return jax.lax.fori_loop(0, _TAYLOR, horner, eye), s


def _expm_static(A):
    """`expm` with a static loop of _SQUARINGS masked squarings: differentiable in both modes
    (`expm`'s derivative)."""
    E, s = _scaled_taylor(A)

    def square(i, E):
        return jnp.where(i < s, E @ E, E)

    return jax.lax.fori_loop(0, _SQUARINGS, square, E)


@jax.custom_jvp
def expm(A):
    """Matrix exponential: Taylor on A / 2^s, then s squarings. The squarings stop at s (a
    batch: at its largest s) instead of running all _SQUARINGS masked ones: the search's
    validation simulations take 6 per candidate (the input terms), 62 -> 19 us. The same
    products as `_expm_static`, whose derivative `expm` uses (grad-safe: a while loop has no
    reverse mode). Badly scaled matrices need squarings they cannot afford: balance them
    first (`balance`, as `step_terms` does)."""
    E, s = _scaled_taylor(A)
    _, E = jax.lax.while_loop(lambda c: c[0] < s, lambda c: (c[0] + 1, c[1] @ c[1]), (0, E))
    return E


@expm.defjvp
def _expm_jvp(primals, tangents):
    return jax.jvp(_expm_static, primals, tangents)


def hurwitz(a):
    r"""True when $\sum_{i\le n} a_i s^i$ ($a_n > 0$, trailing zeros allowed) has every root in
    the open left half plane: the first column of the Routh array is positive."""
    a = jnp.asarray(a)
    N = a.shape[0] - 1  # padded degree; actual degree n = index of the last nonzero
    n = jnp.max(jnp.where(a != 0, jnp.arange(N + 1), 0))
    desc = jnp.where(jnp.arange(N + 1) <= n, a[jnp.clip(n - jnp.arange(N + 1), 0, N)], 0.0)
    width = N // 2 + 2
    r0 = jnp.zeros(width).at[: math.ceil((N + 1) / 2)].set(desc[0::2])
    r1 = jnp.zeros(width).at[: (N + 1) // 2].set(desc[1::2])
    first = [r0[0], r1[0]]
    for _ in range(N - 1):
        safe = jnp.where(r1[0] != 0, r1[0], 1.0)
        r2 = jnp.concatenate([(r1[0] * r0[1:] - r0[0] * r1[1:]) / safe, jnp.zeros(1)])
        r0, r1 = r1, r2
        first.append(r1[0])
    first = jnp.stack(first)
    return jnp.all(jnp.where(jnp.arange(N + 1) <= n, first > 0, True))
