"""Gradients of the scores (finite differences), refine, output-error estimation, Cramer-Rao bound,
delay estimation.

Finite differences are central, float64. The scores are evaluated at settings where tau + h is
not on the sample grid (the cubic rule's stencil switches there, a documented O(dt^4) kink); the
step (1e-6 relative) is far from the next switch. Error bound: truncation O(delta^2) ~ 1e-12
relative plus rounding ~ (noise of one evaluation ~ cond * eps ~ 1e-12) / 1e-6 ~ 1e-6 relative,
hence rtol = 1e-5 below.
"""

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import reference as R
from jaxlog import compiles

import mfmjax
from mfmjax import Model, ModulatingFunction, Signals, Structure
from mfmjax.datasets import paper_table3_model1, simulated_experiment

ST = Structure(2, (0, 0))
FD_RTOL = 1e-5


@pytest.fixture(scope="module")
def noisy():
    true = paper_table3_model1()
    clean = simulated_experiment(true, dt=2.5, n_samples=1600, x0=[0.0, 0.0], seed=0)
    sd = float(np.std(clean.y)) / 10 ** (20 / 20)  # SNR 20 dB
    y = np.asarray(clean.y) + sd * np.random.default_rng(0).standard_normal(1600)
    return true, Signals(y, clean.u, dt=2.5, intersample=clean.intersample), sd


def _packed(sig):
    """[J_rel, E, fit, J] as a function of v = [h, N, M, tau_1, tau_2, eta_1..eta_5]."""

    def f(v):
        out = mfmjax.scores(sig, ST, h=v[0], N=v[1], M=v[2], delays=v[3:5], eta=v[5:],
                            h_max=300.0, delay_max=30.0, validate=(500.0, 3997.5),
                            observer_window=1500.0)
        return jnp.stack([out["J_rel"], out["E"], out["fit"], out["J"]])

    return f


V0 = np.array([201.3, 3.0, 4.0, 10.7, 5.3, 1.0, 1.0, 1.0, 1.0, 1.0])


def _central(f, v, i, rel=1e-6):
    d = rel * max(abs(v[i]), 1.0)
    vp, vm = v.copy(), v.copy()
    vp[i] += d
    vm[i] -= d
    return (np.asarray(f(vp)) - np.asarray(f(vm))) / (2 * d)


def test_scores_jacfwd_equals_finite_differences(noisy):
    _, sig, _ = noisy
    f = jax.jit(_packed(sig))
    J = np.asarray(jax.jacfwd(f)(jnp.asarray(V0)))  # (4 scores, 10 settings)
    for i in range(V0.size):
        fd = _central(f, V0, i)
        scale = np.abs(J).max(axis=1) + 1e-300  # each score's largest derivative
        np.testing.assert_allclose(J[:, i] / scale, fd / scale, atol=FD_RTOL, err_msg=f"v[{i}]")
    assert np.all(np.abs(J[1, :5]) > 0)  # E really depends on h, N, M and both delays


def test_scores_grad_reverse_mode_and_data(noisy):
    _, sig, _ = noisy

    def E_of(v, y):
        s = Signals(y, sig.u, dt=sig.dt, intersample=sig.intersample)
        return _packed(s)(v)[1]

    y0 = jnp.asarray(sig.y)
    g_v, g_y = jax.jit(jax.grad(E_of, argnums=(0, 1)))(jnp.asarray(V0), y0)
    fwd = jax.jacfwd(lambda v: E_of(v, y0))(jnp.asarray(V0))
    np.testing.assert_allclose(np.asarray(g_v), np.asarray(fwd), rtol=1e-9, atol=1e-12)
    # the data: directional derivative along a random direction against central differences
    direction = np.random.default_rng(3).standard_normal(y0.shape[0])
    d = 1e-6 * float(jnp.std(y0))
    E = jax.jit(lambda y: E_of(jnp.asarray(V0), y))
    fd = (float(E(y0 + d * direction)) - float(E(y0 - d * direction))) / (2 * d)
    assert float(jnp.dot(g_y, direction)) == pytest.approx(fd, rel=FD_RTOL)


def test_refine_improves_and_respects_bounds(noisy):
    _, sig, _ = noisy
    start = mfmjax.identify(sig, ST, ModulatingFunction(3, 4, 200.0))
    bounds = {"h": (150.0, 230.0), "N": (2.0, 5.0), "M": (2.0, 6.0)}
    r = mfmjax.refine(sig, start, vary=("h", "N", "M"), bounds=bounds, max_steps=15)
    assert r.result in ("successful", "max_steps_reached")
    assert r.path[-1] <= r.path[0] and r.improved
    for key, (lo, hi) in bounds.items():
        assert lo <= r.settings[key] <= hi
    E_ref = mfmjax.performance_index(r.model, sig)
    E_start = mfmjax.performance_index(start, sig)
    assert float(E_ref) < float(E_start)


def test_refine_failure_returns_start(noisy):
    _, sig, _ = noisy
    start = mfmjax.identify(sig, ST, ModulatingFunction(3, 4, 200.0))
    r = mfmjax.refine(sig, start, vary=("h",), max_steps=0)
    assert r.model is start and r.result == "max_steps_reached" and not r.improved
    with pytest.raises(ValueError, match="must lie in its bounds"):
        mfmjax.refine(sig, start, vary=("h",), bounds={"h": (10.0, 100.0)})
    with pytest.raises(ValueError, match="vary must name"):
        mfmjax.refine(sig, start, vary=("q",))
    # a box that lets N below n: refused before any step (it ran to N = 1.86, and the final
    # identify then blamed N); the start itself lies inside it
    with pytest.raises(ValueError, match=r"bounds\['N'\] must start at n=2 .* \(got 0.5\)"):
        mfmjax.refine(sig, start, vary=("h", "N"), bounds={"N": (0.5, 12)})


def test_refine_from_a_flagged_start_says_there_is_nothing_to_refine(noisy):
    """A start flagged no_excitation (an input constant over the record) scores inf, as every
    point tried: refine said "not converged (max_steps_reached after 3 steps)", as if more
    steps would help (an audit of 2026-11-28)."""
    _, sig, _ = noisy
    u = np.asarray(sig.u).copy()
    u[:, 1] = 0.5
    flat = Signals(np.asarray(sig.y), u, dt=2.5, intersample=sig.intersample, offset=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        start = mfmjax.identify(flat, ST, ModulatingFunction(3, 4, 200.0))
    assert int(start.status) & mfmjax.Status.NO_EXCITATION
    with pytest.warns(UserWarning, match=r"refine\(\): the start scores E = inf on these "
                                         r"signals \(status .*no_excitation.*nothing to refine; "
                                         r"returning the start") as got:
        r = mfmjax.refine(flat, start, vary=("h",), max_steps=3)
    assert r.model is start and not r.improved
    assert not any("not converged" in str(w.message) for w in got)


def test_refine_leaves_a_bound_it_starts_on_and_scores_the_model_it_returns(noisy):
    """A start on its box's edge (h = 200 in (200, 400) here; a delay of 0 or N = n, the
    defaults' lower bounds, are the common case): the sigmoid's slope there, the start clipped
    to 1e-6 of the range, shrank the gradient 1e-6 times, BFGS stopped "successful" at h =
    200.0, and `value` was the clipped point's score (385.095 against the returned model's
    385.229). The start now begins `EDGE` (2 %) inside the box: h moves on (past 201 in 10
    steps), and `value` is the score of the model returned (1e-9: the same E, two programs)."""
    _, sig, _ = noisy
    start = mfmjax.identify(sig, ST, ModulatingFunction(3, 4, 200.0))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # (max_steps_reached: the path is slow past h's kinks)
        r = mfmjax.refine(sig, start, vary=("h",), bounds={"h": (200.0, 400.0)}, max_steps=10)
    assert r.settings["h"] > 201.0 and r.improved, (r.settings, r.result)
    assert r.value == pytest.approx(float(mfmjax.performance_index(r.model, sig)), rel=1e-9)
    assert r.value < float(mfmjax.performance_index(start, sig))
    # a refinement that fails returns the start with the start's own score
    r = mfmjax.refine(sig, start, vary=("h",), max_steps=0)
    assert r.model is start
    assert r.value == pytest.approx(float(mfmjax.performance_index(start, sig)), rel=1e-9)


def test_refine_returns_the_model_its_score_belongs_to(noisy):
    """A start identified on other data (another realisation here) and a refinement that
    fails: `refine` returned that start beside the score of the model its settings give on
    these signals (0.00997 against its own 3.73 in the audit's case). It now returns the
    model it scored, says so, and keeps the start in `Refinement.start`. A start of another
    layout is refused as `output_error` and `srivc` refuse it (it ran, and returned a start
    without an offset beside a score with one: 2.7e-11 against 98.3)."""
    true, sig, sd = noisy
    other = simulated_experiment(true, dt=float(sig.dt), n_samples=sig.n_samples, seed=99,
                                 noise_std=10 * sd)
    start = mfmjax.identify(other, ST, ModulatingFunction(3, 4, 200.0))
    with pytest.warns(UserWarning, match=r"returning the start's settings identified on these "
                                         r"signals \(the start differs"):
        r = mfmjax.refine(sig, start, vary=("h",), max_steps=0)
    assert r.model is not start and r.start is start
    assert r.value == pytest.approx(float(mfmjax.performance_index(r.model, sig)), rel=1e-9)
    with pytest.raises(ValueError, match=r"refine\(\): model.has_offset=False but "
                                         r"signals.offset=True"):
        mfmjax.refine(Signals(sig.y, sig.u, dt=sig.dt, intersample=sig.intersample,
                              offset=True), start, vary=("h",))
    one = Signals(sig.y, np.asarray(sig.u)[:, :1], dt=sig.dt)
    with pytest.raises(ValueError, match=r"refine\(\): the model has 2 inputs but the "
                                         r"signals have 1"):
        mfmjax.refine(one, start, vary=("h",))


def test_output_error_removes_bias_and_reports_errors(noisy):
    true, sig, sd = noisy
    start = mfmjax.identify(sig, ST, ModulatingFunction(3, 4, 200.0))
    oe = mfmjax.output_error(sig, start)
    assert oe.result == "successful" and oe.E <= oe.E_start
    assert oe.names == ("a_0", "a_1", "b_10", "b_20")
    truth = np.array([true.a[0], true.a[1], true.b[0][0], true.b[1][0]])
    err = np.abs(oe.theta - truth)
    assert np.all(err < 4 * oe.std_errors)  # within 4 standard errors
    assert oe.sigma2 == pytest.approx(sd**2, rel=0.15)  # residual variance = the noise
    names, crb = mfmjax.cramer_rao(oe.model, sig.u, oe.x0, dt=sig.dt, sigma=sd)
    np.testing.assert_allclose(oe.std_errors, crb * np.sqrt(oe.sigma2) / sd, rtol=1e-6)


def test_output_error_noise_free_keeps_the_truth():
    true = paper_table3_model1()
    sig = simulated_experiment(true, dt=2.5, n_samples=1600, x0=[0.0, 0.0], seed=0)
    start = mfmjax.identify(sig, ST, ModulatingFunction(3, 4, 200.0))
    oe = mfmjax.output_error(sig, start)
    truth = np.array([true.a[0], true.a[1], true.b[0][0], true.b[1][0]])
    np.testing.assert_allclose(oe.theta, truth, rtol=1e-6)


def test_cramer_rao_against_numpy_finite_differences():
    a, b = [0.5, 1.5, 1.0], [[0.5], [0.3]]
    model = mfmjax.Model.from_coefficients(a, b, intersample=("foh", "zoh"))
    dt, T = 0.1, 400
    t = np.arange(T) * dt
    u = np.stack([np.sin(0.7 * t), np.repeat(np.random.default_rng(0).normal(size=T // 20), 20)],
                 1)
    x0 = np.array([0.2, -0.1])
    _, crb = mfmjax.cramer_rao(model, u, x0, dt=dt, sigma=0.05)
    # reference: scipy lsim, central differences over (a_0, a_1, b_10, b_20, x0)
    base = np.array([0.5, 1.5, 0.5, 0.3, *x0])

    def sim(v):
        return R.lsim([v[0], v[1], 1.0], [[v[2]], [v[3]]], u, dt, ("foh", "zoh"), v[4:])

    J = np.stack([(sim(base + e) - sim(base - e)) / 2e-6 for e in np.eye(6) * 1e-6], 1)
    ref = np.sqrt(np.diag(0.05**2 * np.linalg.inv(J.T @ J)))[:4]
    np.testing.assert_allclose(crb, ref, rtol=1e-5)  # FD truncation ~1e-12, lsim ~1e-9
    # the experiment scaled by c (u, x0 and sigma) has the same bounds: sigma^2 and J's column
    # norms underflowed at c = 1e-155 and every bound came back inf (an audit of 2026-11-28).
    # Equal up to the rounding of the scaled data and an SVD of the same matrix: 1e-9
    for c in (1e-155, 1e100):
        np.testing.assert_allclose(mfmjax.cramer_rao(model, u * c, x0 * c, dt=dt,
                                                     sigma=0.05 * c)[1], crb, rtol=1e-9)
    # a sigma so small that J / sigma overflows: said (numpy's "SVD did not converge" came)
    with pytest.raises(ValueError, match=r"cramer_rao\(\): sigma=1e-307 is too small for these "
                                         r"sensitivities"):
        mfmjax.cramer_rao(model, u * 1e3, x0, dt=dt, sigma=1e-307)
    # another experiment length in the record bucket (448 samples) is a value: 390 samples, or
    # `length=390` of the 400, compile nothing and equal the first 390 rows' bound
    ref = np.sqrt(np.diag(0.05**2 * np.linalg.inv(J[:390].T @ J[:390])))[:4]
    with compiles() as names:
        shorter = [mfmjax.cramer_rao(model, u[:390], x0, dt=dt, sigma=0.05)[1],
                   mfmjax.cramer_rao(model, u, x0, dt=dt, sigma=0.05, length=390)[1]]
    assert names == [], f"a new experiment length compiled {names}"
    for crb in shorter:
        np.testing.assert_allclose(crb, ref, rtol=1e-5)


def test_cramer_rao_undetermined_parameters_are_infinite_and_shapes_checked():
    """An experiment that cannot determine a parameter gives it an infinite bound (the
    pseudo-inverse used to give 0, read as "perfectly determined"): with u = 0 the numerator
    coefficients have zero sensitivity; the free response from x0 != 0 still fixes a_0, a_1,
    whose bounds stay finite and equal those of the Fisher matrix restricted to (a, x0) (from
    central differences of scipy's lsim, 1e-5 relative as above). A u or x0 of the wrong
    shape is refused by name (JAX clamped the missing column and used u for both inputs)."""
    model = mfmjax.Model.from_coefficients([0.5, 1.5, 1.0], [[0.5, 0.2]], intersample=("zoh",))
    x0 = np.array([0.2, -0.1])
    names, crb = mfmjax.cramer_rao(model, np.zeros((400, 1)), x0, dt=0.1, sigma=0.05)
    assert names == ("a_0", "a_1", "b_10", "b_11")
    assert np.all(np.isinf(crb[2:])) and np.all(np.isfinite(crb[:2]))

    def sim(v):
        return R.lsim([v[0], v[1], 1.0], [[0.5, 0.2]], np.zeros((400, 1)), 0.1, ("zoh",), v[2:])

    base = np.array([0.5, 1.5, *x0])
    J = np.stack([(sim(base + e) - sim(base - e)) / 2e-6 for e in np.eye(4) * 1e-6], 1)
    ref = np.sqrt(np.diag(0.05**2 * np.linalg.inv(J.T @ J)))[:2]
    np.testing.assert_allclose(crb[:2], ref, rtol=1e-5)  # FD truncation as above
    two = mfmjax.Model.from_coefficients([0.5, 1.5, 1.0], [[0.5], [0.3]])
    with pytest.raises(ValueError, match=r"u must have shape \(T, 2\)"):
        mfmjax.cramer_rao(two, np.ones(400), x0, dt=0.1, sigma=0.05)
    with pytest.raises(ValueError, match=r"x0 must have shape \(2,\)"):
        mfmjax.cramer_rao(model, np.ones((400, 1)), [0.2, -0.1, 0.0], dt=0.1, sigma=0.05)
    # fewer samples than unknowns (6 here: a_0, a_1, b_10, b_11, x0): the thin SVD left out
    # the null space, so 2-5 samples gave finite bounds ([6.8e4, 848, ...] at 2); with the
    # input switching (after 60 samples here) they are finite and fall with the length
    u = np.repeat(np.random.default_rng(0).choice([-1.0, 1.0], 21), 20)[:400, None]
    for length in (2, 5):
        assert np.all(np.isinf(mfmjax.cramer_rao(model, u, x0, dt=0.1, sigma=0.05,
                                                 length=length)[1]))
    short, longer = (mfmjax.cramer_rao(model, u, x0, dt=0.1, sigma=0.05, length=k)[1]
                     for k in (120, 400))
    assert np.all(np.isfinite(short)) and np.all(longer < short)
    # an experiment too large for float64 (u of 1e200): J^T J overflowed and every bound came
    # back inf, read as "undetermined", with only NumPy's overflow warning
    with pytest.raises(ValueError, match=r"cramer_rao\(\): the sensitivities overflow "
                                         r"float64 .* scale the experiment"):
        mfmjax.cramer_rao(model, u * 1e200, x0, dt=0.1, sigma=0.05)


def test_cramer_rao_of_an_unstable_model_says_why_its_bounds_are_infinite():
    """A pole at +0.68 over 100 s: the sensitivity columns grow e^68-fold and are numerically
    collinear, so every bound came back inf with nothing said, which the docstring reads as
    "undetermined". It now warns and names `length=`; 200 samples (10 s) give finite bounds,
    and a stable model's finite bounds do not warn."""
    unstable = mfmjax.Model.from_coefficients([-1.0, 0.8, 1.0], [[2.0]])
    u = np.sin(0.7 * np.arange(2000) * 0.05)[:, None]
    with pytest.warns(UserWarning, match=r"cramer_rao\(\): the model is unstable \(growth "
                                         r"rate 0\.677\).* give length= a few growth times"):
        _, crb = mfmjax.cramer_rao(unstable, u, np.zeros(2), dt=0.05, sigma=0.3)
    assert np.all(np.isinf(crb))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _, crb = mfmjax.cramer_rao(unstable, u, np.zeros(2), dt=0.05, sigma=0.3, length=200)
        assert np.all(np.isfinite(crb))
        stable = mfmjax.Model.from_coefficients([1.0, 0.8, 1.0], [[2.0]])
        assert np.all(np.isfinite(mfmjax.cramer_rao(stable, u, np.zeros(2), dt=0.05,
                                                    sigma=0.3)[1]))


@pytest.mark.parametrize("snr_db, tol", [(None, 0.5), (20.0, 2.0)])
def test_delay_estimation_262_4(snr_db, tol):
    true = mfmjax.Model.from_coefficients([0.002, 0.09, 1.0], [[0.004]], delays=[262.4],
                                          intersample=("foh",))
    sig = simulated_experiment(true, dt=1.0, n_samples=3000, seed=2)
    if snr_db is not None:
        sd = float(np.std(sig.y)) / 10 ** (snr_db / 20)
        y = np.asarray(sig.y) + sd * np.random.default_rng(5).standard_normal(3000)
        sig = Signals(y, sig.u, dt=1.0, intersample=("foh",), delays=sig.delays)
    res = mfmjax.search(sig, n=2, N=3, M=4, h=80.0, m=[[0]], delays=[np.arange(0, 401, 20)])
    coarse = res.best()
    assert abs(float(coarse.delays[0]) - 262.4) <= 20
    r = mfmjax.refine(sig, coarse, vary=("delays",), max_steps=30)
    assert abs(r.settings["delays"][0] - 262.4) < tol


def test_bad_windows_get_the_search_errors(noisy):
    # scores, refine and search share one window check (validation_window)
    _, sig, _ = noisy
    start = mfmjax.identify(sig, ST, ModulatingFunction(3, 4, 200.0))
    for call in (lambda **kw: mfmjax.scores(sig, ST, h=200.0, N=3, M=4, **kw),
                 lambda **kw: mfmjax.refine(sig, start, vary=("h",), **kw),
                 lambda **kw: mfmjax.search(sig, n=(2,), N=(3,), M=(4,), h=(200.0,), **kw)):
        with pytest.raises(ValueError, match="validate window .* must lie inside the record"):
            call(validate=(0.0, 5000.0))
        with pytest.raises(ValueError, match="observer_window must fit"):
            call(validate=(500.0, 1000.0), observer_window=900.0)


def test_refine_of_a_windowed_search_says_it_identifies_on_all_data():
    """A search with identify= windows, refined: refine re-identified on all of the signals,
    validation window included (a = [2.0475, 3.0643] against the candidate's [2.0096, 2.9983])
    without a word, so its E there was no held-out score; it warns now."""
    sig = simulated_experiment(Model.from_coefficients([2.0, 3.0, 1.0], [[1.0]],
                                                       intersample=["zoh"]),
                               dt=0.05, n_samples=1200, seed=2, noise_std=0.01)
    sr = mfmjax.search(sig, n=(2,), m=[(0,)], N=(3,), M=(3,), h=(1.7, 2.6),
                       identify=(0.0, 30.0), validate=(30.0, 59.95))
    assert sr.identify == ((0.0, 30.0),)
    with pytest.warns(UserWarning, match=r"refine\(\): the search identified on the windows "
                                         r"\[\(0.0, 30.0\)\], but refine identifies on all") as said:
        mfmjax.refine(sig, sr, top=1, vary=("h",), validate=(30.0, 59.95), max_steps=3)
    # every warning, the run's own (not converged) too, points at the caller's line (the
    # runs' pointed into _refine.py)
    assert any("not converged" in str(w.message) for w in said)
    assert {w.filename for w in said} == {__file__}, [(w.filename, w.lineno) for w in said]
    # without validate=, refine scores on the search's window (it scored the whole record:
    # value and start_value could not be compared with the table's E; an audit)
    assert sr.validate == (30.0, 59.95) and sr.to_dict()["validate"] == [30.0, 59.95]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        given = mfmjax.refine(sig, sr, top=1, vary=("h",), validate=(30.0, 59.95), max_steps=0)
        inherited = mfmjax.refine(sig, sr, top=1, vary=("h",), max_steps=0)
    assert inherited.start_value == given.start_value
    assert inherited.start_value == pytest.approx(float(sr.row(0)["E"]), rel=1e-9)
    # given the identification data alone, as the warning above advises: the search's
    # window lies outside them, so it is not inherited (it was refused: "validate window
    # (30, 59.95) must lie inside the record", a window the user never gave; a review)
    with pytest.warns(UserWarning, match=r"refine\(\): the search's validate window "
                                         r"\(30.0, 59.95\) lies outside these signals"):
        mfmjax.refine(sig.window(0.0, 30.0), sr, top=1, vary=("h",), max_steps=0)
    # estimate's search (selection="bic") keeps its validate window too (it was None there:
    # refine scored the whole record, 0.0338 for the table's 0.0112; a review)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        est = mfmjax.estimate(sig, n=(2,), m=[(0,)], N=(3,), M=(3,), h=(1.7,),
                              selection="bic", validate=(30.0, 59.95))
        r = mfmjax.refine(sig, est.search, top=1, vary=("h",), max_steps=0)
    assert est.search.validate == (30.0, 59.95)
    assert r.start_value == pytest.approx(float(est.search.row(0)["E"]), rel=1e-9)


def test_refine_never_returns_a_model_worse_than_its_start(noisy):
    """A start identified with its own eta (eq. 11) was re-identified with the default one
    along the path: an audit's start scored E = 1.2426, the path began at 1.2440 and refine
    returned 1.24399 as `improved`. With `eta=` the path starts at the start's own E; without
    it, score "E" compares the path with the start's own E and returns the start where the
    path is no better (`start_value`, `improved` against it)."""
    _, sig, _ = noisy
    eta = [0.0, 0.0, 1.0, 0.0, 0.0]  # a_2 = 1
    start = mfmjax.identify(sig, ST, ModulatingFunction(3, 4, 200.0), eta=eta)
    E0 = float(mfmjax.performance_index(start, sig))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # (max_steps_reached)
        r = mfmjax.refine(sig, start, vary=("h",), max_steps=4, eta=eta)
    assert r.start_value == pytest.approx(E0, rel=1e-9)
    assert r.path[0] == pytest.approx(E0, rel=1e-9)  # the start's own eta along the path
    assert r.value <= E0 and float(mfmjax.performance_index(r.model, sig)) <= E0 * (1 + 1e-9)
    default = mfmjax.identify(sig, ST, ModulatingFunction(3, 4, 200.0))
    E_default = float(mfmjax.performance_index(default, sig))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = mfmjax.refine(sig, start, vary=("h",), max_steps=1)  # (no eta: the default's path)
    assert r.path[0] == pytest.approx(E_default, rel=1e-9)
    assert r.value <= E0 * (1 + 1e-12) and r.improved == (r.value < E0 * (1 - 1e-9))
    if r.value >= E0:  # the start itself, with its own score, not a worse model
        assert r.model is start
    with pytest.raises(ValueError, match=r"refine\(\): eta must have one entry per parameter "
                                         r"\(5\), not all zero"):
        mfmjax.refine(sig, start, vary=("h",), eta=[1.0, 1.0])
    # score "J": a start's own J_rel is of its own data; its settings' J_rel on these signals
    # (the path's first point) stands for it (a start of other data read improved=False for
    # a J_rel that fell from 0.125 to 0.036)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = mfmjax.refine(sig, start, score="J", vary=("h",), max_steps=3)
    assert r.start_value == pytest.approx(r.path[0], rel=1e-12)
    assert r.improved == (r.value < r.path[0] * (1 - 1e-9))


def test_refine_bounds_that_cannot_be_met_are_refused_and_edges_are_said(noisy):
    """A delay box below 0 and an h box whose top leaves the record no valid samples were
    accepted (the iterates there scored inf: a silently unusable box); refused now. A refined
    setting at an edge of its box that is not a physical limit is warned (h = 8.08, the
    default top, came back unsaid)."""
    from mfmjax._refine import _edges

    _, sig, _ = noisy
    start = mfmjax.identify(sig, ST, ModulatingFunction(3, 4, 200.0))
    with pytest.raises(ValueError, match=r"bounds\['delays'\] lo must be >= 0 \(got -1.0\)"):
        mfmjax.refine(sig, start, vary=("delays",), bounds={"delays": (-1.0, 5.0)})
    with pytest.raises(ValueError, match=r"the bounds let h plus the delays reach 4000, which "
                                         r"leaves the record \(3997.5 time units\) 0 valid "
                                         r"samples, need 10; lower the upper bound"):
        mfmjax.refine(sig, start, vary=("h",), bounds={"h": (100.0, 4000.0)})
    box = {"h": (50.0, 800.0), "N": (2.0, 12.0), "M": (2.0, 12.0),
           "delays": (np.zeros(2), np.array([10.0, 10.0]))}
    with pytest.warns(UserWarning, match=r"refine\(\): h = 799.9 at its upper bound 800; "
                                         r"delays\[1\] = 10 at its upper bound 10: the optimum "
                                         r"may lie beyond the box"):
        _edges("refine", {"h": 799.9, "N": 2.0, "M": 6.0, "delays": [0.0, 10.0]}, box,
               ("h", "N", "M", "delays"), 2, {"h", "delays"})
    with pytest.warns(UserWarning, match=r"h = 799.9 at its upper bound 800 \(refine's default "
                                         r"box\): the optimum"):  # (not a box the user gave)
        _edges("refine", {"h": 799.9}, box, ("h",), 2)
    with warnings.catch_warnings():  # N = n and a delay of 0 are physical limits: nothing said
        warnings.simplefilter("error")
        _edges("refine", {"h": 400.0, "N": 2.0, "M": 6.0, "delays": [0.0, 3.0]}, box,
               ("h", "N", "M", "delays"), 2)
    with pytest.warns(UserWarning, match=r"h = 50.1 at its lower bound 50"):
        _edges("refine", {"h": 50.1}, box, ("h",), 2)


def test_refine_that_does_not_move_says_so():
    """From h on a sample multiple (E jumps there), BFGS rejected every step and stopped
    "successful" after 30 of them; the start came back with `improved` True (a rounding-level
    difference) and nothing said (an audit's record: 2 / (s^2 + 3 s + 2), 20 dB). Now the
    start, `improved` False, and a warning."""
    from mfmjax.datasets import simulated_experiment

    plant = Model.from_coefficients([2.0, 3.0, 1.0], [[2.0]])
    s = simulated_experiment(plant, dt=0.05, n_samples=600, seed=0)
    y = np.asarray(s.y)
    y = y + np.std(y) / 10 * np.random.default_rng(1).standard_normal(600)
    sig = Signals(y, np.asarray(s.u), dt=0.05, intersample=s.intersample, offset=False)
    start = mfmjax.identify(sig, Structure(2, (0,)), ModulatingFunction(3, 4, 2.0))
    with pytest.warns(UserWarning, match=r"refine\(\): no improvement on the start \(BFGS "
                                         r"stopped at it, or scored every step it tried worse\); "
                                         r"returning the start"):
        r = mfmjax.refine(sig, start, vary=("h", "N", "M"))
    # (value: the observation's E of the start, start_value: the objective's; two programs
    # of the same E agree to rounding)
    assert r.model is start and not r.improved
    assert r.value == pytest.approx(r.start_value, rel=1e-12)
