"""Small dense linear algebra in plain XLA ops (no LAPACK custom calls).

jaxlib's batched LAPACK kernels on CPU split a batch over a thread pool and block on it; two
of them running concurrently under `vmap` deadlocked on this 2-core machine (seen with gdb in
`ParallelBatchMap`). The matrices of the method are tiny (p <= ~30), so loops of vectorised
row operations are fast and safe in every batched path; gradients flow through all of them.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

JACOBI_SWEEPS = 10  # Jacobi converges quadratically: 10 sweeps reach rounding for p <= 40
_SQUARINGS = 48  # static bound on expm squarings (||A|| up to 2^47): static trip count for grad
_TAYLOR = 18  # Taylor degree on ||A / 2^s|| <= 1/2: truncation < 1e-21


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


def _round_robin(n: int) -> np.ndarray:
    """(n-1, n/2, 2) disjoint index pairs per round covering every pair once (n even)."""
    players = list(range(n))
    rounds = []
    for _ in range(n - 1):
        rounds.append([(players[k], players[n - 1 - k]) for k in range(n // 2)])
        players = [players[0], players[-1]] + players[1:-1]
    return np.asarray(rounds, dtype=np.int32)


def eigvalsh(A):
    """Eigenvalues (ascending) of a symmetric matrix by parallel (round-robin) Jacobi sweeps.

    Each round applies n/2 disjoint rotations at once as one orthogonal similarity R A R^T.
    """
    n = A.shape[-1]
    if n == 1:
        return A.reshape(1)
    m = n + (n % 2)  # pad to even size with a decoupled zero row/column
    A = jnp.zeros((m, m), dtype=A.dtype).at[:n, :n].set(A)
    rounds = _round_robin(m)
    onehot = np.eye(m)
    Ei = jnp.asarray(onehot[rounds[:, :, 0]])  # (rounds, m/2, m)
    Ej = jnp.asarray(onehot[rounds[:, :, 1]])

    def rotate(r, A):
        ei, ej = Ei[r % (m - 1)], Ej[r % (m - 1)]
        aii = jnp.einsum("pk,kl,pl->p", ei, A, ei)
        ajj = jnp.einsum("pk,kl,pl->p", ej, A, ej)
        aij = jnp.einsum("pk,kl,pl->p", ei, A, ej)
        small = jnp.abs(aij) <= 1e-300
        theta = (ajj - aii) / (2.0 * jnp.where(small, 1.0, aij))
        t = jnp.sign(theta) / (jnp.abs(theta) + jnp.sqrt(theta * theta + 1.0))
        t = jnp.where(small, 0.0, jnp.where(theta == 0, 1.0, t))
        c = 1.0 / jnp.sqrt(t * t + 1.0)
        s = t * c
        R = ((ei.T * c) @ ei + (ej.T * c) @ ej - (ei.T * s) @ ej + (ej.T * s) @ ei)
        return R @ A @ R.T

    A = jax.lax.fori_loop(0, JACOBI_SWEEPS * (m - 1), rotate, A)
    return jnp.sort(jnp.diagonal(A)[:n])


def expm(A):
    """Matrix exponential: Taylor on A / 2^s, then s squarings (static loop bound, grad-safe)."""
    n = A.shape[-1]
    norm = jnp.max(jnp.sum(jnp.abs(A), axis=1))
    s = jnp.clip(jnp.ceil(jnp.log2(jnp.maximum(norm, 1e-300) / 0.5)), 0, _SQUARINGS)
    X = A / (2.0**s)
    eye = jnp.eye(n, dtype=A.dtype)
    E = eye
    for k in range(_TAYLOR, 0, -1):  # Horner: I + X/1 (I + X/2 (I + ...))
        E = eye + (X @ E) / k

    def square(i, E):
        return jnp.where(i < s, E @ E, E)

    return jax.lax.fori_loop(0, _SQUARINGS, square, E)


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
