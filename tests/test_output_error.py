"""Output error says when it did not converge, and recovers from an unstable start (issue 14)."""

import warnings

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

import mfmjax
from mfmjax import Model, Structure
from mfmjax._output_error import stabilised
from mfmjax.datasets import simulated_experiment

TRUE = Model.from_coefficients([2.0, 3.0, 1.0], [[1.0]], intersample=["zoh"])


@pytest.fixture(scope="module")
def noisy():
    return simulated_experiment(TRUE, dt=0.05, n_samples=800, seed=2, noise_std=0.01)


def test_stabilised_mirrors_right_half_plane_poles():
    # (s - 1)(s + 2) = s^2 + s - 2: the pole at +1 goes to -1 -> (s + 1)(s + 2)
    unstable = Model.from_coefficients([-2.0, 1.0, 1.0], [[1.0]])
    fixed, changed = stabilised(unstable)
    assert changed
    np.testing.assert_allclose(np.asarray(fixed.a), [2.0, 3.0, 1.0], rtol=1e-8)
    same, changed = stabilised(TRUE)
    assert not changed and same is TRUE


def test_not_converged_is_reported_and_warned(noisy):
    start = mfmjax.identify(noisy, Structure(2, [0]), mfmjax.ModulatingFunction(3, 3, 2.0))
    with pytest.warns(UserWarning, match=r"output_error\(\): not converged"):
        fit = mfmjax.output_error(noisy, start, max_steps=1)
    assert not fit.converged
    last = fit.summary().splitlines()[-1]  # the solver's code once (it was printed twice)
    assert last.startswith(f"NOT CONVERGED ({fit.result} after 1 steps)")
    assert last.count(fit.result) == 1
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a converged fit does not warn
        done = mfmjax.output_error(noisy, start)
    assert done.converged and "converged" in done.summary()
    assert "NOT" not in done.summary()


def test_a_list_of_records_is_fitted_as_a_batch_and_vmap_is_refused(noisy):
    """`output_error([records], start)` (a Monte Carlo polish): each fit is the record's own
    `output_error` (the same program per pair: 1e-12 of the parameters), one warning counts
    the fits that did not converge, and a window or a count mismatch is refused by name.
    `jax.vmap(output_error)` over stacked records says it runs on the host and names the
    list (before: JAX's TracerArrayConversionError from inside the host code)."""
    import jax

    recs = [noisy] + [simulated_experiment(TRUE, dt=0.05, n_samples=800, seed=s,
                                           noise_std=0.01) for s in (3, 4)]
    start = mfmjax.identify(noisy, Structure(2, [0]), mfmjax.ModulatingFunction(3, 3, 2.0))
    fits = mfmjax.output_error(recs, start)
    for r, got in zip(recs, fits):
        want = mfmjax.output_error(r, start)
        assert got.converged and got.names == want.names
        np.testing.assert_allclose(got.theta, want.theta, rtol=1e-12)
    with pytest.warns(UserWarning, match=r"output_error\(\): 3 of 3 fits did not converge"):
        short = mfmjax.output_error(recs, [start] * 3, max_steps=1)
    assert not any(f.converged for f in short)
    with pytest.raises(ValueError, match=r"output_error\(\): 3 records but 2 start models"):
        mfmjax.output_error(recs, [start] * 2)
    with pytest.raises(ValueError, match=r"output_error\(\): a list of records is fitted on "
                                         r"whole records; give window=None"):
        mfmjax.output_error(recs, start, window=(0.0, 20.0))
    stacked = jax.tree.map(lambda *x: jnp.stack(x), *recs)
    with pytest.raises(TypeError, match=r"output_error\(\) runs on the host .* pass a list"):
        jax.vmap(lambda r: mfmjax.output_error(r, start).theta)(stacked)


def test_unstable_start_is_stabilised_and_fitted(noisy):
    """An unstable start (a_1 < 0) used to raise 'overflows float64 ... shorten the window'.
    Mirrored, it is a stable start with the same |A| on the imaginary axis; the fit then finds
    the true parameters to the noise level (std 0.01 on an O(0.5) output, 800 samples: the
    standard errors are ~1e-2 relative, so 5 % is a 5-sigma bound)."""
    start = Model.from_coefficients([2.0, -3.0, 1.0], [[1.0]], intersample=["zoh"])
    fit = mfmjax.output_error(noisy, start, max_steps=200)
    assert fit.stabilised and fit.converged
    assert np.isfinite(fit.E) and fit.E <= fit.E_start
    np.testing.assert_allclose(fit.theta, [2.0, 3.0, 1.0], rtol=0.05)
    assert "start was unstable" in fit.summary()


def test_fitted_model_describes_its_own_parameters(noisy, tmp_path):
    """The returned model carries what describes it, not the start's MFM diagnostics: `theta`
    is the fitted free-parameter vector (as `srivc`'s), J, J_rel and cond are NaN, no MF, and
    the status says whether A(s) is Hurwitz. A truly unstable plant (pole at +0.048, 20 s
    record: the response grows 2.6x, well inside float64) is fitted unstable and flagged;
    before, the start's theta, J and status `ok` came back beside the new a and b."""
    start = mfmjax.identify(noisy, Structure(2, [0]), mfmjax.ModulatingFunction(3, 3, 2.0))
    fit = mfmjax.output_error(noisy, start)
    m = fit.model
    np.testing.assert_array_equal(np.asarray(m.theta), fit.theta)
    # and keeps it through its file (load_model rebuilt [a; b] / sum, one entry longer)
    mfmjax.save_model(m, tmp_path / "oe.json")
    np.testing.assert_array_equal(np.asarray(mfmjax.load_model(tmp_path / "oe.json").theta),
                                  fit.theta)
    np.testing.assert_array_equal(np.asarray(m.a)[:2], fit.theta[:2])
    assert np.isnan(float(m.J)) and np.isnan(float(m.J_rel)) and np.isnan(float(m.cond))
    assert m.mf is None and int(m.status) == 0
    plant = Model.from_coefficients([-0.05, 1.0, 1.0], [[1.0]])
    t = np.arange(400) * 0.05
    u = (np.sin(1.3 * t) + 0.5 * np.sign(np.sin(0.4 * t)))[:, None]
    y = np.asarray(mfmjax.simulate(plant, u, dt=0.05))
    y = y + 1e-3 * np.random.default_rng(0).standard_normal(y.size)
    sig = mfmjax.Signals(y, u, dt=0.05)
    grown = mfmjax.output_error(sig, mfmjax.identify(sig, Structure(2, [0]),
                                                     mfmjax.ModulatingFunction(3, 3, 2.0)))
    assert grown.converged and float(grown.model.a[0]) < 0  # the plant's pole at +0.048
    assert int(grown.model.status) == int(mfmjax.Status.UNSTABLE)
    assert "unstable" in grown.model.summary()


def test_refine_out_of_steps_warns_and_says_so(noisy):
    start = mfmjax.identify(noisy, Structure(2, [0]), mfmjax.ModulatingFunction(3, 3, 2.0))
    with pytest.warns(UserWarning, match=r"refine\(\): not converged \(max_steps_reached"):
        r = mfmjax.refine(noisy, start, vary=("h",), max_steps=1)
    assert not r.converged and r.result == "max_steps_reached"


def test_levenberg_marquardt_reaches_minpack_minimum(noisy):
    """The compiled Levenberg-Marquardt loop against MINPACK's (scipy.optimize.least_squares,
    method='lm') on the same residual (parameters and initial state, through the public
    `simulate`), from the same start. Both stop at a minimum of a smooth problem: their sums
    of squares agree to 1e-9 relative (ours stops when a step changes the cost by < 1e-10
    relative; it may not be worse than MINPACK's by more than ten such steps)."""
    from scipy.optimize import least_squares

    from mfmjax._output_error import with_parameters

    start = mfmjax.identify(noisy, Structure(2, [0]), mfmjax.ModulatingFunction(3, 3, 2.0))
    fit = mfmjax.output_error(noisy, start)
    assert fit.converged
    u, y = np.asarray(noisy.u), np.asarray(noisy.y)

    def residual(v):
        m = with_parameters(start, jnp.asarray(v[:3]))
        return y - np.asarray(mfmjax.simulate(m, u, jnp.asarray(v[3:]), dt=noisy.dt))

    v0 = np.concatenate([np.asarray(fit.start.a)[:2], np.asarray(fit.start.b[0]),
                         np.zeros(2)])
    ref = least_squares(residual, v0, method="lm", xtol=1e-14, ftol=1e-14, gtol=1e-14)
    ours = np.sum(residual(np.concatenate([fit.theta, np.asarray(fit.x0)])) ** 2)
    assert ours <= np.sum(ref.fun**2) * (1 + 1e-9)
    # each stops within ~1e-10 (relative, its step test) of the minimum; measured 2.5e-9 apart
    np.testing.assert_allclose(fit.theta, ref.x[:3], rtol=1e-7)


def test_structures_of_one_padded_order_share_one_program(noisy):
    """`output_error_many(..., n_max=3)` (estimate's batch path) pads every structure to order 3
    with cubic numerators: nine (record, start) pairs of three structures (n = 1 and 2, m = 0
    and 1; a third order on these second-order data does not converge) run as
    one chunk of `BATCH` pairs and one single pair, each compiled once, and each result is the
    direct `output_error` of its pair. Both stop within the solver's tolerance (a step below
    1e-10 relative in the scaled unknowns) of one minimum, on rounding that differs with the
    padded solve; 1e-7 (norm-wise, as the batched `estimate` test) bounds that, and is 1e-5
    of these fits' standard errors."""
    from jaxlog import compiles

    from mfmjax._batch import BATCH
    from mfmjax._output_error import output_error_many

    starts = [Model.from_coefficients(a, b, intersample=["zoh"]) for a, b in
              (([1.5, 1.0], [[0.5]]), ([2.2, 2.8, 1.0], [[0.9]]),
               ([2.2, 2.8, 1.0], [[0.9, 0.1]]))]
    recs = [simulated_experiment(TRUE, dt=0.05, n_samples=800, seed=s, noise_std=0.01)
            for s in (2, 3, 4)]
    pairs = [(r, m) for r in recs for m in starts]
    assert len(pairs) == BATCH + 1
    with compiles() as names:
        many = output_error_many([r for r, _ in pairs], [m for _, m in pairs], n_max=3)
    assert names.count("jit(_lm_many)") == 1 and names.count("jit(_lm)") == 1, names
    for (r, m), got in zip(pairs, many):
        want = mfmjax.output_error(r, m)
        assert got.names == want.names and got.converged and want.converged
        err = np.linalg.norm(got.theta - want.theta) / np.linalg.norm(want.theta)
        assert err <= 1e-7, (m.n, err)
        np.testing.assert_allclose(got.std_errors, want.std_errors, rtol=1e-5)


def test_first_call_compiles_the_observer_and_the_solver_only(monkeypatch):
    """A first `output_error` (a record length no other test uses) compiles two programs: the
    padded start observer and the Levenberg-Marquardt loop, which returns the residual and
    Jacobian at the start and at its point, so the covariance needs no program of its own
    (before: four, with a residual and a Jacobian program). The loop compiles while the
    observer runs on a second thread (`_output_error._rehearsal`: a run of no step from a
    stand-in residual), so the real solve compiles nothing; a second call rehearses nothing
    and gives the same fit bitwise."""
    from jaxlog import compiles

    from mfmjax import _output_error

    sig = simulated_experiment(TRUE, dt=0.05, n_samples=731, seed=5, noise_std=0.01)
    start = Model.from_coefficients([2.2, 2.8, 1.0], [[0.9]], intersample=["zoh"])
    calls, real_lm = [], _output_error._lm

    def lm(residual, z0, max_steps, *limits):  # the compiles during each solver call
        before = len(names)
        out = real_lm(residual, z0, max_steps, *limits)
        calls.append((int(max_steps), names[before:]))
        return out

    monkeypatch.setattr(_output_error, "_lm", lm)
    with compiles() as names:
        fit = mfmjax.output_error(sig, start)
    assert sorted(names) == ["jit(_lm)", "jit(observe_candidate)"], names
    assert [c[0] for c in calls] == [0, 100]  # the rehearsal, then the real solve
    assert "jit(_lm)" in calls[0][1] and calls[1][1] == [], calls
    assert fit.converged and np.all(np.isfinite(fit.std_errors)) and fit.E < fit.E_start
    again = mfmjax.output_error(sig, start)
    assert [c[0] for c in calls] == [0, 100, 100]
    np.testing.assert_array_equal(again.theta, fit.theta)
    np.testing.assert_array_equal(again.covariance, fit.covariance)


def test_refuses_a_start_whose_offset_flag_differs_from_the_signals(noisy):
    """A model without an offset term on `Signals(offset=True)` used to fit the offset into a
    b coefficient's slot and report convergence (and, the other way round, never fit the
    offset): both are refused by name, as `srivc` refuses them."""
    with_offset = mfmjax.Signals(noisy.y, noisy.u, dt=noisy.dt, intersample=["zoh"], offset=True)
    with pytest.raises(ValueError, match=r"model.has_offset=False but signals.offset=True"):
        mfmjax.output_error(with_offset, TRUE)
    start = Model.from_coefficients([2.0, 3.0, 1.0], [[1.0]], offset=0.1, intersample=["zoh"])
    without = mfmjax.Signals(noisy.y, noisy.u, dt=noisy.dt, intersample=["zoh"], offset=False)
    with pytest.raises(ValueError, match=r"model.has_offset=True but signals.offset=False"):
        mfmjax.output_error(without, start)


def test_fitted_model_carries_the_signals_intersample_rules(noisy):
    """Output error simulates with the signals' intersample rules; the returned model used to
    keep the start's, so `observe` (which uses the model's) disagreed with the fit's own E.
    Started from the zoh truth on data declared foh, the fit's model says foh and `observe`
    reproduces its E within 1 %: the two E differ only by the quadrature of eq. 17 (the
    output's cubic rule against the fit's sum of squares times dt: end corrections of a few
    samples in 800, about 0.5 %) and by the initial state (the observer's least-squares x0
    against the fitted one: it can only lower E). The start's zoh label gave 19 % more."""
    from mfmjax._pytree import replace_fields

    sig = mfmjax.Signals(noisy.y, noisy.u, dt=noisy.dt, intersample=["foh"], offset=False)
    fit = mfmjax.output_error(sig, TRUE)
    assert fit.model.intersample == ("foh",)
    assert abs(float(mfmjax.observe(fit.model, sig).E) - fit.E) <= 0.01 * fit.E
    mislabelled = replace_fields(fit.model, intersample=("zoh",))
    assert float(mfmjax.observe(mislabelled, sig).E) > 1.1 * fit.E  # the check can fail


def test_undetermined_parameters_get_infinite_std_errors_and_a_warning():
    """With u = 0 the numerator has zero sensitivity: its std errors are inf and its
    covariances NaN (a pseudo-inverse gave 0, read as "perfectly determined"); the summary
    and a warning name them. The determined block is sigma2_hat (J^T J)^-1 of (a, x0) at the
    fit, sigma2_hat = RSS / (T - 6), J by central differences of scipy's lsim (step 1e-6:
    truncation ~1e-12, lsim ~1e-9, so 1e-5 relative as in the Cramer-Rao test)."""
    import reference as R

    start = Model.from_coefficients([0.5, 1.5, 1.0], [[0.5, 0.2]], intersample=("zoh",))
    u, x0 = np.zeros((400, 1)), np.array([0.2, -0.1])
    y = R.lsim([0.5, 1.5, 1.0], [[0.5, 0.2]], u, 0.1, ("zoh",), x0)
    y = y + 1e-3 * np.random.default_rng(0).standard_normal(400)
    sig = mfmjax.Signals(y, u, dt=0.1, intersample=("zoh",))
    with pytest.warns(UserWarning, match=r"do not determine b_10, b_11 \(infinite"):
        fit = mfmjax.output_error(sig, start)
    assert fit.converged
    assert np.all(np.isinf(fit.std_errors[2:])) and np.all(np.isfinite(fit.std_errors[:2]))
    assert np.all(np.isnan(fit.covariance[:2, 2:])) and np.all(np.isnan(fit.covariance[2, 3]))
    assert "NOT DETERMINED by the data (infinite std error, the value is arbitrary): b_10, " \
           "b_11" in fit.summary()

    def sim(v):
        return R.lsim([v[0], v[1], 1.0], [[0.5, 0.2]], u, 0.1, ("zoh",), v[2:])

    v = np.concatenate([fit.theta[:2], np.asarray(fit.x0)])
    r = y - sim(v)
    np.testing.assert_allclose(fit.sigma2, np.sum(r**2) / (400 - 6), rtol=1e-5)
    J = np.stack([(sim(v + e) - sim(v - e)) / 2e-6 for e in np.eye(4) * 1e-6], 1)
    ref = fit.sigma2 * np.linalg.inv(J.T @ J)[:2, :2]
    np.testing.assert_allclose(fit.covariance[:2, :2], ref, rtol=1e-5)


def test_output_error_says_what_its_result_hides():
    """An output-error audit: signals given a 0.5 s dead time of their own and a start built
    with delays 0 fitted at the start's delays without a word (a = [0.77, 1.27] for [2, 3],
    converged); a fit that came out unstable read "converged (...)" only; max_steps=0 called
    the start "the best iterate". Each is said now (warnings, the summary)."""
    import warnings as w

    delayed = Model.from_coefficients([2.0, 3.0, 1.0], [[1.0]], delays=[0.5],
                                      intersample=["zoh"])
    rec = simulated_experiment(delayed, dt=0.05, n_samples=800, seed=2, noise_std=0.01)
    sig = mfmjax.Signals(rec.y, rec.u, dt=0.05, intersample=["zoh"], delays=[0.5], offset=False)
    start = Model.from_coefficients([2.2, 3.3, 1.0], [[1.1]], intersample=["zoh"])
    with pytest.warns(UserWarning, match=r"output_error\(\): the start model's delays \[0.0\] "
                                         r"are used, not the signals' own \[0.5\]"):
        mfmjax.output_error(sig, start)
    with w.catch_warnings():
        w.simplefilter("error")  # the start given the record's delays: nothing to say
        fit = mfmjax.output_error(sig, Model.from_coefficients(
            [2.2, 3.3, 1.0], [[1.1]], delays=[0.5], intersample=["zoh"]))
    np.testing.assert_allclose(fit.theta, [2.0, 3.0, 1.0], rtol=0.05)
    with pytest.warns(UserWarning, match="the result is the start"):
        mfmjax.output_error(sig, Model.from_coefficients([2.2, 3.3, 1.0], [[1.1]], delays=[0.5],
                                                         intersample=["zoh"]), max_steps=0)
    # a 1 s window (20 samples): a_1 = -2.11, status unstable, and the fit read converged
    with pytest.warns(UserWarning, match=r"output_error\(\): the fitted model is unstable"):
        short = mfmjax.output_error(sig, Model.from_coefficients(
            [2.2, 3.3, 1.0], [[1.1]], delays=[0.5], intersample=["zoh"]), window=(5.0, 6.0))
    assert int(short.model.status) & mfmjax.Status.UNSTABLE
    assert "UNSTABLE: the fitted A(s) has a root with Re >= 0" in short.summary()


def _two_inputs_one_delayed():
    """2/(s^2 + 3 s + 2) from u1 delayed 0.47 s, 0.5/(...) from u2, held inputs, 800 samples
    of 0.05 s: (T, dt, u, noise-free y, the generator that drew u, for the noise)."""
    true = Model.from_coefficients([2.0, 3.0, 1.0], [[1.0], [0.5]], delays=[0.47, 0.0],
                                   intersample=["zoh", "zoh"])
    T, dt = 800, 0.05
    rng = np.random.default_rng(0)
    u = np.column_stack([np.repeat(rng.normal(size=T // 20 + 1), 20)[:T],
                         np.repeat(rng.normal(size=T // 25 + 1), 25)[:T]])
    return T, dt, u, np.asarray(mfmjax.simulate(true, u, dt=dt)), rng


def test_delay_uncertainty_counts_a_fitted_delay_in_the_std_errors():
    """A delay estimated from the same data (refine, a search's delay grid) held as known:
    the std errors came out 0.43-0.52 of the estimates' spread (10 dB, 800 samples, 70
    realisations; coverage of nominal 95 % intervals 56-67 %). `delay_uncertainty=True` adds a
    Jacobian column per nonzero delay (forward mode through the simulation, checked here
    against central differences of the same residual) and takes the parameters' block of the
    joint covariance: 1.00-1.01 of the spread in the same study (README), and the delay's own
    std error. The parameters are the same fit; a zero delay is not counted (NaN)."""
    from mfmjax._output_error import _delay_jacobian, _prepare

    T, dt, u, y0, rng = _two_inputs_one_delayed()
    y = y0 + np.std(y0) * 10 ** (-10 / 20) * rng.standard_normal(T)
    sig = mfmjax.Signals(y, u, dt=dt, intersample=["zoh", "zoh"], delays=[0.47, 0.0],
                         offset=False)
    start = mfmjax.identify(sig, Structure(2, [0, 0]), mfmjax.ModulatingFunction(3, 3, 1.0))
    known = mfmjax.output_error(sig, start)
    fitted = mfmjax.output_error(sig, start, delay_uncertainty=True)
    assert known.delay_std_errors is None
    np.testing.assert_array_equal(fitted.theta, known.theta)
    assert np.all(fitted.std_errors >= known.std_errors)
    # the delay and the denominator trade phase: their std errors grow most
    assert fitted.std_errors[0] > 1.3 * known.std_errors[0]
    d_std = fitted.delay_std_errors
    assert 0 < d_std[0] < 0.2 and np.isnan(d_std[1])
    assert "delay u1" in fitted.summary() and "delay u2" not in fitted.summary()
    # the Jacobian column against central differences of the residual in the delay (0.47 s,
    # 9.4 samples: smooth between whole-sample delays, where zoh's response is C^1 only;
    # 1e-6 relative at eps = 1e-5)
    residual, _ = _prepare(sig, start, None)
    z = jnp.zeros(residual.size)
    J = np.asarray(_delay_jacobian(residual, z))[:, 0]
    eps = 1e-5

    def r_at(d):
        c = dict(residual.c, delays=jnp.asarray([d, 0.0]))
        return np.asarray(type(residual)(**{**residual.__dict__, "c": c})(z, None))

    fd = (r_at(0.47 + eps) - r_at(0.47 - eps)) / (2 * eps)
    assert np.linalg.norm(J - fd) <= 1e-6 * np.linalg.norm(fd)
    with pytest.raises(ValueError, match=r"delay_uncertainty is for one record"):
        mfmjax.output_error([sig, sig], start, delay_uncertainty=True)


def test_fit_delays_fits_the_nonzero_delays_with_the_parameters():
    """`fit_delays=True`: the nonzero delays are unknowns of the same Levenberg-Marquardt fit
    (their Jacobian columns from the same forward-mode pass), the model carries the fitted
    delays, a zero delay is held (NaN std error), and the covariance is the joint one. Started
    on a grid point (0.5 s) of a 0.47 s delay, noise-free: the delay and the parameters to the
    truth (LM's rtol 1e-10 on z; 1e-7 allows for the conditioning of the joint fit). On noisy
    data the std errors equal those of `delay_uncertainty=True` held at the fitted delay (the
    same Gauss-Newton covariance at the same optimum, reached by two paths to rtol 1e-10: 1e-5
    relative), and a list of records is fitted as each alone (1e-12)."""
    T, dt, u, y0, rng = _two_inputs_one_delayed()
    start = Model.from_coefficients([2.2, 3.3, 1.0], [[1.1], [0.45]], delays=[0.5, 0.0],
                                    intersample=["zoh", "zoh"])

    def record(y):
        return mfmjax.Signals(y, u, dt=dt, intersample=["zoh", "zoh"], delays=[0.5, 0.0],
                              offset=False)

    exact = mfmjax.output_error(record(y0), start, fit_delays=True)
    assert exact.converged and exact.delays_fitted
    np.testing.assert_allclose(np.asarray(exact.model.delays), [0.47, 0.0], rtol=1e-7,
                               atol=1e-9)
    np.testing.assert_allclose(exact.theta, [2.0, 3.0, 1.0, 0.5], rtol=1e-7)
    held = mfmjax.output_error(record(y0), start)
    # held at the grid point the fit cannot reach the data (0.03 s of a response of unit
    # scale over 40 s: E about 1e-3), fitted it does to rounding
    assert held.E > 1e-6 and exact.E < 1e-20, (held.E, exact.E)
    assert np.isnan(exact.delay_std_errors[1]) and "(fitted)" in exact.summary()

    noisy = [record(y0 + np.std(y0) * 10 ** (-10 / 20) * rng.standard_normal(T))
             for _ in range(2)]
    fits = mfmjax.output_error(noisy, start, fit_delays=True)
    for sig, fit in zip(noisy, fits):
        alone = mfmjax.output_error(sig, start, fit_delays=True)
        np.testing.assert_allclose(fit.theta, alone.theta, rtol=1e-12)
        np.testing.assert_allclose(np.asarray(fit.model.delays), np.asarray(alone.model.delays),
                                   rtol=1e-12)
        np.testing.assert_allclose(fit.delay_std_errors, alone.delay_std_errors, rtol=1e-12)
        # the joint covariance (parameters, then each input's delay; the one of 0 held: zero
        # rows) holds the marginal blocks reported (the bands read it)
        p, J = len(alone.names), alone.joint_covariance
        assert J.shape == (p + 2, p + 2) and not np.any(J[p + 1]) and not np.any(J[:, p + 1])
        np.testing.assert_array_equal(J[:p, :p], alone.covariance)
        assert J[p, p] == pytest.approx(alone.delay_std_errors[0] ** 2, rel=1e-14)  # (sqrt)
        d = np.asarray(alone.model.delays)
        assert abs(d[0] - 0.47) < 4 * alone.delay_std_errors[0] and d[1] == 0.0
        at = mfmjax.output_error(eqx.tree_at(lambda q: q.delays, sig, jnp.asarray(d)),
                                 alone.model, delay_uncertainty=True)
        np.testing.assert_allclose(at.std_errors, alone.std_errors, rtol=1e-5)
        np.testing.assert_allclose(at.delay_std_errors, alone.delay_std_errors, rtol=1e-5)
    # every delay 0: nothing to fit, the fit is output error's own (delays held)
    zero = Model.from_coefficients([2.2, 3.3, 1.0], [[1.1], [0.45]], intersample=["zoh", "zoh"])
    sig0 = mfmjax.Signals(y0, u, dt=dt, intersample=["zoh", "zoh"], offset=False)
    none = mfmjax.output_error(sig0, zero, fit_delays=True)
    assert not none.delays_fitted and np.all(np.isnan(none.delay_std_errors))
    np.testing.assert_allclose(none.theta, mfmjax.output_error(sig0, zero).theta, rtol=1e-6)
