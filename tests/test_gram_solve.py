import warnings

import jax.numpy as jnp
import numpy as np
import pytest
import reference as R

import mfmjax
from mfmjax import ModulatingFunction, Signals, Structure
from mfmjax._gram import gram, modulated_signals
from mfmjax.datasets import simulated_experiment, third_order_two_input


def _small_record(noise=0.0, delays=(0.0, 0.0)):
    true = mfmjax.Model.from_coefficients(
        [1.0, 3.5, 3.5, 1.0], [[1.0, 0.5], [0.8]], intersample=("foh", "zoh"), delays=delays
    )
    return simulated_experiment(true, dt=0.1, n_samples=150, noise_std=noise, seed=3)


def test_gram_equals_reference():
    # delays and h not multiples of dt; the reference kernels are exact rationals, so G may
    # differ only by float64 rounding in the convolution and the sums: 1e-12 relative
    sig = _small_record(delays=(0.33, 0.05))
    st, mf = Structure(3, (1, 0)), ModulatingFunction(3, 4, 2.17)
    G = np.asarray(gram(modulated_signals(sig, st, mf)))
    Gr = R.gram(np.asarray(sig.y), np.asarray(sig.u), 0.1, 3, (1, 0), 3, 4, 2.17,
                ("foh", "zoh"), (0.33, 0.05))
    assert np.max(np.abs(G - Gr)) <= 1e-12 * np.max(np.abs(Gr))


def test_closed_form_agrees_with_kkt_when_well_conditioned():
    # noisy data make G well conditioned; both solve the same problem, so they agree to the
    # rounding amplified by cond(G_eq) < 1e6: 1e-8 relative
    sig = _small_record(noise=0.05)
    st, mf = Structure(3, (1, 0)), ModulatingFunction(4, 5, 2.0)
    G = gram(modulated_signals(sig, st, mf))
    eta = jnp.ones(G.shape[0])
    theta, cond, _ = mfmjax.constrained_solve(G, eta, jnp.ones(G.shape[0], bool))
    assert float(cond) < 1e6
    ref = R.closed_form(np.asarray(G), np.ones(G.shape[0]))
    assert np.max(np.abs(np.asarray(theta) - ref)) <= 1e-8 * np.max(np.abs(ref))
    jax_ref = np.asarray(mfmjax.closed_form(G, eta))
    assert np.max(np.abs(jax_ref - ref)) <= 1e-8 * np.max(np.abs(ref))
    # a non-default eta too
    eta2 = jnp.linspace(0.5, 2.0, G.shape[0])
    theta2, _, _ = mfmjax.constrained_solve(G, eta2, jnp.ones(G.shape[0], bool))
    ref2 = R.closed_form(np.asarray(G), np.asarray(eta2))
    assert np.max(np.abs(np.asarray(theta2) - ref2)) <= 1e-8 * np.max(np.abs(ref2))


def test_kkt_defined_for_exactly_singular_gram():
    # rank-deficient G with null vector v: the closed form divides by ~0, the KKT solve returns
    # v scaled to eta^T theta = 1 exactly
    rng = np.random.default_rng(0)
    X = rng.normal(size=(50, 4))
    v = np.array([1.0, -2.0, 0.5, 3.0])
    X -= np.outer(X @ v, v) / (v @ v)
    G = jnp.asarray(X.T @ X)
    theta, cond, reduced = mfmjax.constrained_solve(G, jnp.ones(4), jnp.ones(4, bool))
    assert np.allclose(np.asarray(theta), v / v.sum(), rtol=1e-10, atol=0)
    assert float(cond) > 1e14 and float(reduced) < 1e3


def test_masked_column_gets_zero():
    rng = np.random.default_rng(1)
    X = rng.normal(size=(30, 3))
    G = jnp.asarray(X.T @ X)
    active = jnp.asarray([True, False, True])
    theta, _, _ = mfmjax.constrained_solve(G, jnp.ones(3), active)
    sub = R.closed_form(np.asarray(G)[np.ix_([0, 2], [0, 2])], np.ones(2))
    assert float(theta[1]) == 0.0
    assert np.allclose(np.asarray(theta)[[0, 2]], sub, rtol=1e-12)


def test_constant_input_flagged_not_nan():
    sig0 = simulated_experiment(third_order_two_input(), dt=0.01, n_samples=1500)
    for level in (0.0, 2.5):
        u = np.asarray(sig0.u).copy()
        u[:, 1] = level
        sig = Signals(sig0.y, u, dt=0.01, intersample=("foh", "zoh"))
        with warnings.catch_warnings(record=True) as rec:
            warnings.simplefilter("always")
            model = mfmjax.identify(sig, Structure(3, (1, 1)), ModulatingFunction(4, 5, 2.0))
        assert int(model.status) & mfmjax.Status.NO_EXCITATION
        assert np.all(np.isfinite(np.asarray(model.theta)))
        assert any("no_excitation" in str(w.message) for w in rec)


def test_a_steady_input_is_masked_and_its_level_goes_to_the_offset():
    """An input held constant: its lag-0 column is its level times the offset column. With an
    offset term the two entered a null direction of G and came back split at random (here
    b_20 = 0.41 with offset 1.24 from `identify`, -0.033 and 3.90 from `search`; on the DaISy
    heating system with a constant input, +-1e12): now `identify` and `search` mask the
    input (b_2 = 0, status no_excitation) and the offset takes its steady contribution,
    0.7 + 0.5 x 6 = 3.7. Without an offset term b_20 carries it and stays: 0.5 (a first
    version of the mask took it too and returned a wrong model, a_1 = 6.5). Noise-free data:
    the MFM estimate to its quadrature error, 1e-6 relative; the search's candidate equals
    `identify`'s (the same solve, 1e-9). With `identify=` windows the search judges the input
    on them, as `identify` on the window's record: u_2 moves only outside the window."""
    dt, T = 0.02, 1500
    t = np.arange(T) * dt
    u = np.stack([np.sin(0.9 * t) + 0.4 * np.cos(2.9 * t), np.full(T, 6.0)], 1)
    st, mf = Structure(2, (0, 0)), ModulatingFunction(3, 4, 1.5)
    for offset, truth in ((0.7, [2.0, 3.0, 1.0, 0.0, 3.7]), (None, [2.0, 3.0, 1.0, 0.5, 0.0])):
        true = mfmjax.Model.from_coefficients([2.0, 3.0, 1.0], [[1.0], [0.5]], offset=offset)
        sig = Signals(np.asarray(mfmjax.simulate(true, u, None, dt=dt)), u, dt=dt,
                      offset=offset is not None)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            model = mfmjax.identify(sig, st, mf)
        assert int(model.status) & mfmjax.Status.NO_EXCITATION
        got = [*np.asarray(model.a)[:2], float(model.b[0][0]), float(model.b[1][0]),
               float(model.offset)]
        np.testing.assert_allclose(got, truth, rtol=1e-6, atol=1e-6)
        best = mfmjax.search(sig, n=(2,), m=[(0,), (0,)], N=(3,), M=(4,), h=(1.5,)).best(0)
        np.testing.assert_allclose(np.asarray(best.theta), np.asarray(model.theta), rtol=1e-9,
                                   atol=1e-12)
    # u_2 steps outside an identification window [0, 20]: the search on that window masks it
    # as `identify` on the window's own record does (both with the offset term)
    u2 = u.copy()
    u2[1200:, 1] = 7.0
    true = mfmjax.Model.from_coefficients([2.0, 3.0, 1.0], [[1.0], [0.5]], offset=0.7)
    sig = Signals(np.asarray(mfmjax.simulate(true, u2, None, dt=dt)), u2, dt=dt, offset=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = mfmjax.identify(sig.window(0.0, 20.0), st, mf)
    best = mfmjax.search(sig, n=(2,), m=[(0,), (0,)], N=(3,), M=(4,), h=(1.5,),
                         identify=[(0.0, 20.0)]).best(0)
    assert float(model.b[1][0]) == float(best.b[1][0]) == 0.0
    np.testing.assert_allclose(np.asarray(best.theta), np.asarray(model.theta), rtol=1e-9,
                               atol=1e-12)


def test_a_delayed_input_is_judged_on_the_samples_its_columns_read():
    """u_1 (delay 100 s) steps 50 s before the record's end: its delayed copy, all the
    columns read, never moves, so it is no excitation and its column the offset's. The test
    ran on the window's samples, saw the step and passed: identify returned b_10 = 0.61 for
    0.01 (status ill_conditioned only), and on the forehearth's identifier windows (delay
    265 s) the constant delayed input and the offset came out at 2e9 and -2.6e12, status ok,
    predicting 1e14 off. Now identify and search flag NO_EXCITATION and mask the column as for
    a steady input (the level goes to the offset; noise-free: the MFM estimate's quadrature
    error, 1e-6). The same input stepping 200 s earlier (its delayed step inside the window)
    is excitation, as before."""
    dt, T, d = 1.0, 1200, 100.0
    t = np.arange(T) * dt
    u2 = np.sin(0.05 * t) + 0.3 * np.sign(np.sin(0.013 * t))
    true = mfmjax.Model.from_coefficients([0.01, 0.3, 1.0], [[0.01], [0.02]], delays=[d, 0.0],
                                          offset=0.05)
    st, mf = Structure(2, (0, 0)), ModulatingFunction(3, 3, 40.0)
    for step, excited in ((1150, False), (950, True)):
        u = np.stack([np.where(t < step, 1.0, 2.0), u2], 1)
        sig = Signals(np.asarray(mfmjax.simulate(true, u, None, dt=dt)), u, dt=dt,
                      delays=[d, 0.0], offset=True)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            model = mfmjax.identify(sig, st, mf)
            res = mfmjax.search(sig, n=(2,), m=[(0,), (0,)], N=(3,), M=(3,), h=(40.0,),
                                delays=[[d], [0.0]])
        best = res.best(0)
        flag = int(mfmjax.Status.NO_EXCITATION)
        assert bool(int(model.status) & flag) == bool(int(best.status) & flag) == (not excited)
        got = [*np.asarray(model.a)[:2], float(model.b[0][0]), float(model.b[1][0]),
               float(model.offset)]
        # masked: the level 1.0 x 0.01 of u_1 joins the offset (0.05 + 0.01)
        want = [0.01, 0.3, 0.01, 0.02, 0.05] if excited else [0.01, 0.3, 0.0, 0.02, 0.06]
        np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(np.asarray(best.theta), np.asarray(model.theta), rtol=1e-9,
                                   atol=1e-12)
    # the newest sample read, by rule (a review of the change): zoh holds the sample before
    # t - tau (lag d + 1, d = 100 here): a step at sample T - 1 - d is never read, flagged (it
    # was counted: b_10 = 7.2, ill_conditioned only); the cubic rule reads one node beyond
    # the cell (lag d - 1): a step at T - d is read, not flagged
    for rule, smooth, step, excited in (("zoh", False, T - 1 - 100, False),
                                        ("foh", True, T - 100, True)):
        u = np.stack([np.where(t < step, 1.0, 2.0), u2], 1)
        sig = Signals(np.asarray(mfmjax.simulate(true, u, None, dt=dt)), u, dt=dt,
                      delays=[d, 0.0], offset=True, intersample=[rule, "foh"],
                      smooth=[smooth, False])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            model = mfmjax.identify(sig, st, mf)
            best = mfmjax.search(sig, n=(2,), m=[(0,), (0,)], N=(3,), M=(3,), h=(40.0,),
                                 delays=[[d], [0.0]]).best(0)
        flag = int(mfmjax.Status.NO_EXCITATION)
        assert bool(int(model.status) & flag) == bool(int(best.status) & flag) == (not excited)


def test_search_on_a_window_scores_j_rel_as_identify_on_the_window():
    """With an offset term the search centred the signals on the whole record's means, the
    validation data included, and `identify` on the window's record on the window's: the same
    model's J_rel differed (0.16479 against 0.16443 on the DaISy heating system, a CLI audit).
    Both now centre on the identification window's means."""
    dt, T = 0.02, 1500
    t = np.arange(T) * dt
    u = (np.sin(0.9 * t) + 0.4 * np.cos(2.9 * t) + 0.3 * (t > 22.0))[:, None]
    true = mfmjax.Model.from_coefficients([2.0, 3.0, 1.0], [[1.0]], offset=0.7)
    y = np.asarray(mfmjax.simulate(true, u, None, dt=dt))
    y = y + 0.01 * np.random.default_rng(3).standard_normal(T) + 40.0 * (t > 25.0)
    sig = Signals(y, u, dt=dt, offset=True)
    model = mfmjax.identify(sig.window(0.0, 20.0), Structure(2, (0,)),
                            ModulatingFunction(3, 4, 1.5))
    res = mfmjax.search(sig, n=(2,), m=[(0,)], N=(3,), M=(4,), h=(1.5,), identify=[(0.0, 20.0)],
                        validate=(20.5, 29.9))
    row = res.row(0)
    np.testing.assert_allclose(np.asarray(res.best(0).theta), np.asarray(model.theta),
                               rtol=1e-9)
    assert row["J"] == pytest.approx(float(model.J_rel), rel=1e-9)


def test_building_blocks_refuse_what_identify_refuses():
    """`modulated_signals` took a structure of another input count (columns of the second
    input dropped, fits=True), N, M < n (the true theta then left a residual of 47 %), an h
    beyond the record or end=0 (G all zeros) and a float end; `constrained_solve` and
    `closed_form` returned NaN for a zero eta or G, and cond = 1 for a negative-definite G.
    Concrete arguments are now refused by name."""
    import pytest

    sig = _small_record()  # 2 inputs, 15 s
    mf = ModulatingFunction(3, 4, 2.0)
    refuse = [
        (lambda: modulated_signals(sig, Structure(3, (1, 0, 0)), mf),
         r"modulated_signals\(\): the data have K=2 inputs but m has 3 entries"),
        (lambda: modulated_signals(sig, Structure(3, (1, 0)), ModulatingFunction(1, 1, 2.0)),
         r"modulated_signals\(\): N must be >= n"),
        (lambda: modulated_signals(sig, Structure(3, (1, 0)), ModulatingFunction(3, 4, 25.0)),
         r"modulated_signals\(\): the record .* is too short for h=25"),
        (lambda: modulated_signals(sig, Structure(3, (1, 0)), mf, end=0), r"end must be"),
        (lambda: modulated_signals(sig, Structure(3, (1, 0)), mf, end=100.5), r"end must be"),
        (lambda: modulated_signals(np.ones(5), Structure(3, (1, 0)), mf),
         r"modulated_signals\(\): signals must be a Signals"),
    ]
    for call, says in refuse:
        with pytest.raises((ValueError, TypeError), match=says):
            call()
    G = np.asarray(gram(modulated_signals(sig, Structure(3, (1, 0)), mf)))
    p, on = G.shape[0], np.ones(G.shape[0], bool)
    for args, says in (((G, np.zeros(p), on), r"eta is zero on every active column"),
                       ((np.zeros((p, p)), np.ones(p), on), r"no finite solution: G is zero"),
                       ((-G, np.ones(p), on), r"G must be a Gram matrix"),
                       ((G + np.triu(np.ones((p, p)), 1) * np.max(G), np.ones(p), on),
                        r"G must be a Gram matrix"),
                       ((np.full((p, p), np.nan), np.ones(p), on), r"G and eta must be finite"),
                       ((np.zeros((0, 0)), np.zeros(0), np.zeros(0, bool)), r"G is empty")):
        with pytest.raises(ValueError, match=r"constrained_solve\(\): " + says):
            mfmjax.constrained_solve(*args)
    with pytest.raises(ValueError, match=r"closed_form\(\): no finite solution: G is singular"):
        mfmjax.closed_form(np.ones((3, 3)), np.ones(3))
    theta, _, _ = mfmjax.constrained_solve(G, np.ones(p), on)  # the Gram itself: a solution
    assert np.all(np.isfinite(np.asarray(theta)))
