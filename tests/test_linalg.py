import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg as sl

from mfmjax import _linalg as L

# compiled: eager, each operation of these unrolled kernels is a program of its own (the
# batched and grad test below runs them under vmap and grad)
solve, eigvalsh, expm, hurwitz = (jax.jit(f) for f in (L.solve, L.eigvalsh, L.expm, L.hurwitz))
conditioning_eigvals = jax.jit(L.conditioning_eigvals)


@pytest.mark.parametrize("n", [1, 3, 8, 25])
def test_solve_eigvalsh_expm_match_lapack(n):
    rng = np.random.default_rng(n)
    A, b = rng.normal(size=(n, n)), rng.normal(size=n)
    ref = np.linalg.solve(A, b)
    # backward-stable elimination: error ~ cond(A) * eps
    assert np.max(np.abs(np.asarray(solve(A, b)) - ref)) <= 1e-13 * np.linalg.cond(A) * np.max(
        np.abs(ref))
    S = A @ A.T
    lam = np.linalg.eigvalsh(S)
    assert np.max(np.abs(np.asarray(eigvalsh(S)) - lam)) <= 1e-13 * lam[-1]
    for scale in (1e-3, 1.0, 40.0):
        X = A * scale / n
        E = sl.expm(X)
        # each of the s squarings can double the relative rounding error: bound 1e-14 * 2^s
        s = max(0, int(np.ceil(np.log2(np.max(np.sum(np.abs(X), axis=1)) / 0.5))))
        assert np.max(np.abs(np.asarray(expm(X)) - E)) <= 1e-14 * 2**s * np.max(np.abs(E))


def test_batched_and_grad():
    rng = np.random.default_rng(0)
    As = jnp.asarray(rng.normal(size=(5, 4, 4)))
    bs = jnp.asarray(rng.normal(size=(5, 4)))
    batched = jax.vmap(L.solve)(As, bs)
    assert np.allclose(np.asarray(batched), np.linalg.solve(np.asarray(As), np.asarray(bs)[..., None])[..., 0],
                       rtol=1e-12)
    A = jnp.asarray(rng.normal(size=(3, 3)))

    def f(t):
        return jnp.sum(L.expm(A * t))

    t0, eps = 0.7, 1e-6
    fd = (f(t0 + eps) - f(t0 - eps)) / (2 * eps)
    assert abs(jax.grad(f)(t0) - fd) <= 1e-7 * abs(fd)


def test_small_matmul_is_the_matrix_product_through_jit_vmap_grad_and_scan():
    # A (n, n) @ x as n broadcast products (the simulation scans' state update): the same
    # product as NumPy's to rounding, for a vector and a matrix x, under jit and vmap. Both
    # are within gamma_n |A| |x| of the exact product (gamma_n = n u / (1 - n u), u = eps / 2),
    # so they differ by at most 2 gamma_n <= 2 n eps of |A| |x|. Its derivatives are the
    # product's (bilinear: d/dA = w x^T, d/dx = A^T w, each entry one or n roundings), also
    # inside a scan under forward mode (50 steps of n-term sums of contracting maps: rounding
    # about 50 n eps = 3e-14 relative; 1e-12 leaves a margin for the recursion's growth)
    rng = np.random.default_rng(3)
    for n, tail in ((1, ()), (4, ()), (4, (3,)), (6, (2,))):
        A, x = rng.normal(size=(n, n)), rng.normal(size=(n,) + tail)
        bound = 2 * n * np.finfo(float).eps * (np.abs(A) @ np.abs(x))
        for out in (L.small_matmul(jnp.asarray(A), jnp.asarray(x)),
                    jax.jit(L.small_matmul)(A, x),
                    jax.vmap(L.small_matmul, (None, 0))(A, x[None])[0]):
            assert out.shape == (A @ x).shape
            assert np.all(np.abs(np.asarray(out) - A @ x) <= bound)
    A, x, w = rng.normal(size=(3, 3)), rng.normal(size=3), rng.normal(size=3)
    gA, gx = jax.grad(lambda A, x: w @ L.small_matmul(A, x), (0, 1))(A, x)
    assert np.allclose(gA, np.outer(w, x), rtol=1e-14, atol=1e-15)
    assert np.allclose(gx, A.T @ w, rtol=1e-14, atol=1e-15)
    ds = rng.normal(size=(50, 3))

    def run(Phi):  # a state recursion as in `simulate`; its Jacobian in Phi, forward mode
        return jax.lax.scan(lambda z, d: (L.small_matmul(Phi, z) + d,) * 2, jnp.zeros(3), ds)[1]

    def ref(Phi):
        return jax.lax.scan(lambda z, d: (Phi @ z + d,) * 2, jnp.zeros(3), ds)[1]

    P = 0.3 * A
    assert np.allclose(run(P), ref(P), rtol=1e-13, atol=1e-14)
    assert np.allclose(jax.jacfwd(run)(P), jax.jacfwd(ref)(P), rtol=1e-12, atol=1e-13)


def test_expm_stops_squaring_at_s_with_the_static_loops_results_and_derivatives():
    # the while loop runs the same products as the static loop of masked squarings (a batch:
    # until its largest s, each matrix kept once its own s is reached): equal bitwise, jitted
    # and vmapped over matrices needing 0 to 9 squarings; its derivative is the static loop's
    # (a while loop has no reverse mode), in both modes
    rng = np.random.default_rng(3)
    As = jnp.asarray(rng.normal(size=(6, 5, 5)) * np.array([1e-3, 0.1, 1.0, 5.0, 40.0, 300.0])
                     [:, None, None])
    fast, static = jax.jit(jax.vmap(L.expm)), jax.jit(jax.vmap(L._expm_static))
    np.testing.assert_array_equal(np.asarray(fast(As)), np.asarray(static(As)))
    for A in As[:3]:
        np.testing.assert_array_equal(np.asarray(expm(A)), np.asarray(jax.jit(L._expm_static)(A)))

    def loss(f):
        return lambda A: jnp.sum(jnp.sin(f(A)))

    for A in As[:4]:
        for d in (jax.grad, jax.jacfwd):
            np.testing.assert_array_equal(np.asarray(jax.jit(d(loss(L.expm)))(A)),
                                          np.asarray(jax.jit(d(loss(L._expm_static)))(A)))


@pytest.mark.parametrize(
    "a", [[1, 3.5, 3.5, 1], [2, 3, 1, 0], [1, -1, 1], [0, 1, 1], [1, 0, 1], [62.86e-6, 10.82e-3, 1],
          [1, 2, 3, 4, 1, 0, 0], [-1, 0, 1], [6, 11, 6, 1, 0]])
def test_hurwitz_matches_roots(a):
    roots = np.roots(np.trim_zeros(np.asarray(a, float)[::-1], "f"))
    assert bool(hurwitz(jnp.asarray(a, dtype=float))) == bool(np.all(roots.real < 0))


@pytest.mark.parametrize("n", [1, 2, 5, 14])
def test_conditioning_eigvals_relative_accuracy(n):
    # PSD with eigenvalues spread over 1e-9..1 (and one exact zero): log-bisection gives every
    # eigenvalue above the floor (Gershgorin bound * eps^2) to 1e-4 relative; the Householder
    # step adds ~n eps ||A|| absolute, which is below 1e-4 of 1e-9 for these sizes
    rng = np.random.default_rng(n)
    Q, _ = np.linalg.qr(rng.normal(size=(n, n)))
    lam = np.logspace(-9, 0, n)
    lam[0] = 0.0 if n > 2 else lam[0]
    S = (Q * lam) @ Q.T
    S = (S + S.T) / 2
    got = np.asarray(conditioning_eigvals(S, jnp.arange(n)))
    ref = np.linalg.eigvalsh(S)
    floor = np.max(np.sum(np.abs(S), axis=1)) * np.finfo(float).eps ** 2
    live = ref > 1e3 * n * np.finfo(float).eps * ref[-1]
    assert np.all(np.abs(got[live] - ref[live]) <= 1e-4 * ref[live])
    assert np.all(got[~live] <= 1e3 * n * np.finfo(float).eps * ref[-1] + floor)
    # batched, and one index
    many = jax.vmap(lambda A: L.conditioning_eigvals(A, jnp.asarray([n - 1])))(jnp.stack([S, 2 * S]))
    assert np.allclose(np.asarray(many)[:, 0], [ref[-1], 2 * ref[-1]], rtol=1e-4)
