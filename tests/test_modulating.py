import jax
import jax.numpy as jnp
import numpy as np
import pytest
import reference as R

import mfmjax
from mfmjax import ModulatingFunction, phi, phi_integral


@pytest.mark.parametrize("N,M,h", [(3, 4, 50.0), (5, 6, 2.5), (2, 7, 1.0), (8, 8, 3.7)])
def test_phi_matches_reference(N, M, h):
    mf = ModulatingFunction(N, M, h)
    t = np.linspace(-0.1 * h, 1.1 * h, 101)
    for i in range(min(N, M) + 2):
        ref = R.phi(t, N, M, h, i)
        got = np.asarray(phi(t, mf, i))
        # Leibniz form vs monomial expansion: both exact to rounding of O(2^(N+M)) terms
        assert np.max(np.abs(got - ref)) <= 1e-12 * np.max(np.abs(ref)), i
        # the host evaluation (search plans): the same Leibniz form in NumPy, same bound
        host = h ** (N + M - i) * mfmjax.phi_scaled(t / h, N, M, i, xp=np)
        assert isinstance(host, np.ndarray)
        assert np.max(np.abs(host - ref)) <= 1e-12 * np.max(np.abs(ref)), i


def test_eager_phi_at_new_exponents_compiles_nothing():
    """Eager `phi`, `phi_integral` and `kernel_weights` at new integer exponents N, M reuse the
    programs of the first ones: the exponents are float64 values, not static `integer_pow`
    exponents (before, 6 `integer_pow` programs for (5, 6) after (3, 4)). Values: the NumPy
    twin, 1e-12 relative as above."""
    from jaxlog import compiles

    from mfmjax._quadrature import kernel_weights

    t = np.linspace(0.0, 2.0, 41)

    def calls(mf):
        return (phi(t, mf, 1), phi_integral(0.1, 1.5, mf, 0), phi_integral(0.1, 1.5, mf, 2),
                kernel_weights(mf, 1, 0.05, "foh", 0.0, 48))

    calls(ModulatingFunction(3, 4, 2.0))
    with compiles() as names:
        got = calls(ModulatingFunction(5, 6, 2.0))
    assert names == [], f"new exponents compiled {names}"
    ref = R.phi(t, 5, 6, 2.0, 1)
    assert np.max(np.abs(np.asarray(got[0]) - ref)) <= 1e-12 * np.max(np.abs(ref))
    ref = R.phi(1.5, 5, 6, 2.0, 1) - R.phi(0.1, 5, 6, 2.0, 1)
    assert abs(float(got[2]) - ref) <= 1e-12 * np.max(np.abs(R.phi(t, 5, 6, 2.0, 1)))


def test_phi_vanishes_at_ends_and_is_consistent():
    mf = ModulatingFunction(3, 4, 2.0)
    for i in range(3):
        assert float(phi(0.0, mf, i)) == 0.0 and float(phi(2.0, mf, i)) == 0.0
    # d/dt phi^(i) = phi^(i+1): central difference, error O(eps^2) ~ 1e-10 relative
    t, eps = np.linspace(0.1, 1.9, 9), 1e-5
    for i in range(4):
        fd = (phi(t + eps, mf, i) - phi(t - eps, mf, i)) / (2 * eps)
        assert np.allclose(fd, phi(t, mf, i + 1), rtol=0, atol=1e-8 * np.max(np.abs(phi(t, mf, i + 1))))


def test_phi_at_the_ends_is_the_one_sided_value_for_every_order():
    """For i >= N (or i >= M) phi^(i) jumps at t = 0 (or h): the value on [0, h] is the
    one-sided one (the exact reference's); it was 0, so phi_integral(0, h, i=4) of (3, 4, 2)
    was 0 instead of phi^(3)(h) - phi^(3)(0) = -96. A NaN time gives NaN (it gave 0)."""
    mf = ModulatingFunction(3, 4, 2.0)
    t = np.array([0.0, 0.7, 2.0])
    for i in range(8):
        ref = R.phi(t, 3, 4, 2.0, i)
        assert np.allclose(np.asarray(phi(t, mf, i)), ref, rtol=1e-12, atol=0), i
    assert float(phi_integral(0.0, 2.0, mf, 4)) == -96.0
    assert np.isnan(float(phi(np.nan, mf))) and np.isnan(float(phi(np.nan, mf, 2)))


def test_phi_integral_exact():
    from scipy.integrate import quad

    mf = ModulatingFunction(3, 4, 2.0)
    for i in range(4):
        ref = quad(lambda s: R.phi(s, 3, 4, 2.0, i), 0.3, 1.7, epsabs=1e-15, epsrel=1e-14)[0]
        assert abs(float(phi_integral(0.3, 1.7, mf, i)) - ref) <= 1e-12 * max(1.0, abs(ref))


def test_phi_differentiable_in_h():
    t = 0.7

    def f(h):
        return phi(t, ModulatingFunction(3, 4, h, h_max=3.0), 1)

    h0, eps = 2.0, 1e-6
    g = jax.grad(f)(h0)
    fd = (f(h0 + eps) - f(h0 - eps)) / (2 * eps)
    assert abs(g - fd) <= 1e-7 * abs(fd)


@pytest.mark.parametrize(
    "kwargs,match",
    [
        (dict(N=0, M=3, h=1.0), "N must be"),
        (dict(N=3, M=float("nan"), h=1.0), "M must be"),
        (dict(N=3, M=3, h=0.0), "h must be > 0"),
        (dict(N=3, M=3, h=-2.0), "h must be > 0"),
        (dict(N=12, M=12, h=1.0), "N \\+ M must be"),
        (dict(N=3, M=3, h=2.0, h_max=1.0), "exceeds h_max"),
    ],
)
def test_bad_settings(kwargs, match):
    with pytest.raises(ValueError, match=match):
        ModulatingFunction(**kwargs)


def test_float64_everywhere():
    mf = ModulatingFunction(3, 4, 2.0)
    assert phi(jnp.asarray([0.5]), mf, 2).dtype == jnp.float64
    assert mfmjax.kernel_weights(mf, 1, 0.1, "cubic", 0.0, 22).dtype == jnp.float64
