import jax
import jax.numpy as jnp
import numpy as np
import pytest
import reference as R
from scipy.integrate import quad

from mfmjax import ModulatingFunction
from mfmjax._quadrature import gregory_weights, kernel_length, kernel_weights

CASES = [  # N, M, h, dt, delay: fractional h and delay on purpose
    (3, 4, 2.03, 0.1, 0.35),
    (4, 5, 1.0, 0.1, 0.0),
    (2, 2, 0.55, 0.1, 0.07),
    (6, 5, 1.9, 0.1, 0.0),
    (3, 4, 0.2, 0.1, 0.0),  # h = 2 dt: a support of 3 samples (the cubic rule's parabola)
]


# one compiled program per (i, dt, rule, length) instead of dozens of eager operations each
# (the eager path is checked by the tests below)
_weights = jax.jit(kernel_weights, static_argnums=(1, 2, 3, 5))


@pytest.mark.parametrize("rule", ["zoh", "foh", "cubic"])
@pytest.mark.parametrize("N,M,h,dt,tau", CASES)
def test_weights_equal_exact_reference(rule, N, M, h, dt, tau):
    # the reference is exact rational arithmetic: the only error is float64 rounding, 1e-12
    L = kernel_length(h + tau, dt)
    for i in range(3):
        got = np.asarray(_weights(ModulatingFunction(N, M, h), i, dt, rule, tau, L))
        ref = R.kernel_weights(N, M, h, i, dt, rule, tau, L)
        assert np.max(np.abs(got - ref)) <= 1e-12 * np.max(np.abs(ref))


def _error(rule, dt, i=1, h=2.03, tau=0.35):
    mf = ModulatingFunction(3, 4, h)
    L = kernel_length(h + tau, dt)
    w = np.asarray(kernel_weights(mf, i, dt, rule, tau, L))
    s = np.arange(L) * dt
    ex = quad(lambda v: np.sin(v) * R.phi(v - tau, 3, 4, h, i) / h ** (3 + 4 - i + 1), tau,
              tau + h, epsabs=1e-15, epsrel=1e-14)[0]
    return abs(w @ np.sin(s) - ex)


def test_convergence_orders():
    # on a smooth signal the cubic rule is O(dt^4) (ratio 16 per halving), foh O(dt^2) (4);
    # observed ratios must be within 20% of those
    for rule, order in (("foh", 2), ("cubic", 4)):
        e1, e2 = _error(rule, 0.05), _error(rule, 0.025)
        assert 0.8 * 2**order <= e1 / e2 <= 1.25 * 2**order, (rule, e1 / e2)
    assert _error("cubic", 0.05) < 1e-3 * _error("foh", 0.05)


@pytest.mark.parametrize("h,tau", [(1.23, 0.4), (0.2, 0.0)])
def test_zero_beyond_support_and_constant_integral(h, tau):
    # h = 2 dt: the cubic rule's 4th node (lag 3) lay before the support: at the first valid
    # sample it read the sample before the record, as 0 (a 100 % coefficient error with an
    # offset and a level of 1e4, before the columns were centred)
    mf = ModulatingFunction(3, 4, h)
    L = kernel_length(3.0, 0.1)
    for rule in ("zoh", "foh", "cubic"):
        w = np.asarray(kernel_weights(mf, 0, 0.1, rule, tau, L))
        assert np.all(w[int(np.ceil((h + tau) / 0.1 - 1e-9)) + 1 :] == 0.0)
        # all rules integrate a constant exactly: sum w = B(N+1, M+1)
        assert abs(w.sum() - 1 / 280) <= 1e-15
        w1 = np.asarray(kernel_weights(mf, 1, 0.1, rule, 0.4, L))
        assert abs(w1.sum()) <= 1e-15


def test_jit_vmap_grad_in_h_and_delay():
    L = kernel_length(2.5, 0.1)

    def f(h, tau):
        return kernel_weights(ModulatingFunction(3, 4, h, h_max=2.0), 1, 0.1, "cubic", tau, L)

    hs = jnp.asarray([1.0, 1.37, 1.9])
    eager = np.stack([np.asarray(f(h, 0.2)) for h in hs])
    assert np.array_equal(np.asarray(jax.vmap(lambda h: f(h, 0.2))(hs)), eager)
    assert np.allclose(np.asarray(jax.jit(f)(1.37, 0.2)), eager[1], rtol=0, atol=1e-15)
    x = np.cos(np.arange(L) * 0.1)

    def g(h, tau):
        return f(h, tau) @ x

    # (tau + h)/dt = 15.8 stays inside one stencil choice of the cubic rule under +-eps
    # (grad and the differences compiled: eager, each operation of the grad is a program)
    g_jit = jax.jit(g)
    for argnum in (0, 1):
        args = [1.37, 0.21]
        grad = jax.jit(jax.grad(g, argnums=argnum))(*args)
        eps = 1e-6
        hi, lo = list(args), list(args)
        hi[argnum] += eps
        lo[argnum] -= eps
        fd = (g_jit(*hi) - g_jit(*lo)) / (2 * eps)
        assert abs(grad - fd) <= 1e-6 * abs(fd) + 1e-12
    # traced values past what eager calls refuse: NaN (a support beyond L gave the cut-off
    # weights, a sum of 2.3e-4 for 7.9e-4; a negative delay gave finite weights)
    f_jit = jax.jit(f)
    assert np.all(np.isnan(np.asarray(f_jit(2.4, 0.2))))  # (h + tau) / dt = 26 > L - 1
    assert np.all(np.isnan(np.asarray(f_jit(1.37, -0.1))))
    with pytest.raises(ValueError, match="shorter than the support"):
        kernel_weights(ModulatingFunction(3, 4, 2.4), 1, 0.1, "cubic", 0.2, L)


def test_gregory_weights():
    q = np.asarray(gregory_weights(20, 5, 0.5))
    assert np.array_equal(q, R.gregory(20, 5, 0.5))
    t = np.arange(20) * 0.5
    # exact for cubics on the valid part [2.5, 9.5]
    assert abs(q @ t**3 - (9.5**4 - 2.5**4) / 4) <= 1e-12 * 9.5**4


def test_legendre_expansion_reproduces_phi():
    # search's moment basis: p_i = sum_q c_q P_q(2r - 1) exactly (degree N + M - i <= degree);
    # the projection is a Gauss rule, exact, so only float64 rounding of ~20 terms: 1e-11
    from numpy.polynomial import legendre as npleg

    from mfmjax._quadrature import legendre_coefficients

    pairs = [(3, 3), (4, 7), (8, 8), (5, 2)]
    r = np.linspace(0.0, 1.0, 41)
    for i in range(4):
        coef = legendre_coefficients([a for a, _ in pairs], [b for _, b in pairs], i, 16)
        for (N, M), c in zip(pairs, coef):
            ref = R.phi_poly(N, M, i)(r)
            got = npleg.legval(2 * r - 1, c)
            assert np.max(np.abs(got - ref)) <= 1e-11 * max(1.0, np.max(np.abs(ref)))


def test_shift_samples_is_the_clipped_index_for_every_lag_window_and_batch():
    # x[clip(j - lag, 0, T - 1)] for j in the record or in a window of consecutive samples,
    # lags from -1 (the next sample) to beyond the window's front padding; jitted, and vmapped
    # over the lag (the search's candidates differ in their delays)
    from mfmjax._quadrature import shift_samples

    x = jnp.asarray(np.random.default_rng(0).normal(size=50))
    lags = jnp.asarray([-1, 0, 1, 7, 49, 50, 61, 140])
    # windows that run past the record's end (a buffer beyond it: the held last sample)
    for start, length in ((None, 50), (0, 12), (20, 12), (38, 12), (45, 30), (49, 50)):
        j = np.arange(50) if start is None else start + np.arange(length)
        rows = None if start is None else jnp.asarray(j)
        want = np.stack([np.asarray(x)[np.clip(j - int(lag), 0, 49)] for lag in lags])
        got = jax.jit(jax.vmap(lambda lag, r=rows: shift_samples(x, lag, r)))(lags)
        np.testing.assert_array_equal(np.asarray(got), want)


def test_window_bucket_keeps_one_bucket_for_a_share_across_a_record_bucket():
    """A window that is a share of its record, cut as `holdout_folds` cuts them (a hold-out
    block of L = round(s T) samples and a fit part of T - L), gets one `window_bucket` for
    every record length T of a record bucket: shares whose length in the bucket falls on a
    bucket edge (1/3 and 2/3 of 1536 are 512 and 1024), shares on the 1/48 steps (1/4, 1/2)
    and small ones (5 % of 1024: 51 samples, which `record_bucket` keeps as they are; 64
    now). The bucket holds the window and at most the record's bucket, which the whole
    record gets."""
    from mfmjax._quadrature import record_bucket, window_bucket

    for lo, hi in ((513, 640), (1025, 1280), (1281, 1536), (1537, 1792), (2561, 3072),
                   (7169, 8192)):
        assert record_bucket(lo) == record_bucket(hi) != record_bucket(lo - 1)
        for share in (0.05, 0.1, 0.2, 0.25, 0.3, 1 / 3, 0.4, 0.5):
            L = {T: max(round(share * T), 1) for T in range(lo, hi + 1)}
            assert len({window_bucket(L[T], T) for T in L}) == 1, (lo, share)
            assert len({window_bucket(T - L[T], T) for T in L}) == 1, (lo, 1 - share)
        for T in (lo, hi):
            assert window_bucket(T, T) == record_bucket(T)
            for length in (8, 100, T // 2, T - 1):
                assert length <= window_bucket(length, T) <= record_bucket(T)


def test_split_delay_takes_a_whole_number_of_samples_typed_in_decimals_as_whole():
    """tau = k dt computed in decimals (k * 0.37 / 0.37 rounds to either side of k) is k
    samples and f = 0 exactly (a zoh input's held value changes sample at f = 0); a delay a
    fraction off the grid keeps its fraction; df/dtau = 1/dt on and off the grid (jit, grad)."""
    from mfmjax._quadrature import split_delay

    for dt in (0.01, 0.1, 0.3, 0.37, 3.3):
        k = np.arange(0, 201)
        d, f = jax.jit(split_delay, static_argnums=1)(jnp.asarray(k * dt), dt)
        np.testing.assert_array_equal(np.asarray(d), k)
        np.testing.assert_array_equal(np.asarray(f), 0.0)
        d, f = split_delay(jnp.asarray((k + 0.25) * dt), dt)
        np.testing.assert_array_equal(np.asarray(d), k)
        np.testing.assert_allclose(np.asarray(f), 0.25, rtol=0, atol=1e-12)  # k dt / dt: 1e-14
    for tau, dt in ((22 * 0.37, 0.37), (22.25 * 0.37, 0.37), (1.0, 0.5)):  # 1.0 / 0.5 = 2
        slope = jax.grad(lambda t, dt=dt: split_delay(t, dt)[1])(tau)  # exactly: the old clip
        np.testing.assert_allclose(float(slope), 1 / dt, rtol=1e-15)  # halved it (1 / (2 dt))
