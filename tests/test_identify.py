import jax
import jax.numpy as jnp
import numpy as np
import pytest

import mfmjax
from mfmjax import ModulatingFunction, Signals, Structure
from mfmjax.datasets import paper_table3_model1, simulated_experiment, third_order_two_input


def _params(model):
    return np.concatenate([np.asarray(model.a)] + [np.asarray(b) for b in model.b])


def _rel_err(est, true):
    return np.max(np.abs(_params(est) - _params(true)) / np.abs(_params(true)))


# Acceptance: noise-free data, ~50 samples per shortest time constant, error <= 5e-5.
# The cubic output rule is O(dt^4): measured ~1e-7 here; the piecewise-linear rule (O(dt^2))
# gives ~1e-4, which is why it is not the default.
SYSTEMS = [
    (paper_table3_model1, 2.5, 3000, (0, 0), (3, 4, 200.0)),  # 1/|p| = 126 s -> dt 2.5 s
    (third_order_two_input, 0.01, 2000, (1, 0), (4, 5, 2.0)),  # fastest pole 2 -> tau 0.5 s
]


@pytest.mark.parametrize("make,dt,T,m,mf", SYSTEMS)
def test_noise_free_accuracy(make, dt, T, m, mf):
    true = make()
    sig = simulated_experiment(true, dt=dt, n_samples=T, x0=0.1 * np.ones(true.n))
    model = mfmjax.identify(sig, Structure(true.n, m), ModulatingFunction(*mf))
    assert int(model.status) == 0
    assert _rel_err(model, true) <= 5e-5
    assert float(model.a[-1]) == 1.0
    # eta-normalised raw vector: eta^T theta = 1
    assert abs(float(jnp.sum(model.theta)) - 1.0) <= 1e-12


def test_cubic_rule_far_below_piecewise_linear():
    true = third_order_two_input()
    sig = simulated_experiment(true, dt=0.01, n_samples=2000)
    lin = Signals(sig.y, sig.u, dt=0.01, intersample=("foh", "zoh"), output_rule="foh")
    st, mf = Structure(3, (1, 0)), ModulatingFunction(4, 5, 2.0)
    e_cubic = _rel_err(mfmjax.identify(sig, st, mf), true)
    e_lin = _rel_err(mfmjax.identify(lin, st, mf), true)
    assert e_cubic < 1e-2 * e_lin


def test_fractional_delays_and_m_equal_n():
    true = mfmjax.Model.from_coefficients(
        [2.0, 3.0, 1.0], [[0.5, 0.2, 0.3], [1.0]], intersample=("foh", "zoh"),
        delays=[0.237, 0.0413],
    )
    sig = simulated_experiment(true, dt=0.01, n_samples=2500)
    model = mfmjax.identify(sig, Structure(2, (2, 0)), ModulatingFunction(3, 4, 2.5))
    assert int(model.status) == 0
    # m_1 = n: y carries D u_1(t - tau), kinks the cubic rule cannot see; the feed-through
    # correction of identify removes them (without it: 5e-4 here)
    assert _rel_err(model, true) <= 5e-5


def test_m_equal_n_zoh_input():
    # zoh input with m = n: y jumps at every input switch and the strictly proper rest still
    # has derivative jumps there, an O(dt^2) local error at each of the 40 switches: measured
    # 7.7e-5, bound 2e-4 (without the feed-through correction: 5e-2 on the same data)
    true = mfmjax.Model.from_coefficients(
        [2.0, 3.0, 1.0], [[0.5, 0.2], [1.0, 0.4, 0.1]], intersample=("foh", "zoh")
    )
    sig = simulated_experiment(true, dt=0.01, n_samples=2500)
    model = mfmjax.identify(sig, Structure(2, (1, 2)), ModulatingFunction(3, 4, 2.5))
    assert _rel_err(model, true) <= 2e-4


def test_offset_term():
    true = mfmjax.Model.from_coefficients([0.5, 1.5, 1.0], [[0.7]], offset=0.3)
    sig0 = simulated_experiment(true, dt=0.02, n_samples=2000)
    sig = Signals(sig0.y, sig0.u, dt=0.02, offset=True)
    model = mfmjax.identify(sig, Structure(2, (0,)), ModulatingFunction(3, 4, 4.0))
    assert abs(float(model.offset) - 0.3) <= 5e-5 * 0.3
    assert _rel_err(model, true) <= 5e-5


def _sine_response(t, a, b, parts):
    """Steady-state response of b0 / A(s) to a sum of sines (amplitude, w, phase): exact."""
    u = sum(A * np.sin(w * t + p) for A, w, p in parts)
    y = 0.0
    for A, w, p in parts:
        g = b[0] / np.polyval(a[::-1], 1j * w)
        y = y + A * abs(g) * np.sin(w * t + p + np.angle(g))
    return y, u


def test_a_large_level_with_an_offset_changes_only_the_offset():
    # y + Ly, u + Lu with an offset term: the same a and b, offset + a0 Ly - b0 Lu. The
    # columns of the raw levels were collinear to ~(sigma / L)^2 and the solve returned a and
    # b 1e-4 off at L = 1e4 (1.0 at 1e6), status ok; now the signals are centred inside
    # (an exact reparametrisation). What remains is the data's own rounding: eps L / sigma
    # = 2e-12 relative at L = 1e4 (sigma ~ 1), amplified by the problem's sensitivity; the
    # bound 1e-9 leaves a factor 500 for it and fails the old code by 5 orders.
    a, b = np.array([2.0, 3.0, 1.0]), np.array([2.0])
    t = np.arange(6000) * 0.02
    y, u = _sine_response(t, a, b, [(1.0, 0.7, 0.3), (0.5, 2.3, 1.0), (0.3, 0.13, 2.0)])
    st, mf = Structure(2, (0,)), ModulatingFunction(4, 4, 2.0)
    grid = dict(n=(2,), m=[(0,)], N=(4,), M=(4,), h=(2.0,))
    base = mfmjax.identify(Signals(y, u, dt=0.02, smooth=True, offset=True), st, mf)
    for Ly, Lu in ((1e4, 1e4), (-3e4, 2e3)):
        sig = Signals(y + Ly, u + Lu, dt=0.02, smooth=True, offset=True)
        for m in (mfmjax.identify(sig, st, mf), mfmjax.search(sig, **grid).best()):
            assert int(m.status) == 0
            got = np.concatenate([m.a, m.b[0]])
            ref = np.concatenate([base.a, base.b[0]])
            assert np.max(np.abs(got - ref) / np.abs(ref)) <= 1e-9
            shift = float(base.a[0]) * Ly - float(base.b[0][0]) * Lu
            assert abs(float(m.offset) - float(base.offset) - shift) <= 1e-9 * (abs(Ly)
                                                                               + abs(Lu))


def test_the_default_constraint_makes_noisy_estimates_level_free():
    """eta = ones on the offset too (the old default) made a and b depend on the signals'
    levels on noisy data: 27 % at a level of 1e4 with this noise, status ok, and a search's
    ranking changed at 1e2. The default now leaves the offset out of eq. (11)'s constraint, and
    J_rel is that of the centred columns: neither depends on the level. What remains is the
    data's rounding (eps L / sigma = 2e-12 at 1e4) through the noisy problem's conditioning
    (cond ~1e3): 1e-9 bounds it; the old default fails it by 8 orders."""
    a, b = np.array([2.0, 3.0, 1.0]), np.array([2.0])
    t = np.arange(6000) * 0.02
    y, u = _sine_response(t, a, b, [(1.0, 0.7, 0.3), (0.5, 2.3, 1.0), (0.3, 0.13, 2.0)])
    y = y + 0.01 * np.std(y) * np.random.default_rng(7).standard_normal(t.size)
    st, mf = Structure(2, (0,)), ModulatingFunction(4, 5, 5.0)
    grid = dict(n=(1, 2, 3), N=(3, 4), M=(4, 5), h=(4.0, 6.0))
    results = []
    for L in (0.0, 1e4):
        sig = Signals(y + L, u + L, dt=0.02, smooth=True, offset=True)
        results.append((mfmjax.identify(sig, st, mf), mfmjax.search(sig, **grid)))
    (m0, s0), (m1, s1) = results
    coef = lambda m: np.concatenate([m.a, m.b[0]])  # noqa: E731
    assert np.max(np.abs(coef(m1) - coef(m0)) / np.abs(coef(m0))) <= 1e-9
    assert abs(float(m1.J_rel) - float(m0.J_rel)) <= 1e-9 * float(m0.J_rel)
    assert np.array_equal(s0.rank, s1.rank)
    assert np.max(np.abs(coef(s1.best()) - coef(s0.best())) / np.abs(coef(s0.best()))) <= 1e-9


def test_a_n_test_does_not_depend_on_the_time_unit():
    """A plant with four poles near 1e3 rad/s (0.3-1.4 ms) written in seconds has a_0 = 4e12
    against a_4 = 1: |a_n| <= 1e-12 max |a_i| flagged every n = 4 candidate a_n_zero (and
    `estimate` dropped the true order: hold-out fit 87 % for 92 % in ms; an audit of
    2026-11-28). The test reads the equilibrated parameters now: the same record in s and ms
    is ok in both, with the same poles. Noise-free, so the two solves differ by rounding only
    (their a_i differ by 1e3^(n - i)): poles to 1e-9 relative (measured 1e-12)."""
    p = np.array([3e3, 2e3, 1e3, 700.0])
    a = np.poly(-p)[::-1]
    true = mfmjax.Model.from_coefficients(a, [[a[0]]], intersample=("zoh",))
    u = np.repeat(np.random.default_rng(4).choice([-1.0, 1.0], 100), 30)[:, None]
    y = np.asarray(mfmjax.simulate(true, u, dt=1e-5))
    poles = []
    for c in (1.0, 1e-3):  # seconds, milliseconds
        sig = Signals(y, u, dt=1e-5 / c, intersample="zoh", offset=False)
        model = mfmjax.identify(sig, Structure(4, (0,)), ModulatingFunction(5, 5, 4e-3 / c))
        assert int(model.status) == 0, (c, int(model.status))
        poles.append(np.sort_complex(np.roots(np.asarray(model.a)[::-1]) / c))
    np.testing.assert_allclose(poles[0], poles[1], rtol=1e-9)
    np.testing.assert_allclose(np.sort(poles[0].real), np.sort(-p), rtol=1e-6)


def test_zero_inputs_K0():
    # autonomous decay from a nonzero state: K = 0
    true = mfmjax.Model.from_coefficients([2.0, 0.6, 1.0], [])
    y = np.asarray(mfmjax.simulate(true, np.zeros((2000, 0)), [1.0, 0.5], dt=0.01))
    model = mfmjax.identify(Signals(y, dt=0.01), Structure(2), ModulatingFunction(3, 3, 3.0))
    assert np.max(np.abs(np.asarray(model.a) - np.asarray(true.a))) <= 5e-5 * 2.0


def test_jit_and_vmap_over_h_equal_eager():
    sig = simulated_experiment(third_order_two_input(), dt=0.01, n_samples=1500, noise_std=0.01)
    st = Structure(3, (1, 0))
    hs = jnp.asarray([1.5, 2.0, 2.37])
    eager = [_params(mfmjax.identify(sig, st, ModulatingFunction(4, 5, float(h)))) for h in hs]

    def f(h):
        return mfmjax.identify(sig, st, ModulatingFunction(4, 5, h, h_max=2.5))

    batched = jax.vmap(f)(hs)
    jitted = jax.jit(f)(hs[1])
    for k in range(3):
        got = np.concatenate([np.asarray(batched.a[k])] + [np.asarray(b[k]) for b in batched.b])
        # kernel length differs (h_max) -> different zero padding only: rounding level
        assert np.allclose(got, eager[k], rtol=1e-10, atol=0)
    assert np.allclose(_params(jitted), eager[1], rtol=1e-10, atol=0)


def test_vmap_over_datasets():
    true = third_order_two_input()
    sigs = [simulated_experiment(true, dt=0.01, n_samples=1200, seed=s, noise_std=0.01)
            for s in range(3)]
    st, mf = Structure(3, (1, 0)), ModulatingFunction(4, 5, 2.0)
    ys = jnp.stack([s.y for s in sigs])
    us = jnp.stack([s.u for s in sigs])

    def f(y, u):
        return mfmjax.identify(Signals(y, u, dt=0.01, intersample=("foh", "zoh")), st, mf)

    batched = jax.vmap(f)(ys, us)
    for k, s in enumerate(sigs):
        eager = mfmjax.identify(s, st, mf)
        # batched BLAS sums in another order: rounding (1e-16) times the reduced condition
        # number of the solve (< 1e6 here) bounds the difference
        assert np.allclose(np.asarray(batched.a[k]), np.asarray(eager.a), rtol=1e-9, atol=0)


def test_vmap_over_stacked_signals():
    """Records stacked as `Signals` (one dt, an explicit offset choice) vmap through `identify`
    (delays traced: their bound given) and `observe`: dt is a traced value there, and the host
    decisions (kernel and window lengths) read the number the records were built with
    (`Signals.dt_host`). Equal to one record at a time within the rounding bound of the test
    above (1e-9)."""
    true = third_order_two_input()
    sigs = [simulated_experiment(true, dt=0.01, n_samples=1200, seed=s, noise_std=0.01)
            for s in range(3)]
    sigs = [Signals(s.y, s.u, dt=0.01, intersample=("foh", "zoh"), offset=False) for s in sigs]
    st, mf = Structure(3, (1, 0)), ModulatingFunction(4, 5, 2.0)
    stacked = jax.tree.map(lambda *x: jnp.stack(x), *sigs)

    def f(sig):
        model = mfmjax.identify(sig, st, mf, delay_max=0.0)
        return model.a, mfmjax.observe(model, sig).E

    a, E = jax.vmap(f)(stacked)
    for k, s in enumerate(sigs):
        one = mfmjax.identify(s, st, mf)
        assert np.allclose(np.asarray(a[k]), np.asarray(one.a), rtol=1e-9, atol=0)
        assert float(E[k]) == pytest.approx(float(mfmjax.observe(one, s).E), rel=1e-9)
    # without the bound, the error says why a record's delays are traced (its kernel length
    # read dt as a traced value before, and the traced delays gave TracerArrayConversionError)
    with pytest.raises(ValueError, match=r"scores\(\): delays are traced .* delay_max=0\.0 when"):
        jax.vmap(lambda s: mfmjax.scores(s, st, h=2.0, N=4.0, M=5.0)["E"])(stacked)
    # the functions that run on the host refuse a traced record by name, with what to do
    model = mfmjax.identify(sigs[0], st, mf)
    for fn, call, fix in (
            ("estimate", lambda s: mfmjax.estimate(s, h=2.0), "pass a list"),
            ("search", lambda s: mfmjax.search(s, n=3, N=4, M=5, h=2.0), "once per record"),
            ("refine", lambda s: mfmjax.refine(s, model), "use scores"),
            ("compare", lambda s: mfmjax.compare(model, s), "use observe"),
            ("residuals", lambda s: mfmjax.residuals(model, s), "use observe"),
            ("output_error", lambda s: mfmjax.output_error(s, model), "pass a list")):
        with pytest.raises(TypeError, match=rf"{fn}\(\) runs on the host .*{fix}"):
            jax.vmap(call)(stacked)


def test_no_recompile_second_call():
    sig = simulated_experiment(third_order_two_input(), dt=0.01, n_samples=1200)
    st = Structure(3, (1, 0))
    from mfmjax._identify import identify_core

    mfmjax.identify(sig, st, ModulatingFunction(4, 5, 2.0))
    before = identify_core._cached._cache_size()
    mfmjax.identify(sig, st, ModulatingFunction(4, 5, 1.9, h_max=2.0))
    assert identify_core._cached._cache_size() == before
    # a model's own settings identify again (they carry no static bound: "h is traced ... pass
    # h_max" was raised for this concrete h), in the same program, to the same model
    model = mfmjax.identify(sig, st, ModulatingFunction(4, 5, 2.0))
    again = mfmjax.identify(sig, st, model.mf)
    np.testing.assert_array_equal(np.asarray(again.a), np.asarray(model.a))
    assert identify_core._cached._cache_size() == before


def test_grad_in_h_equals_finite_differences():
    """`identify` is differentiable in h (eager `jax.grad`, and under `jit`): d a_0 / d h
    equals the central difference with step 1e-4. Its truncation error, step^2 f^(3) / 6, was
    measured at 6e-8 relative (it falls as step^2: 3e-9 at 1e-5), and rounding adds about
    |delta f| / step = 1e-14 / 1e-4 = 1e-10: checked to 1e-6 relative. (Before the unstable
    bit moved into the compiled program, the eager grad failed in the host-side flag.)"""
    sig = simulated_experiment(third_order_two_input(), dt=0.01, n_samples=1200,
                               noise_std=0.01, seed=3)
    st = Structure(3, (1, 0))

    def a0(h):
        return mfmjax.identify(sig, st, ModulatingFunction(4, 5, h, h_max=2.5)).a[0]

    h0, step = 2.0037, 1e-4  # h0 +- step inside one sampling cell (dt = 0.01)
    g = float(jax.grad(a0)(h0))
    fd = (float(a0(h0 + step)) - float(a0(h0 - step))) / (2 * step)
    assert g == pytest.approx(fd, rel=1e-6)
    assert float(jax.jit(jax.grad(a0))(h0)) == pytest.approx(g, rel=1e-12)


def test_grad_of_the_offset_in_the_data_counts_the_centring_levels():
    """The centring levels (`signal_levels`) carried no gradient, as if a constant were exact:
    at non-integer N, M it is not quite (the quadrature of phi^(i) does not sum to zero), and
    d offset / dy along ones came out 6.33641e-5 for 6.33633e-5 (an audit of 2026-11-28).
    The offset is affine in a constant added to y, so the central difference has no
    truncation error; its rounding (the offset's own, about 1e-16 of the parameters' scale,
    over the step) stays below 1e-10 relative (measured 5.9e-14)."""
    true = paper_table3_model1()
    clean = simulated_experiment(true, dt=2.5, n_samples=800, x0=[0.0, 0.0], seed=0)
    y = np.asarray(clean.y) + 0.1 * np.std(clean.y) * np.random.default_rng(0).standard_normal(800)
    st, mf = Structure(2, (0, 0)), ModulatingFunction(2.5, 3.3, 201.3)

    def offset(yy):
        sig = Signals(yy, clean.u, dt=2.5, intersample=clean.intersample, offset=True)
        return mfmjax.identify(sig, st, mf).offset

    ones, step = np.ones(800), 1e-3
    g = float(jax.jvp(offset, (jnp.asarray(y),), (jnp.asarray(ones),))[1])
    fd = (float(offset(jnp.asarray(y + step * ones))) - float(offset(jnp.asarray(y - step * ones)))
          ) / (2 * step)
    assert g == pytest.approx(fd, rel=1e-10)


def test_settings_are_read_only_copies():
    """A concrete h is kept as a read-only NumPy copy (no device transfer per setting), and
    the model stores N, M and h the same way: changing the caller's array afterwards changes
    neither the ModulatingFunction nor a model fitted with it (as with the JAX arrays they
    replaced), and an in-place update is refused instead of changing a frozen Module."""
    sig = simulated_experiment(third_order_two_input(), dt=0.01, n_samples=1200)
    h = np.array(2.0)
    mf = ModulatingFunction(4, 5, h)
    model = mfmjax.identify(sig, Structure(3, (1, 0)), mf)
    h[...] = 1.6
    assert float(mf.h) == float(model.mf.h) == 2.0 and mf.h_max == 2.0
    for x in (mf.h, model.mf.N, model.mf.M, model.mf.h):
        assert isinstance(x, np.ndarray) and x.dtype == np.float64 and not x.flags.writeable
    with pytest.raises(ValueError, match="read-only"):
        mf.h *= 2
    assert float(mf.h) == 2.0
    again = mfmjax.identify(sig, Structure(3, (1, 0)), mf)
    np.testing.assert_array_equal(np.asarray(again.theta), np.asarray(model.theta))


@pytest.mark.parametrize(
    "st,mf,kw,match",
    [
        (Structure(3, (1, 0)), ModulatingFunction(2, 5, 2.0), {}, "N must be >= n"),
        (Structure(3, (1, 0)), ModulatingFunction(4, 2, 2.0), {}, "M must be >= n"),
        (Structure(3, (1, 0, 0)), ModulatingFunction(4, 5, 2.0), {}, "m has 3 entries"),
        (Structure(3, (1, 0)), ModulatingFunction(4, 5, 11.9), {}, "too short"),
        (Structure(3, (1, 0)), ModulatingFunction(4, 5, 2.0), {"eta": [1, 2]}, "eta must"),
    ],
)
def test_bad_arguments(st, mf, kw, match):
    sig = simulated_experiment(third_order_two_input(), dt=0.01, n_samples=1200)
    with pytest.raises(ValueError, match=match):
        mfmjax.identify(sig, st, mf, **kw)


def test_bad_structure():
    with pytest.raises(ValueError, match="exceeds n"):
        Structure(2, (3,))
    with pytest.raises(ValueError, match="n must be"):
        Structure(0)


def test_unstable_estimate_is_flagged_eager_jit_and_vmap():
    """A(s) with a right-half-plane root sets Status.UNSTABLE (as srivc, output_error and the
    search's validation do); the NumPy reference is np.roots of the returned a. Data from
    x' = 0.5 x + u (pole at +0.5) and from its mirror x' = -0.5 x + u (stable): noise-free, so
    the estimates are the true a_0 = -0.5 and +0.5 to 1e-6, far from the boundary."""
    dt, T = 0.01, 1201
    t = np.arange(T) * dt
    u = np.sin(0.9 * t) + 0.5 * np.cos(2.3 * t)
    st = Structure(1, [0])
    for a0, flagged in ((-0.5, True), (0.5, False)):
        true = mfmjax.Model.from_coefficients([a0, 1.0], [[1.0]])
        sig = Signals(np.asarray(mfmjax.simulate(true, u, None, dt=dt)), u, dt=dt)
        if flagged:
            with pytest.warns(UserWarning, match="status unstable"):
                eager = mfmjax.identify(sig, st, ModulatingFunction(3, 3, 2.0))
        else:
            eager = mfmjax.identify(sig, st, ModulatingFunction(3, 3, 2.0))
        assert np.allclose(np.asarray(eager.a), [a0, 1.0], atol=1e-6)
        assert (np.roots(np.asarray(eager.a)[::-1]).real >= 0).any() == flagged

        def f(h, sig=sig):
            return mfmjax.identify(sig, st, ModulatingFunction(3, 3, h, h_max=2.5))

        want = int(mfmjax.Status.UNSTABLE) if flagged else 0
        assert int(eager.status) == want
        assert int(jax.jit(f)(2.0).status) == want
        assert np.asarray(jax.vmap(f)(jnp.asarray([1.5, 2.0])).status).tolist() == [want] * 2


def _logged_twice():
    """(t, u, y, signals) of a second-order plant driven by u, the signals holding u twice
    (u2 = 2 u1), output noise 0.01."""
    true = mfmjax.Model.from_coefficients([1.0, 0.8, 1.0], [[2.0]], intersample=["zoh"])
    t = 0.1 * np.arange(1000)
    u = np.sign(np.sin(0.3 * t)) + 0.5 * np.sign(np.sin(0.11 * t))
    y = np.asarray(mfmjax.simulate(true, u[:, None], dt=0.1))
    y = y + 0.01 * np.random.default_rng(1).standard_normal(y.shape)
    return t, u, y, Signals(y, np.c_[u, 2 * u], dt=0.1, intersample="zoh", offset=False)


def test_linearly_dependent_inputs_are_flagged_and_named():
    """One signal logged twice in other units (u2 = 2 u1): no method can split the gain, and
    under output noise the Gram's conditioning test missed it (noise fills the eigenvalue it
    reads), so `identify` returned b = 7e10 / -4e10 with status ok. The inputs themselves are
    checked now: status ILL_CONDITIONED and a warning naming them. Inputs that differ (other
    rule, other delay, or independent) are not flagged: `dependent_inputs` is empty."""
    from mfmjax._signals import dependent_inputs
    from mfmjax._status import Status

    t, u, y, sig = _logged_twice()
    assert dependent_inputs(sig) == ("u1", "u2")
    with pytest.warns(UserWarning) as caught:
        model = mfmjax.identify(sig, Structure(2, [0, 0]), ModulatingFunction(4, 4, 5.0))
    texts = [str(w.message) for w in caught]
    assert any("inputs ['u1', 'u2'] are linearly dependent" in t for t in texts), texts
    assert any("status ill_conditioned" in t for t in texts), texts  # the status warning
    assert int(model.status) & Status.ILL_CONDITIONED
    other = np.sign(np.sin(0.17 * t + 1.0))
    for u2, rules, delays in ((2 * u, ("zoh", "foh"), None), (2 * u, "zoh", [0.0, 0.3]),
                              (other, "zoh", None)):
        assert dependent_inputs(Signals(y, np.c_[u, u2], dt=0.1, intersample=rules,
                                        delays=delays, offset=False)) == ()
    # u2 = 2 u1 + 3: dependent on the constant input the offset term adds, not without it
    shifted = np.c_[u, 2 * u + 3.0]
    assert dependent_inputs(Signals(y, shifted, dt=0.1, intersample="zoh", offset=True)) \
        == ("u1", "u2")
    assert dependent_inputs(Signals(y, shifted, dt=0.1, intersample="zoh", offset=False)) == ()


def test_search_flags_candidates_whose_inputs_are_linearly_dependent():
    """`search` checks the inputs under each candidate's delays as `identify` does: with u2 =
    2 u1 the candidates at equal delays are flagged ILL_CONDITIONED (they ranked first with
    status ok), the warning names the inputs and counts them, and a candidate whose delay
    separates the inputs (u2 one second later) is not flagged and ranks first."""
    from mfmjax._status import Status

    sig = _logged_twice()[3]
    with pytest.warns(UserWarning, match=r"inputs \['u1', 'u2'\] are linearly dependent .* "
                      r"under the delays of 1 of 2 candidates"):
        res = mfmjax.search(sig, h=5.0, n=2, N=4, M=4, m=[[0], [0]],
                            delays=[[0.0], [0.0, 1.0]])
    c = res.columns
    flagged = (c["status"] & Status.ILL_CONDITIONED) != 0
    assert flagged.tolist() == [bool(d[1] == 0.0) for d in c["delays"]]
    assert res.row(0)["delays"] == [0.0, 1.0]
