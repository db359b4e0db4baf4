"""Residual analysis, compare, step / frequency responses with bands, delay-keeping export.

Each quantity is checked against its plain NumPy (or SciPy) definition written below."""

from __future__ import annotations

import functools
import math
import types
import warnings

import jax
import numpy as np
import pytest
from scipy import signal
from scipy.stats import chi2

import mfmjax
from mfmjax import Model, Signals
from mfmjax._analysis import Z99, residual_tests

DT, T, TAU = 0.05, 1500, 0.2
A_TRUE, B_TRUE = [1.0, 0.8, 1.0], [[1.0, 0.3]]
PNG = b"\x89PNG\r\n\x1a\n"


def _model(a=A_TRUE, b=B_TRUE, tau=TAU):
    return Model.from_coefficients(a, b, delays=[tau], intersample=["zoh"])


@functools.cache
def record() -> Signals:
    """The true model driven by white zoh noise, plus white output noise (seed fixed)."""
    rng = np.random.default_rng(1)
    u = rng.standard_normal(T)
    y = np.asarray(mfmjax.simulate(_model(), u, dt=DT))
    y = y + 0.05 * np.std(y) * rng.standard_normal(T)
    return Signals(y, u, dt=DT, intersample="zoh", delays=[TAU])


# -- NumPy twins --------------------------------------------------------------------------------


def corr_twin(a, b, tau):
    """(1/N) sum_t a(t) b(t - tau) over the t where both exist (plain loop)."""
    N = a.size
    return sum(a[t] * b[t - tau] for t in range(N) if 0 <= t - tau < N) / N


def resid_twin(e, u, L):
    N = e.size
    eb = e - e.mean()
    Re0 = corr_twin(eb, eb, 0)
    auto = np.array([corr_twin(eb, eb, k) / Re0 for k in range(L + 1)])
    out = {"auto": auto, "auto_bound": 2.5758293035489004 / math.sqrt(N),
           "Q": N * np.sum(auto[1:] ** 2), "cross": [], "bound": [], "Qx": [], "dof": []}
    r_ee = {k: auto[abs(k)] for k in range(-L, L + 1)}
    for k in range(u.shape[1]):
        ub = u[:, k] - u[:, k].mean()
        Ru0 = corr_twin(ub, ub, 0)
        c = np.array([corr_twin(eb, ub, tau) / math.sqrt(Re0 * Ru0) for tau in range(-L, L + 1)])

        @functools.cache
        def r_uu(j):
            return corr_twin(ub, ub, abs(j)) / Ru0

        P1 = sum(r_ee[j] * r_uu(j) for j in range(-L, L + 1))
        lags = range(-L, L + 1)
        S = np.array([[sum(r_ee[j] * r_uu(j + ti - tj) for j in range(-L, L + 1)) / N
                       for ti in lags] for tj in lags])
        lam, V = np.linalg.eigh(S)
        keep = lam > 1e-10 * lam.max()
        out["cross"].append(c)
        out["bound"].append(2.5758293035489004 * math.sqrt(P1 / N))
        out["Qx"].append(np.sum((V[:, keep].T @ c) ** 2 / lam[keep]))
        out["dof"].append(int(keep.sum()))
    return out


def test_correlations_match_numpy_definitions():
    rng = np.random.default_rng(0)
    N, L = 300, 12
    e = np.convolve(rng.standard_normal(N + 3), [1.0, 0.6, 0.2], "valid")[:N] + 0.1
    u = np.stack([np.convolve(rng.standard_normal(N + 4), [1, 0.9, 0.5, 0.2, 0.1], "valid")[:N],
                  rng.standard_normal(N) + 2.0], axis=1)
    got, ref = residual_tests(e, u, L), resid_twin(e, u, L)
    # FFT vs direct sums of O(1) terms: rounding ~ N * eps = 7e-14; 1e-12 bounds it
    np.testing.assert_allclose(got["auto"], ref["auto"], rtol=0, atol=1e-12)
    np.testing.assert_allclose(got["cross"], np.array(ref["cross"]), rtol=0, atol=1e-12)
    np.testing.assert_allclose(got["cross_bound"], ref["bound"], rtol=1e-12)
    assert got["auto_bound"] == pytest.approx(ref["auto_bound"], rel=1e-15)
    assert got["whiteness_stat"] == pytest.approx(ref["Q"], rel=1e-10)
    np.testing.assert_allclose(got["independence_stat"], ref["Qx"], rtol=1e-8)
    np.testing.assert_allclose(got["independence_critical"],
                               [chi2.ppf(0.99, d) for d in ref["dof"]], rtol=1e-12)
    assert got["whiteness_critical"] == pytest.approx(chi2.ppf(0.99, L), rel=1e-12)
    assert got["white"] == bool(ref["Q"] <= chi2.ppf(0.99, L))
    assert Z99 == pytest.approx(2.58, abs=5e-3)


def test_residuals_true_model_white_wrong_model_not(tmp_path):
    sig = record()
    res = mfmjax.residuals(_model(), sig, lags=20)
    obs = mfmjax.observe(_model(), sig)
    np.testing.assert_array_equal(res.e, np.asarray(sig.y) - np.asarray(obs.y_sim))
    ref = resid_twin(res.e, np.asarray(sig.u), 20)
    np.testing.assert_allclose(res.auto, ref["auto"], rtol=0, atol=1e-12)
    assert res.white and res.independent == (True,) and res.ok
    wrong = mfmjax.residuals(_model(a=[1.0, 1.6, 1.0]), sig, lags=20)
    assert not wrong.white and not wrong.ok
    assert "whiteness" in res.summary() and "PASS" in res.summary()
    assert "FAIL" in wrong.summary()
    d = wrong.to_dict()
    assert d["whiteness"]["pass"] is False and d["N"] == T
    path = tmp_path / "resid.png"
    res.plot(path)
    _is_png(path)


def test_residuals_window_and_errors():
    sig = record()
    res = mfmjax.residuals(_model(), sig, (10.0, 60.0), observer_window=10.0, lags=10)
    assert res.e.size == round(50.0 / DT) + 1 and res.t[0] == pytest.approx(10.0)
    obs = mfmjax.observe(_model(), sig, (10.0, 60.0), observer_window=10.0)
    k0 = round(10.0 / DT)
    np.testing.assert_array_equal(res.e, np.asarray(sig.y)[k0 : k0 + res.e.size]
                                  - np.asarray(obs.y_sim))
    with pytest.raises(ValueError, match=r"residuals\(\): lags=400 is more than a quarter"):
        mfmjax.residuals(_model(), sig, lags=400)
    with pytest.raises(ValueError, match=r"residuals\(\): lags must be an integer >= 1"):
        mfmjax.residuals(_model(), sig, lags=2.5)
    with pytest.raises(TypeError, match=r"residuals\(\): signals must be a Signals"):
        mfmjax.residuals(_model(), np.zeros(10))
    two = Model.from_coefficients(A_TRUE, [[1.0], [2.0]])
    with pytest.raises(ValueError, match=r"compare\(\): the model has 2 inputs but the signals"):
        mfmjax.compare(two, sig)


def test_compare_fit_is_the_numpy_nrmse(tmp_path):
    sig = record()
    cmp = mfmjax.compare(_model(), sig, (20.0, 70.0))
    k0 = round(20.0 / DT)
    y = np.asarray(sig.y)[k0 : k0 + cmp.y.size]
    np.testing.assert_array_equal(cmp.y, y)
    np.testing.assert_array_equal(cmp.y_sim, np.asarray(mfmjax.observe(_model(), sig,
                                                                       (20.0, 70.0)).y_sim))
    fit = 100 * (1 - np.linalg.norm(y - cmp.y_sim) / np.linalg.norm(y - y.mean()))
    assert cmp.fit == pytest.approx(fit, rel=1e-12)
    assert cmp.fit > 90  # 5 % output noise on the true model
    cmp.plot(tmp_path / "cmp.png")
    _is_png(tmp_path / "cmp.png")


# -- responses ----------------------------------------------------------------------------------


def step_twin(a, b, tau, t):
    """Unit step from rest of b(s)/a(s) e^{-s tau} (SciPy, shifted by the delay)."""
    sys = signal.lti(np.asarray(b)[::-1], np.asarray(a)[::-1])
    out = np.zeros_like(t)
    after = t >= tau - 1e-12
    ts = np.maximum(t[after] - tau, 0.0)
    if ts.size:
        _, y = signal.step(sys, T=ts)
        out[after] = y
    return out


def freq_twin(a, b, tau, w):
    s = 1j * w
    return np.polyval(np.asarray(b)[::-1], s) / np.polyval(np.asarray(a)[::-1], s) * np.exp(-s * tau)


def _theta_split(theta):  # free parameters a_0, a_1, b_0, b_1 of the 2nd-order test model
    return [theta[0], theta[1], 1.0], list(theta[2:4])


def _fd_std(fn, theta, cov, rel=1e-6):
    """Delta method with central finite differences (NumPy twin of the jacfwd one)."""
    cols = []
    for i in range(theta.size):
        h = rel * max(abs(theta[i]), 1.0)
        tp, tm = theta.copy(), theta.copy()
        tp[i] += h
        tm[i] -= h
        cols.append((fn(tp) - fn(tm)) / (2 * h))
    J = np.stack(cols, axis=-1)
    return np.sqrt(np.einsum("...i,ij,...j->...", J, cov, J))


COV = np.array([[4e-3, 1e-3, 5e-4, 0.0], [1e-3, 3e-3, 0.0, 2e-4], [5e-4, 0.0, 2e-3, 1e-4],
                [0.0, 2e-4, 1e-4, 1e-3]])
THETA = np.array([1.0, 0.8, 1.0, 0.3])


def test_step_response_and_band_match_scipy(tmp_path):
    tau = 0.25  # 10 steps of dt = 12.475 / 499 = 0.025
    model = _model(tau=tau)
    st = mfmjax.step_response(model, 12.475, covariance=COV, n_points=500)
    dt = 12.475 / 499
    assert st.t[1] == pytest.approx(dt, rel=1e-12)
    ref = step_twin(A_TRUE, B_TRUE[0], tau, st.t)
    # zoh step is exact: matrix exponentials on both sides, rounding ~1e-13 of the response
    np.testing.assert_allclose(st.y[0], ref, rtol=0, atol=1e-10)

    def fn(theta):
        a, b = _theta_split(theta)
        return step_twin(a, b, tau, st.t)

    sd = _fd_std(fn, THETA, COV)
    # central differences, h = 1e-6: truncation h^2 |y'''| ~ 1e-12, rounding eps / h ~ 1e-10
    np.testing.assert_allclose(st.std[0], sd, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(st.upper - st.y, Z99 * st.std, rtol=1e-15)
    assert np.all(st.y[0][st.t < tau - 1e-9] == 0)  # the delay: nothing before tau
    st.plot(tmp_path / "step.png")
    _is_png(tmp_path / "step.png")
    plain = mfmjax.step_response(model, 12.475, n_points=500)
    assert plain.std is None and plain.lower is None
    np.testing.assert_array_equal(plain.y, st.y)


def test_step_response_default_horizon_and_offset_excluded():
    model = Model.from_coefficients(A_TRUE, B_TRUE, offset=5.0, delays=[TAU])
    st = mfmjax.step_response(model)
    # poles -0.4 +- 0.92j: 7 / 0.4 + tau
    assert st.t[-1] == pytest.approx(7 / 0.4 + TAU, rel=1e-9)
    assert st.y[0, -1] == pytest.approx(B_TRUE[0][0] / A_TRUE[0], abs=2e-3)  # e^-7 of the gain


def test_step_response_default_horizon_of_undamped_poles():
    """(s^2 + 0.25)(s + 1): np.roots gives the undamped pair Re = -7e-17, which counted as a
    stable pole and set the default horizon to 7 / 7e-17 = 1e17 s; the response there lost
    the oscillation's phase to float64 (values off by up to 3.7 on a 0..7.6 response). Poles
    within the roots' rounding of the axis (1e-9 |p|, as `growing_poles`) are undamped now:
    the horizon is 3 periods of the slowest (37.7 s, beyond 7 s of the pole at -1), and the
    response equals the closed form. s(s^2 + 1) (7e300 before: "overflows float64") gets 3
    periods, over which it is t - sin t."""
    model = Model.from_coefficients([0.25, 0.25, 1.0, 1.0], [[1.0]])
    st = mfmjax.step_response(model)
    assert st.t[-1] == pytest.approx(3 * 2 * np.pi / 0.5, rel=1e-12)
    t = np.asarray(st.t)
    # 1/(s (s^2 + 1/4)(s + 1)) = 4/s - (4/5) e^-t/(s+1) - (16/5 s + 4/5)/(s^2 + 1/4)
    closed = 4 - 0.8 * np.exp(-t) - 3.2 * np.cos(t / 2) - 1.6 * np.sin(t / 2)
    np.testing.assert_allclose(st.y[0], closed, rtol=0, atol=1e-12)
    st = mfmjax.step_response(Model.from_coefficients([0.0, 1.0, 0.0, 1.0], [[1.0]]))
    assert st.t[-1] == pytest.approx(6 * np.pi, rel=1e-12)
    np.testing.assert_allclose(st.y[0], np.asarray(st.t) - np.sin(st.t), rtol=0, atol=1e-12)


def test_frequency_response_and_band_match_numpy(tmp_path):
    model = _model()
    w = np.logspace(-2, 1.5, 60)
    fr = mfmjax.frequency_response(model, w, covariance=COV)
    H = freq_twin(A_TRUE, B_TRUE[0], TAU, w)
    np.testing.assert_allclose(fr.H[0], H, rtol=1e-12)
    np.testing.assert_allclose(fr.mag_db[0], 20 * np.log10(np.abs(H)), rtol=0, atol=1e-11)
    np.testing.assert_allclose(np.exp(1j * np.radians(fr.phase_deg[0])), H / np.abs(H),
                               rtol=0, atol=1e-12)
    assert np.all(np.abs(np.diff(fr.phase_deg[0])) < 90)  # unwrapped

    def fn(theta):
        a, b = _theta_split(theta)
        Hn = freq_twin(a, b, 0.0, w)
        return np.stack([20 * np.log10(np.abs(Hn)), np.angle(Hn)])

    sd = _fd_std(fn, THETA, COV)
    np.testing.assert_allclose(fr.mag_db_std[0], sd[0], rtol=1e-6, atol=1e-10)
    np.testing.assert_allclose(fr.phase_deg_std[0], np.degrees(sd[1]), rtol=1e-6, atol=1e-8)
    fr.plot(tmp_path / "bode.png")
    _is_png(tmp_path / "bode.png")
    # the data's Nyquist frequency marked (inside the range: a line, the band above it
    # shaded; beyond it: said in the title, not a legend entry for a line clipped out of
    # view); a non-positive one refused by name
    from matplotlib.figure import Figure

    seen, save = [], Figure.savefig

    def spy(fig, *args, **kw):
        top = fig.axes[0]
        seen.append(([t.get_text() for t in top.get_legend().get_texts()], top.get_title()))
        return save(fig, *args, **kw)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(Figure, "savefig", spy)
        for nyq in (float(np.median(w)), 10 * float(w[-1])):
            fr.plot(tmp_path / "bode_nyquist.png", nyquist=nyq)
            _is_png(tmp_path / "bode_nyquist.png")
    (inside, title_in), (beyond, title_out) = seen
    assert "Nyquist of the data (pi/dt)" in inside and "above this grid" not in title_in
    assert "Nyquist of the data (pi/dt)" not in beyond and "above this grid" in title_out
    with pytest.raises(ValueError, match="nyquist"):
        fr.plot(tmp_path / "bad.png", nyquist=0.0)
    default = mfmjax.frequency_response(model)
    # |poles| = sqrt(a_0) = 1, |zero| = 1 / 0.3: from 0.01 x the smallest to 100 x the largest
    assert default.w[0] == pytest.approx(0.01, rel=1e-9)
    assert default.w[-1] == pytest.approx(100 / 0.3, rel=1e-9)
    with pytest.raises(ValueError, match=r"frequency_response\(\): w must hold frequencies > 0"):
        mfmjax.frequency_response(model, [0.0, 1.0])


def test_bands_from_a_fit_and_covariance_checks():
    model = _model()
    fit = types.SimpleNamespace(model=model, covariance=COV, names=("a_0", "a_1", "b_10", "b_11"))
    a = mfmjax.step_response(fit, 5.0, n_points=50)
    b = mfmjax.step_response(model, 5.0, covariance=COV, n_points=50)
    np.testing.assert_array_equal(a.std, b.std)
    with pytest.raises(ValueError, match=r"step_response\(\): covariance must be \(4, 4\)"):
        mfmjax.step_response(model, 5.0, covariance=np.eye(3))
    bad = types.SimpleNamespace(model=model, covariance=COV, names=("x", "a_1", "b_10", "b_11"))
    with pytest.raises(ValueError, match=r"frequency_response\(\): the fit's parameters"):
        mfmjax.frequency_response(bad)
    nan_fit = types.SimpleNamespace(model=model, covariance=np.full((4, 4), np.nan), names=())
    with pytest.warns(UserWarning, match=r"step_response\(\): the fit carries no usable"):
        assert mfmjax.step_response(nan_fit, 5.0, n_points=50).std is None
    with pytest.raises(TypeError, match=r"step_response\(\): model must be a Model or a fit"):
        mfmjax.step_response("model.json")


def test_bands_of_a_fit_whose_delay_was_fitted_hold_the_delays_uncertainty():
    """A fit that counted its delays (`output_error(..., fit_delays=True)`, `estimate` after
    a delay grid) carries `joint_covariance` over (parameters, delays): the bands are the
    delta method over both, as the NumPy twins with the delay as a fifth parameter (the phase
    gains -w tau, the step response shifts). They held the delay known: an audit of
    2026-11-28 measured a phase band 1.4x too narrow at w = 3 after a fitted delay (std error
    0.0042 s). Central differences: as the tests above."""
    model = _model()
    joint = np.zeros((5, 5))
    joint[:4, :4] = COV
    joint[4, 4], joint[0, 4], joint[4, 0], joint[2, 4], joint[4, 2] = 4e-3, 1e-3, 1e-3, -5e-4, -5e-4
    assert np.min(np.linalg.eigvalsh(joint)) > 0
    fit = types.SimpleNamespace(model=model, covariance=COV, joint_covariance=joint,
                                names=("a_0", "a_1", "b_10", "b_11"))
    w = np.logspace(-1, 1, 9)
    fr = mfmjax.frequency_response(fit, w)

    def phase(v):
        a, b = _theta_split(v[:4])
        return np.angle(freq_twin(a, b, 0.0, w)) - w * v[4]

    sd = _fd_std(phase, np.r_[THETA, TAU], joint)
    np.testing.assert_allclose(fr.phase_deg_std[0], np.degrees(sd), rtol=1e-6, atol=1e-8)
    known = mfmjax.frequency_response(model, w, covariance=COV)  # the delay held
    np.testing.assert_array_equal(fr.mag_db_std, known.mag_db_std)  # |H| has no delay
    assert np.max(np.abs(fr.phase_deg_std - known.phase_deg_std)) > 0.1 * np.max(
        known.phase_deg_std)
    st = mfmjax.step_response(fit, 5.0, n_points=97)  # tau between grid points (no kink)

    def step(v):  # b(s) / (a(s) s) by partial fractions, shifted by the delay v[4]
        a, b = _theta_split(v[:4])
        r, p, _ = signal.residue(np.asarray(b)[::-1], np.polymul(np.asarray(a)[::-1], [1, 0]))
        ts = st.t - v[4]
        return np.where(ts >= 0, (r * np.exp(np.outer(np.maximum(ts, 0), p))).sum(1).real, 0)

    np.testing.assert_allclose(st.y[0], step(np.r_[THETA, TAU]), rtol=0, atol=1e-12)
    sd = _fd_std(step, np.r_[THETA, TAU], joint)
    np.testing.assert_allclose(st.std[0], sd, rtol=1e-6, atol=1e-9)
    # a delay fitted down to its bound 0 (infinite std error, NaN covariances; the fit warned)
    # counts as known: the parameters' bands, not none at all
    bound = joint.copy()
    bound[4, :] = bound[:, 4] = np.nan
    bound[4, 4] = np.inf
    at_bound = types.SimpleNamespace(model=model, covariance=COV, joint_covariance=bound,
                                     names=fit.names)
    np.testing.assert_array_equal(mfmjax.frequency_response(at_bound, w).phase_deg_std,
                                  known.phase_deg_std)
    # a covariance given by the caller is the parameters' (the delays known), as before
    given = mfmjax.step_response(fit, 5.0, n_points=97, covariance=COV)
    np.testing.assert_array_equal(given.std, mfmjax.step_response(
        model, 5.0, n_points=97, covariance=COV).std)


def test_covariance_that_is_not_positive_semidefinite_or_not_finite_is_refused():
    """A symmetric "covariance" with a correlation of 10 (eigenvalue -1.9e-3 x) gave bands of
    zero width (clamped variances) without a word; an inf entry was refused with the data's
    advice ("remove or interpolate non-finite samples")."""
    model = _model()
    bad = COV.copy()
    bad[0, 1] = bad[1, 0] = 10 * np.sqrt(COV[0, 0] * COV[1, 1])
    with pytest.raises(ValueError, match=r"frequency_response\(\): covariance is not positive "
                                         r"semidefinite \(its correlation matrix has the "
                                         r"eigenvalue -9"):
        mfmjax.frequency_response(model, np.array([1.0]), covariance=bad)
    with pytest.raises(ValueError, match=r"step_response\(\): covariance has a NaN or inf .*an "
                                         r"undetermined parameter \(infinite variance\) has no "
                                         "band"):
        mfmjax.step_response(model, 5.0, covariance=np.diag([np.inf, 1.0, 1.0, 1.0]))
    # a parameter of zero variance is fine if it covaries with nothing
    fixed = COV.copy()
    fixed[0, :] = fixed[:, 0] = 0.0
    assert mfmjax.step_response(model, 5.0, covariance=fixed, n_points=20).std is not None


def test_phase_is_continuous_and_the_default_grid_finds_the_resonance():
    """np.unwrap of sampled angles took the wrong branch where the phase moved by more than
    180 degrees between grid points: 1/(s + 1)^4 at w = 0.1, 10 gave +22.8 degrees for
    -337.2, and two pole pairs of damping 5e-4 ended at +0.001 degrees for -360 on the default
    grid, whose log-spaced points also missed a resonance (32.8 dB shown of 54.0 dB at damping
    ratio 0.001). The phase is checked against the sum of the factors' angles; the peak
    against 1/(2 zeta sqrt(1 - zeta^2)) (the grid holds wn, where |G| is 1/(2 zeta): 2.2e-6 dB
    below the peak)."""
    four = Model.from_coefficients(np.poly([-1.0] * 4)[::-1], [[1.0]])
    w = np.array([0.1, 10.0])
    want = -4 * np.degrees(np.arctan(w))
    np.testing.assert_allclose(mfmjax.frequency_response(four, w).phase_deg[0], want, rtol=1e-12)
    # a grid starting at high frequency: the branch continuous from w -> 0 (it kept the first
    # point's principal value, +22.8 for -337.2); three integrators read -270 from any grid
    np.testing.assert_allclose(mfmjax.frequency_response(four, w[1:]).phase_deg[0], want[1:],
                               rtol=1e-12)
    triple = Model.from_coefficients([0.0, 0.0, 0.0, 1.0], [[1.0]])
    for grid in ([1e-3, 1.0], [1e3]):
        np.testing.assert_allclose(mfmjax.frequency_response(triple, np.array(grid)).phase_deg[0],
                                   -270.0, rtol=1e-12)
    # a negative gain starts at +180 as a low grid shows it (python-control, MATLAB), also
    # from a high grid: -1/(s + 1) at w = 1000 reads 180 - atan(1000), not its -269.9 branch
    neg = Model.from_coefficients([1.0, 1.0], [[-1.0]])
    assert mfmjax.frequency_response(neg, np.array([1e3])).phase_deg[0][0] == pytest.approx(
        180.0 - np.degrees(np.arctan(1e3)), rel=1e-12)
    q = [1.0, 0.001, 1.0]
    pairs = mfmjax.frequency_response(Model.from_coefficients(np.convolve(q, q), [[1.0]]))
    assert pairs.phase_deg[0][-1] == pytest.approx(-360.0, abs=0.01)
    assert np.all(np.abs(np.diff(pairs.phase_deg[0])) < 180.0)
    zeta = 0.001
    peak = mfmjax.frequency_response(Model.from_coefficients([1.0, 2 * zeta, 1.0], [[1.0]]))
    true = -20 * np.log10(2 * zeta * np.sqrt(1 - zeta**2))  # 53.98 dB
    assert true - 1e-3 < peak.mag_db.max() <= true + 1e-9
    # an undamped zero pair: no default grid point on it (the response is 0 there), whatever
    # n_points (401 points put one on w = 1 and raised "zero or infinite")
    notch = Model.from_coefficients([1.0, 2.0, 1.0], [[1.0, 0.0, 1.0]])
    for n_points in (400, 401):
        assert np.all(np.isfinite(mfmjax.frequency_response(notch, n_points=n_points).mag_db))


def test_residuals_of_a_perfect_fit_are_undefined_not_failed():
    """The true model on noise-free data: residuals at rounding level (1.7e-17 here) were
    judged as data (and exactly zero ones printed "Q = nan ... FAIL" and "undefined (constant
    input)" for an input that moves; report.json said pass: false). Within `EXACT_FIT` (1e-9
    of the output's spread) both tests are undefined."""
    sig = record()
    true = _model()
    exact = Signals(np.asarray(mfmjax.simulate(true, sig.u, dt=DT)), sig.u, dt=DT,
                    intersample=sig.intersample, delays=sig.delays)
    res = mfmjax.residuals(true, exact, window=(TAU, (T - 1) * DT))  # u known over the window
    assert 0 < np.max(np.abs(res.e)) < 1e-12 * np.std(np.asarray(exact.y))
    assert res.white is None and res.independent == (None,) and res.ok
    text = res.summary()
    assert "undefined (the residuals are constant or at rounding level" in text
    assert "undefined (residuals at rounding level)" in text and "FAIL" not in text
    # exactly zero residuals (the window from the record's start, the input held before it)
    with pytest.warns(UserWarning, match="is delayed by 0.2"):
        zero = mfmjax.residuals(true, exact)
    assert zero.white is None and zero.ok and "FAIL" not in zero.summary()
    assert res.to_dict()["whiteness"]["pass"] is None
    # "JSON-ready": strict JSON (NaN statistics of the undefined tests are None; they made
    # json.dumps(allow_nan=False) fail)
    import json

    for r in (res, zero):
        json.dumps(r.to_dict(), allow_nan=False)


# -- export -------------------------------------------------------------------------------------


def test_to_scipy_and_to_control_of_a_concrete_model_inside_a_users_jit():
    """A concrete model converted inside a traced function (a user's jit building a
    controller from a fixed model): the realisation stays NumPy, equal to the eager one
    exactly (the same NumPy operations). Before, `state_space` put its NumPy result on the
    device, which inside a trace is a traced value, and `to_scipy` failed with JAX's
    TracerArrayConversionError."""
    model = Model.from_coefficients([2.0, 3.0, 1.0], [[1.0, 0.5]], offset=0.3)
    eager_sp, seen = mfmjax.to_scipy(model), {}

    def f(x):
        seen["sp"] = mfmjax.to_scipy(model)
        return x * float(seen["sp"].A[1, 0])

    assert float(jax.jit(f)(2.0)) == 2.0 * float(eager_sp.A[1, 0])
    for name in ("A", "B", "C", "D"):
        np.testing.assert_array_equal(getattr(seen["sp"], name), getattr(eager_sp, name))
    control = pytest.importorskip("control")  # optional: to_control's half only
    eager_ct = mfmjax.to_control(model)
    jax.jit(lambda x: (seen.update(ct=mfmjax.to_control(model)), x)[1])(1.0)
    assert isinstance(seen["ct"], control.StateSpace)
    for name in ("A", "B", "C", "D"):
        np.testing.assert_array_equal(getattr(seen["ct"], name), getattr(eager_ct, name))


def test_to_control_keeps_delays_as_pade_and_to_scipy_refuses_them():
    control = pytest.importorskip("control")
    model = Model.from_coefficients([2.0, 3.0, 1.0], [[1.0, 0.5], [0.8]], delays=[0.0, 0.5],
                                    offset=0.3)
    sys = mfmjax.to_control(model)
    assert sys.ninputs == 3 and sys.nstates == 2 + 5 and sys.input_labels == ["u1", "u2", "offset"]
    w = np.linspace(0.05, 4.0, 40)  # omega tau <= 2
    H = sys(1j * w)[0]
    # Pade(5): exact magnitude, phase error < 5e-5 deg for omega tau <= 2 (docstring table):
    # |dH| / |H| = |dphase| in rad < 1e-6
    np.testing.assert_allclose(H[1], freq_twin([2.0, 3.0, 1.0], [0.8], 0.5, w), rtol=1e-6)
    np.testing.assert_allclose(H[0], freq_twin([2.0, 3.0, 1.0], [1.0, 0.5], 0.0, w), rtol=1e-12)
    np.testing.assert_allclose(H[2], freq_twin([2.0, 3.0, 1.0], [0.3], 0.0, w), rtol=1e-12)
    assert mfmjax.to_control(model, pade_order=0).nstates == 2
    assert control.ss2tf(mfmjax.to_control(model, pade_order=0)).den[0][0][0] == 1.0
    with pytest.raises(ValueError, match=r"to_scipy\(\): scipy.signal systems cannot carry"):
        mfmjax.to_scipy(model)
    sp = mfmjax.to_scipy(model, ignore_delays=True)
    assert sp.A.shape == (2, 2)
    # an input named "offset" beside the offset term: python-control kept one label for two
    # inputs, and sys[0, "offset"] picked the plant's input (B = 3, not the offset's)
    clash = Model.from_coefficients([1.0, 1.0], [[3.0]], offset=1.0, input_names=["offset"])
    with pytest.raises(ValueError, match=r"to_control\(\): the system's input labels "
                       r"\['offset', 'offset'\] .* must differ: rename the inputs"):
        mfmjax.to_control(clash)
    assert mfmjax.to_control(clash.labelled("y", ["heat"])).input_labels == ["heat", "offset"]
    with pytest.raises(ValueError, match=r"to_control\(\): pade_order must be"):
        mfmjax.to_control(model, pade_order=-1)


def test_save_model_keeps_an_optional_covariance(tmp_path):
    import json

    from mfmjax._analysis import saved_covariance

    model = _model()
    mfmjax.save_model(model, tmp_path / "m.json", covariance=COV)
    back = mfmjax.load_model(tmp_path / "m.json")
    cov, note = saved_covariance(tmp_path / "m.json", back)
    np.testing.assert_array_equal(cov, COV)
    assert json.loads((tmp_path / "m.json").read_text())["covariance"]["names"] == [
        "a_0", "a_1", "b_10", "b_11"]
    mfmjax.save_model(model, tmp_path / "plain.json")
    assert saved_covariance(tmp_path / "plain.json", back)[0] is None
    # the public reader: bands on a loaded model without `mfmjax report`
    np.testing.assert_array_equal(mfmjax.load_covariance(tmp_path / "m.json"), COV)
    assert mfmjax.load_covariance(tmp_path / "plain.json") is None
    band = mfmjax.step_response(back, 5.0, covariance=mfmjax.load_covariance(tmp_path / "m.json"),
                                n_points=50)
    assert band.std is not None and band.std[0, -1] > 0  # (zero before the delay)
    other = Model.from_coefficients([2.0, 3.0, 1.0], [[1.0]])  # another parameter layout
    with pytest.raises(ValueError, match=r"load_covariance\(\): .* not a finite matrix over"):
        mfmjax.load_covariance(tmp_path / "m.json", other)
    with pytest.raises(ValueError, match=r"save_model\(\): covariance must be a finite \(4, 4\)"):
        mfmjax.save_model(model, tmp_path / "x.json", covariance=np.eye(2))
    # a plain MFM estimate's NaN covariance: the message named the (right) shape
    with pytest.raises(ValueError, match=r"save_model\(\): covariance has non-finite entries "
                                         r"\(NaN or inf\): a model without standard errors"):
        mfmjax.save_model(model, tmp_path / "x.json", covariance=np.full((4, 4), np.nan))
    import json  # a hand-edited matrix: refused by file, not later by step_response

    doc = json.loads((tmp_path / "m.json").read_text())
    for i, j, v in ((0, 0, -1.0), (0, 1, 123.0)):
        bad = json.loads(json.dumps(doc))
        bad["covariance"]["matrix"][i][j] = v
        (tmp_path / "bad.json").write_text(json.dumps(bad))
        with pytest.raises(ValueError, match=r"load_covariance\(\): .*bad.json: the covariance "
                                             r"must be symmetric with a non-negative diagonal"):
            mfmjax.load_covariance(tmp_path / "bad.json")


def test_save_model_keeps_the_joint_covariance_of_fitted_delays(tmp_path):
    """A fit whose delays were fitted carries `joint_covariance`; `save_model` dropped it, so
    the bands of the loaded model (`mfmjax report` on the saved file) held the delays known,
    unsaid: an audit measured a phase band 7.5x narrower at w = 10 than the fit's. Saved and
    loaded now, the loaded bands equal the fit's exactly; a file without it says the delays
    count as known; a delay at its bound 0 is saved as known (zero rows)."""
    from mfmjax._analysis import saved_covariance

    model = _model()
    joint = np.zeros((5, 5))
    joint[:4, :4] = COV
    joint[4, 4], joint[0, 4], joint[4, 0] = 4e-3, 1e-3, 1e-3
    fit = types.SimpleNamespace(model=model, covariance=COV, joint_covariance=joint,
                                names=("a_0", "a_1", "b_10", "b_11"))
    mfmjax.save_model(model, tmp_path / "j.json", covariance=COV, joint_covariance=joint)
    back = mfmjax.load_model(tmp_path / "j.json")
    loaded = mfmjax.load_covariance(tmp_path / "j.json", joint=True)
    np.testing.assert_array_equal(loaded, joint)
    w = np.logspace(-1, 1, 7)
    for ours, theirs in ((mfmjax.frequency_response(back, w, covariance=loaded),
                          mfmjax.frequency_response(fit, w)),
                         (mfmjax.step_response(back, 5.0, covariance=loaded, n_points=60),
                          mfmjax.step_response(fit, 5.0, n_points=60))):
        for field in ("std", "phase_deg_std", "mag_db_std"):
            if hasattr(ours, field):
                np.testing.assert_array_equal(getattr(ours, field), getattr(theirs, field))
    cov, note = saved_covariance(tmp_path / "j.json", back)
    np.testing.assert_array_equal(cov, joint)
    assert note.endswith("the fitted delays' uncertainty included)"), note
    mfmjax.save_model(model, tmp_path / "p.json", covariance=COV)
    cov, note = saved_covariance(tmp_path / "p.json", back)
    np.testing.assert_array_equal(cov, COV)
    assert "the delays count as known: the file holds no covariance of them" in note, note
    assert mfmjax.load_covariance(tmp_path / "p.json", joint=True) is None
    bound = joint.copy()  # the delay fitted down to 0: inf / NaN, saved as known
    bound[4, :] = bound[:, 4] = np.nan
    bound[4, 4] = np.inf
    mfmjax.save_model(model, tmp_path / "b.json", covariance=COV, joint_covariance=bound)
    held = mfmjax.load_covariance(tmp_path / "b.json", joint=True)
    assert np.all(held[4] == 0) and np.all(held[:, 4] == 0)
    np.testing.assert_array_equal(held[:4, :4], COV)
    with pytest.raises(ValueError, match=r"save_model\(\): joint_covariance must be a \(5, 5\) "
                                         r"matrix ordered as \['a_0', 'a_1', 'b_10', 'b_11', "
                                         r"'delay u1'\]"):
        mfmjax.save_model(model, tmp_path / "x.json", joint_covariance=COV)
    # a hand-edited matrix that is no covariance (a correlation of 10): refused by file and
    # field at load (it reached step_response, whose error named neither)
    import json

    for key in ("covariance", "joint_covariance"):
        doc = json.loads((tmp_path / "j.json").read_text())
        doc[key]["matrix"][0][1] = doc[key]["matrix"][1][0] = 10 * math.sqrt(4e-3 * 3e-3)
        (tmp_path / "bad.json").write_text(json.dumps(doc))
        with pytest.raises(ValueError, match=rf"load_covariance\(\): .*bad.json: the {key} is "
                                             "not positive semidefinite"):
            mfmjax.load_covariance(tmp_path / "bad.json", joint=key == "joint_covariance")


def _is_png(path):
    data = open(path, "rb").read()
    assert data[:8] == PNG and len(data) > 10_000, (path, len(data))


def test_unstable_model_step_and_frequency_responses_warn_and_show_the_growth():
    """A model with a slow unstable pole (the DaISy dryer's estimate: -0.0147, -0.0071,
    +0.00055): the default step horizon was 7 time constants of the slowest stable pole (988
    s), where the response looked settled. Now both responses warn, and the horizon is 3
    e-folding times of the growing mode (3 / 0.00055 s), over which the response grows:
    its growing mode's share e^(0.00055 t) rises from e^0.6 at a fifth of the horizon to e^3."""
    poles = [-0.0147, -0.0071, 0.00055]
    model = Model.from_coefficients(np.poly(poles)[::-1], [[1e-4]])
    with pytest.warns(UserWarning, match=r"step_response\(\): the model is unstable \(poles "
                      r"with Re > 0: 0\.00055\)"):
        st = mfmjax.step_response(model)
    assert st.t[-1] == pytest.approx(3 / 0.00055, rel=1e-9)
    assert st.y[0, -1] > 10 * st.y[0, len(st.t) // 5] > 0
    with pytest.warns(UserWarning, match=r"frequency_response\(\): the model is unstable"):
        mfmjax.frequency_response(model)
    with warnings.catch_warnings():  # a stable model and an integrator (root 0) do not warn
        warnings.simplefilter("error")
        mfmjax.step_response(Model.from_coefficients([2.0, 3.0, 1.0], [[1.0]]))
        mfmjax.frequency_response(Model.from_coefficients([0.0, 3.0, 1.0], [[1.0]]))


def test_step_response_that_leaves_float64_raises_instead_of_flattening():
    """A pole at +1 over 400 s: e^t passes the simulation's 1e150 guard at t = 345 s, where
    the state was frozen and the curve came back flat at 5e149 up to t_final (1e4 s: a flat
    9e147), with the warning that the response grows without bound beside it. The overflow
    status now reaches `step_response`, which says to shorten t_final; 300 s stays below the
    guard (e^300 = 2e130) and equals e^t - 1 to rounding."""
    model = Model.from_coefficients([-1.0, 1.0], [[1.0]])
    for t_final in (400.0, 1e4):
        with pytest.warns(UserWarning, match="unstable"), pytest.raises(
                ValueError, match=r"step_response\(\): the response overflows float64 .*"
                                  r"shorter t_final"):
            mfmjax.step_response(model, t_final, n_points=500)
    with pytest.warns(UserWarning, match="unstable"):
        st = mfmjax.step_response(model, 300.0, n_points=500)
    # a_0 = -1: y = e^t - 1; 500 exact steps, each rounding a few ulp: 500 x 4 x 2.2e-16
    np.testing.assert_allclose(st.y[0], np.expm1(st.t), rtol=5e-13)


def test_state_space_exports_refuse_what_is_not_a_model():
    sig = mfmjax.Signals(np.zeros(100), np.ones((100, 1)), dt=0.1)
    for fn in (mfmjax.state_space, mfmjax.to_scipy, mfmjax.to_control):
        for bad in (sig, np.ones(3)):
            with pytest.raises(TypeError, match=rf"{fn.__name__}\(\): model must be a Model"):
                fn(bad)


def test_a_constant_output_has_no_fit_and_says_so():
    """compare and residuals on an output that does not move: the fit % is undefined. It was
    NaN with nothing said and the summary printed "fit nan %" (fit_percent refuses it)."""
    sig = record()
    flat = Signals(np.ones(sig.n_samples), sig.u, dt=DT, intersample=sig.intersample,
                   delays=sig.delays)
    with pytest.warns(UserWarning, match=r"compare\(\): the output is constant on the window, "
                      r"so the fit % is undefined") as got:
        cmp = mfmjax.compare(_model(), flat, window=(TAU, (T - 1) * DT))
    assert np.isnan(cmp.fit) and "fit undefined (constant output)" in cmp.summary()
    assert __file__ in [w.filename for w in got]
    with pytest.warns(UserWarning, match=r"residuals\(\): the output is constant"):
        res = mfmjax.residuals(_model(), flat, window=(TAU, (T - 1) * DT))
    assert "fit undefined (constant output)" in res.summary() and res.to_dict()["fit"] is None
