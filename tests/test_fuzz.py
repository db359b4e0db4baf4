"""Property-based fuzzing of every public name in `mfmjax.__all__` (hypothesis).

The property, for random valid and invalid arguments: the call either raises a clear
ValueError/TypeError (for the library's own boundary checks: the message names the function),
or returns a result that is finite, or whose non-finite values are flagged by a non-zero
status. Never a NaN with status ok, never another exception type.

`FUZZ` maps each public name to the test that fuzzes it; `test_registry_covers_all` fails when
a name is added to `__all__` without a fuzz test. Shapes are fixed per test (small arrays) so
that each jitted program compiles once; example counts are small (the file runs in well under
a minute of fuzzing on top of the compiles).
"""

from __future__ import annotations

import functools
import math
import os
import warnings

import numpy as np
from hypothesis import HealthCheck, assume, example, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

import mfmjax
from mfmjax import ModulatingFunction, Signals, Structure
from mfmjax._pytree import replace_fields

FUZZ: dict[str, object] = {}  # public name -> the test that fuzzes it


def fuzzes(*names):
    def register(test):
        for name in names:
            FUZZ[name] = test
        return test
    return register


FAST = settings(max_examples=15, deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much])
FEW = settings(FAST, max_examples=4)

DT = 0.05
T = 200

# junk and edge values for any scalar argument
junk = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True, width=64),
    st.integers(-3, 30),
    st.booleans(),
    st.none(),
    st.text(max_size=3),
    st.just([]),
    st.just([1.0, 2.0]),
)
any_float = st.floats(allow_nan=True, allow_infinity=True, width=64)
finite = st.floats(-1e3, 1e3, allow_nan=False)


def _clear(err: Exception, labels) -> None:
    msg = str(err)
    assert msg and "\n" not in msg.strip() and len(msg) < 800, msg
    if labels:
        assert any(lab in msg for lab in labels), f"{msg!r} names none of {labels}"


def outcome(call, labels=()):
    """(True, result) or (False, error) for a clear ValueError/TypeError; anything else fails."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            return True, call()
        except (ValueError, TypeError) as err:
            _clear(err, labels)
            return False, err


def _floats(x):
    leaves = []
    for leaf in _leaves(x):
        a = np.asarray(leaf)
        if a.dtype.kind in "fc":
            leaves.append(a)
    return leaves


def _leaves(x):
    import jax

    return jax.tree_util.tree_leaves(x)


def honest(result, status=None, skip=()) -> None:
    """Finite floats everywhere (except fields in `skip`), unless `status` flags a problem."""
    if status is not None and int(np.max(np.asarray(status))) != 0:
        return
    for a in _floats(result):
        if any(a is np.asarray(s) for s in skip):
            continue
        assert np.all(np.isfinite(a)), "non-finite value with status ok"


def honest_model(model) -> None:
    st_ = int(np.max(np.asarray(model.status)))
    if st_ != 0:
        return
    for arr in (model.a, *model.b, model.offset, model.delays, model.theta):
        assert np.all(np.isfinite(np.asarray(arr))), "non-finite parameter with status ok"
    if model.mf is not None:  # identified: the diagnostics are computed, so finite
        assert math.isfinite(float(model.J)) and math.isfinite(float(model.J_rel))


# -- shared data (one shape each, built once) -------------------------------------------------


@functools.cache
def plant():
    return mfmjax.Model.from_coefficients([2.0, 3.0, 1.0], [[1.0]])


@functools.cache
def record() -> Signals:
    t = np.arange(T) * DT
    u = np.sin(t) + np.sign(np.sin(0.7 * t))
    rng = np.random.default_rng(0)
    y = np.asarray(mfmjax.simulate(plant(), u, dt=DT)) + 1e-3 * rng.standard_normal(T)
    return Signals(y, u, dt=DT)


@functools.cache
def fitted():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return mfmjax.identify(record(), Structure(2, 0), ModulatingFunction(3, 3, 2.0))


@functools.cache
def searched():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return mfmjax.search(record(), n=(1, 2), N=3, M=3, h=2.0)


def model_strategy():
    """n = 2, one input: stable, unstable or NaN coefficients."""
    return st.builds(lambda a0, a1, b0: (a0, a1, b0), any_float, any_float, finite)


# -- data containers and orders -----------------------------------------------------------------


@fuzzes("Signals")
@FAST
@given(y=st.one_of(arrays(np.float64, st.sampled_from([1, 2, 10]), elements=any_float),
                   arrays(np.bool_, 10), st.text(max_size=4), st.just([[1.0, 2.0]])),
       dt=junk, t0=junk)
def test_fuzz_signals(y, dt, t0):
    ok, sig = outcome(lambda: Signals(y, dt=dt, t0=t0), ["Signals()"])
    if ok:
        assert np.all(np.isfinite(np.asarray(sig.y))) and sig.dt > 0
        assert math.isfinite(sig.dt) and math.isfinite(sig.t0)
        assert np.all(np.isfinite(np.asarray(sig.t)))


@fuzzes("Structure")
@FAST
@given(n=junk, m=st.one_of(junk, st.lists(junk, max_size=3)))
def test_fuzz_structure(n, m):
    ok, s = outcome(lambda: Structure(n, m), ["Structure()"])
    if ok:
        assert isinstance(s.n, int) and s.n >= 1
        assert all(isinstance(mk, int) and 0 <= mk <= s.n for mk in s.m)


@fuzzes("ModulatingFunction", "phi", "phi_integral", "phi_scaled")
@FAST
@given(N=st.one_of(junk, st.integers(1, 8)), M=st.one_of(junk, st.integers(1, 8)),
       h=st.one_of(junk, st.floats(0.1, 5.0)), t=finite, i=st.integers(0, 3))
def test_fuzz_modulating_function(N, M, h, t, i):
    ok, mf = outcome(lambda: ModulatingFunction(N, M, h), ["ModulatingFunction()"])
    if not ok:
        return
    assert math.isfinite(float(mf.h)) and float(mf.h) > 0
    for value in (mfmjax.phi(t, mf, i), mfmjax.phi_integral(0.0, t, mf, i),
                  mfmjax.phi_scaled(t / float(mf.h), mf.N, mf.M, i)):
        v = float(value)
        # phi^(i) ~ h^(N+M-i) (N+M)^i: may overflow only for huge h; finite in this range
        assert math.isfinite(v)


@fuzzes("kernel_weights")
@FAST
@given(h=st.floats(0.1, 2.0), i=st.integers(0, 2), rule=st.sampled_from(["zoh", "foh", "cubic",
                                                                         "simpson"]),
       delay=st.floats(0.0, 1.0))
def test_fuzz_kernel_weights(h, i, rule, delay):
    mf = ModulatingFunction(3, 3, h)
    length = 64
    ok, w = outcome(lambda: mfmjax.kernel_weights(mf, i, DT, rule, delay, length),
                    ["kernel_weights()"])
    if ok:
        assert np.all(np.isfinite(np.asarray(w)))
    else:
        assert rule == "simpson"


@fuzzes("Model", "StateSpace", "state_space", "to_scipy", "to_control")
@FAST
@given(coef=model_strategy(), offset=st.one_of(st.none(), any_float))
def test_fuzz_model_and_state_space(coef, offset):
    a0, a1, b0 = coef
    ok, model = outcome(lambda: mfmjax.Model.from_coefficients([a0, a1, 1.0], [[b0]],
                                                               offset=offset),
                        ["Model.from_coefficients()", "Structure()"])
    if not ok:
        assert not all(math.isfinite(v) for v in (a0, a1)) or (
            offset is not None and not math.isfinite(offset))
        return
    honest_model(model)
    ss = mfmjax.state_space(model)
    assert isinstance(ss, mfmjax.StateSpace)
    honest(ss)
    sp = mfmjax.to_scipy(model)
    A, B, C, D = (np.asarray(v) for v in (sp.A, sp.B, sp.C, sp.D))
    assert all(np.all(np.isfinite(v)) for v in (A, B, C, D))
    try:
        sys = mfmjax.to_control(model)
    except ImportError as err:  # python-control is optional: the message says how to get it
        assert "pip install control" in str(err)
    else:
        assert np.all(np.isfinite(np.asarray(sys.A)))


# -- identification -------------------------------------------------------------------------------


@fuzzes("identify", "modulated_signals", "gram")
@settings(FAST, max_examples=8)
@given(n=st.integers(1, 2), N=st.integers(2, 6), M=st.integers(2, 6),
       h=st.one_of(st.floats(2 * DT, 3.0), st.floats(0.0, 2 * DT), any_float),
       eta=st.one_of(st.none(), st.just("nan")))
@example(n=2, N=3, M=3, h=0.06, eta=None)  # h below 2 samples: refused
def test_fuzz_identify(n, N, M, h, eta):
    assume(N >= n and M >= n)
    sig = record()
    p = n + 1 + 1
    eta_v = None if eta is None else np.r_[np.ones(p - 1), np.nan]
    ok, model = outcome(
        lambda: mfmjax.identify(sig, Structure(n, 0), ModulatingFunction(N, M, h), eta=eta_v),
        ["identify()", "ModulatingFunction()"])
    if not ok:
        return
    honest_model(model)
    ms = mfmjax.modulated_signals(sig, Structure(n, 0), ModulatingFunction(N, M, h))
    G = np.asarray(mfmjax.gram(ms))
    assert np.all(np.isfinite(G)) and np.allclose(G, G.T, rtol=1e-12, atol=0)


@fuzzes("closed_form", "constrained_solve")
@FAST
@given(A=arrays(np.float64, (4, 4), elements=st.floats(-10, 10)),
       eta=arrays(np.float64, 4, elements=st.floats(0.5, 2.0)),
       active=arrays(np.bool_, 4))
def test_fuzz_solves(A, eta, active):
    G = A @ A.T + 1e-3 * np.eye(4)  # symmetric positive definite, cond <= ~4e5 * ...
    theta = np.asarray(mfmjax.closed_form(G, eta))
    assert np.all(np.isfinite(theta))
    assert abs(eta @ theta - 1.0) < 1e-6  # the constraint of eq. (11) holds
    out = mfmjax.constrained_solve(G, eta, np.ones(4, bool) if not active.any() else active)
    leaves = out if isinstance(out, tuple) else (out,)
    theta2 = np.asarray(leaves[0])
    assert np.all(np.isfinite(theta2))
    ok, _ = outcome(lambda: mfmjax.closed_form(G, eta[:3]))  # mismatched: a TypeError/ValueError
    assert not ok


@fuzzes("search", "SearchResult")
@FEW
@given(n=st.one_of(st.just((1, 2)), junk), h=st.one_of(st.just(2.0), junk),
       i=st.one_of(st.integers(-2, 5), junk))
@example(n=(1, 2), h=2.0, i=0)
def test_fuzz_search(n, h, i):
    sig = record()
    ok, res = outcome(lambda: mfmjax.search(sig, n=n, N=3, M=3, h=h), ["search()"])
    if not ok:
        return
    assert isinstance(res, mfmjax.SearchResult)
    for r in range(len(res)):
        row = res.row(r)
        if row["status"] == "ok":
            assert row["E"] is not None and row["J"] is not None
    ok, model = outcome(lambda: res.best(i), ["best()"])
    if ok:
        honest_model(model)


@fuzzes("scores")
@FAST
@given(h=st.one_of(st.floats(0.2, 3.0), junk), N=st.sampled_from([2.0, 3.0, 4.5]),
       validate=st.one_of(st.none(), st.just((0.0, 5.0)), junk))
def test_fuzz_scores(h, N, validate):
    sig = record()
    ok, out = outcome(lambda: mfmjax.scores(sig, Structure(2, 0), h=h, N=N, M=3.0,
                                            validate=validate, h_max=3.0),
                      ["scores()", "ModulatingFunction()"])
    if ok:
        honest({k: out[k] for k in ("J", "J_rel", "E", "fit")}, out["status"])


@fuzzes("refine", "Refinement")
@FEW
@given(vary=st.one_of(st.just(("h",)), st.sampled_from(["h", ("h", "x"), ()]), junk),
       max_steps=st.one_of(st.just(0), junk),
       bounds=st.one_of(st.none(), st.just({"h": (1.0, 3.0)}), st.just({"h": (math.nan, 3.0)}),
                        st.just({"h": 2.0})))
@example(vary=("h",), max_steps=0, bounds={"h": (1.0, 3.0)})  # 0 steps: compiles less
def test_fuzz_refine(vary, max_steps, bounds):
    ok, ref = outcome(lambda: mfmjax.refine(record(), fitted(), vary=vary, max_steps=max_steps,
                                            bounds=bounds), ["refine()"])
    if ok:
        assert isinstance(ref, mfmjax.Refinement)
        honest_model(ref.model)
        assert np.all(np.isfinite(ref.path[:1]))


@fuzzes("output_error", "OutputErrorFit", "cramer_rao")
@FEW
@given(window=st.one_of(st.none(), junk),
       max_steps=st.one_of(st.just(3), junk), sigma=st.one_of(st.floats(1e-3, 1.0), junk),
       fit_delays=st.one_of(st.just(False), junk))
@example(window=None, max_steps=3, sigma=0.1, fit_delays=False)
def test_fuzz_output_error(window, max_steps, sigma, fit_delays):
    sig = record()
    ok, oe = outcome(lambda: mfmjax.output_error(sig, fitted(), window=window,
                                                 max_steps=max_steps, fit_delays=fit_delays),
                     ["output_error()"])
    if ok:
        assert isinstance(oe, mfmjax.OutputErrorFit)
        honest_model(oe.model)
    x0 = np.zeros(2)
    ok, cr = outcome(lambda: mfmjax.cramer_rao(fitted(), np.asarray(sig.u), x0, dt=DT,
                                               sigma=sigma), ["cramer_rao()"])
    if ok:
        names, std = cr
        assert len(names) == np.asarray(std).size and np.all(np.isfinite(std))


@fuzzes("srivc", "SrivcFit")
@FEW
@given(max_iter=st.one_of(st.just(3), junk), tol=st.one_of(st.just(1e-8), junk))
@example(max_iter=3, tol=1e-8)
def test_fuzz_srivc(max_iter, tol):
    ok, fit = outcome(lambda: mfmjax.srivc(record(), fitted(), max_iter=max_iter, tol=tol),
                      ["srivc()"])
    if ok:
        assert isinstance(fit, mfmjax.SrivcFit)
        honest_model(fit.model)


@fuzzes("estimate", "Estimate")
@FEW
@given(h=st.one_of(st.just(2.0), junk), polish=st.one_of(st.booleans(), junk),
       max_iter=st.one_of(st.just(5), junk))
@example(h=2.0, polish=False, max_iter=5)
def test_fuzz_estimate(h, polish, max_iter):
    ok, est = outcome(lambda: mfmjax.estimate(record(), h=h, n=(1, 2), N=3, M=3, polish=polish,
                                              max_iter=max_iter),
                      ["estimate()", "search()", "srivc()"])
    if ok:
        assert isinstance(est, mfmjax.Estimate)
        honest_model(est.model)
        if est.converged:
            assert np.all(np.isfinite(est.std_errors))


@fuzzes("estimate_outputs")
@FEW
@given(records=st.one_of(st.just("two"), st.just("mismatch"), junk))
@example(records="two")
def test_fuzz_estimate_outputs(records):
    sig = record()
    renamed = replace_fields(sig, output_name="y2")  # one name twice is refused
    arg = {"two": [sig, renamed], "mismatch": [sig, Signals(sig.y[:-5], sig.u[:-5], dt=DT)]}.get(
        records, records) if isinstance(records, str) else records
    ok, out = outcome(lambda: mfmjax.estimate_outputs(arg, h=2.0, n=(1, 2), N=3, M=3),
                      ["estimate_outputs()", "estimate()", "search()"])
    if ok:
        assert len(out) == 2 and all(isinstance(e, mfmjax.Estimate) for e in out)
        for e in out:
            honest_model(e.model)


# -- simulation and observers ---------------------------------------------------------------------


@fuzzes("simulate")
@FAST
@given(coef=model_strategy(), u=arrays(np.float64, 30, elements=any_float),
       dt=st.one_of(st.just(DT), junk))
def test_fuzz_simulate(coef, u, dt):
    a0, a1, b0 = coef
    assume(math.isfinite(a0) and math.isfinite(a1))
    model = mfmjax.Model.from_coefficients([a0, a1, 1.0], [[b0]])
    ok, y = outcome(lambda: mfmjax.simulate(model, u, dt=dt), ["simulate()"])
    if ok:
        assert np.all(np.isfinite(np.asarray(y)))


windows = st.one_of(st.none(), st.sampled_from([(0.0, 3.0), (1.0, 4.0), (0.0, 0.1)]), junk)


@fuzzes("observe", "Observation", "initial_state", "final_state", "performance_index")
@FAST
@given(window=windows, which=st.sampled_from(["observe", "initial_state", "final_state",
                                               "performance_index"]))
def test_fuzz_observers(window, which):
    fn = getattr(mfmjax, which)
    ok, out = outcome(lambda: fn(plant(), record(), window), [f"{which}()", "observe()"])
    if not ok:
        return
    if which == "observe":
        assert isinstance(out, mfmjax.Observation)
        honest(out, out.status)
    else:  # the single-value wrappers raise for a flagged window, so a value is finite
        assert np.all(np.isfinite(np.asarray(out)))


@fuzzes("compare", "Comparison", "residuals", "Residuals")
@FEW
@given(window=windows, lags=st.one_of(st.integers(-1, 60), junk))
def test_fuzz_analysis(window, lags):
    ok, cmp = outcome(lambda: mfmjax.compare(plant(), record(), window),
                      ["compare()", "observe()"])
    if ok:
        assert isinstance(cmp, mfmjax.Comparison) and np.all(np.isfinite(cmp.y_sim))
    ok, res = outcome(lambda: mfmjax.residuals(plant(), record(), window, lags=lags),
                      ["residuals()", "observe()"])
    if ok:
        assert isinstance(res, mfmjax.Residuals) and isinstance(res.white, bool)
        assert np.all(np.isfinite(res.auto)) and np.all(np.isfinite(res.cross))


@fuzzes("step_response", "StepResponse", "frequency_response", "FrequencyResponse")
@FEW
@given(coef=model_strategy(), var=st.one_of(st.floats(0.0, 1.0), junk))
def test_fuzz_responses(coef, var):
    a0, a1, b0 = coef
    ok, model = outcome(lambda: mfmjax.Model.from_coefficients([a0, a1, 1.0], [[b0]]),
                        ["Model.from_coefficients()"])
    if not ok:
        return
    cov = var * np.eye(3) if isinstance(var, float) and math.isfinite(var) else var
    ok, step = outcome(lambda: mfmjax.step_response(model, covariance=cov),
                       ["step_response()"])
    if ok:
        assert np.all(np.isfinite(step.y)) and (step.std is None or np.all(np.isfinite(step.std)))
    ok, fr = outcome(lambda: mfmjax.frequency_response(model, covariance=cov),
                     ["frequency_response()"])
    if ok:
        assert np.all(np.isfinite(fr.mag_db)) and np.all(np.isfinite(fr.phase_deg))


@fuzzes("moving_final_states")
@FAST
@given(T_ob=st.one_of(st.just(2.0), junk),
       times=st.one_of(st.lists(st.floats(0.0, 12.0), min_size=1, max_size=3),
                       st.lists(any_float, max_size=3), junk))
def test_fuzz_moving_final_states(T_ob, times):
    ok, x = outcome(lambda: mfmjax.moving_final_states(plant(), record(), T_ob, times),
                    ["moving_final_states()"])
    if ok:
        assert np.all(np.isfinite(np.asarray(x)))


@fuzzes("fit_percent")
@FAST
@given(y=arrays(np.float64, st.sampled_from([1, 8]), elements=any_float),
       y_sim=arrays(np.float64, 8, elements=any_float))
def test_fuzz_fit_percent(y, y_sim):
    ok, fit = outcome(lambda: mfmjax.fit_percent(y, y_sim), ["fit_percent()"])
    if ok:
        v = float(fit)
        assert math.isfinite(v)  # finite inputs, y not constant: finite (no overflow)


@fuzzes("detrend", "Trend")
@FEW
@given(kind=st.one_of(st.sampled_from(["linear", "constant"]), junk),
       offset=st.one_of(st.booleans(), junk))
def test_fuzz_detrend(kind, offset):
    ok, res = outcome(lambda: mfmjax.detrend(record(), kind, offset=offset), ["detrend()"])
    if ok:
        sig, trend = res
        assert isinstance(trend, mfmjax.Trend) and sig.offset == offset
        honest((sig, trend))
        honest(trend.apply(record().window(1.0, 5.0)))
        assert np.all(np.isfinite(np.asarray(trend.restore(sig.t, sig.y))))


@fuzzes("resample")
@FAST
@given(t=arrays(np.float64, 12, elements=st.one_of(st.floats(0.0, 5.0), any_float)),
       dt=st.one_of(st.floats(0.01, 2.0), junk),
       rule=st.one_of(st.sampled_from(["zoh", "foh"]), junk),
       output_rule=st.one_of(st.sampled_from(["linear", "cubic"]), junk))
def test_fuzz_resample(t, dt, rule, output_rule):
    y, u = np.sin(np.arange(12.0)), np.cos(np.arange(12.0))
    for t_ in (t, np.sort(t)):
        ok, sig = outcome(lambda t_=t_: mfmjax.resample(t_, y, u, dt=dt, intersample=rule,
                                                        output_rule=output_rule),
                          ["resample()", "Signals()"])
        if ok:
            honest(sig)
            assert sig.dt == float(dt) and sig.n_samples >= 2


# -- status, files, caches, data sets -------------------------------------------------------------


@fuzzes("Status")
@FAST
@given(code=st.integers(0, 2**16))
def test_fuzz_status(code):
    from mfmjax._status import describe

    text = describe(code)
    assert isinstance(text, str) and text
    assert (text == "ok") == (code == 0)
    assert int(mfmjax.Status(code)) == code


@fuzzes("save_model", "load_model", "load_covariance")
@FAST
@given(cut=st.integers(0, 400), flip=st.integers(0, 400))
def test_fuzz_model_files(tmp_path_factory, cut, flip):
    from mfmjax._output_error import free_parameters

    path = tmp_path_factory.mktemp("fuzz") / "model.json"
    k = len(free_parameters(fitted())[0])
    mfmjax.save_model(fitted(), path, covariance=np.eye(k))
    raw = path.read_bytes()
    back = mfmjax.load_model(path)
    np.testing.assert_array_equal(np.asarray(back.a), np.asarray(fitted().a))
    np.testing.assert_array_equal(mfmjax.load_covariance(path), np.eye(k))
    damaged = bytearray(raw[: min(cut, len(raw))] if cut < len(raw) else raw)
    if damaged and flip < len(damaged):
        damaged[flip] ^= 0x5A
    path.write_bytes(bytes(damaged))
    ok, model = outcome(lambda: mfmjax.load_model(path), ["load_model()"])
    if ok:  # a flip that still parses must still give a valid model
        honest_model(model)
    ok, cov = outcome(lambda: mfmjax.load_covariance(path), ["load_model()",
                                                             "load_covariance()"])
    if ok and cov is not None:  # the free parameters' covariance, finite
        n = len(free_parameters(mfmjax.load_model(path))[0])
        assert cov.shape == (n, n) and np.all(np.isfinite(cov))


@fuzzes("enable_compile_cache")
@FAST
@given(size=junk)
def test_fuzz_enable_compile_cache(size):
    # invalid sizes are refused before anything changes; with the opt-out set nothing changes
    old = os.environ.get("MFMJAX_NO_COMPILE_CACHE")
    os.environ["MFMJAX_NO_COMPILE_CACHE"] = "1"
    try:
        assert mfmjax.enable_compile_cache("/nonexistent/never", max_size_bytes=size) is None
    finally:
        if old is None:
            del os.environ["MFMJAX_NO_COMPILE_CACHE"]
        else:
            os.environ["MFMJAX_NO_COMPILE_CACHE"] = old
    if not (isinstance(size, int) and not isinstance(size, bool) and size > 0):
        os.environ.pop("MFMJAX_NO_COMPILE_CACHE", None)
        try:
            ok, _ = outcome(lambda: mfmjax.enable_compile_cache("/nonexistent/never",
                                                                max_size_bytes=size),
                            ["enable_compile_cache()"])
            assert not ok
        finally:
            if old is not None:
                os.environ["MFMJAX_NO_COMPILE_CACHE"] = old


@fuzzes("datasets")
@FAST
@given(seed=st.integers(0, 2**32 - 1), noise=st.floats(0.0, 1.0),
       name=st.one_of(st.text(max_size=4), st.none(), st.integers()), pull=any_float)
def test_fuzz_datasets(seed, noise, name, pull):
    # one record shape (compiled once); junk values of these generators are not fuzzed here
    t, y, u, _ = mfmjax.datasets.switching_experiment(
        interval=50, n_intervals=3, quiet=(0,), switches=(1,), noise_std=noise, seed=seed)
    assert np.all(np.isfinite(y)) and np.all(np.isfinite(u)) and y.shape == t.shape
    ok, _ = outcome(lambda: mfmjax.datasets.daisy(name), ["daisy()"])
    assert not ok  # no such record
    ok, d = outcome(lambda: mfmjax.datasets.transport_delay(pull), ["transport_delay()"])
    if ok and math.isfinite(pull) and pull > 0:
        assert math.isfinite(float(np.asarray(d)))


# -- the on-line identifier -----------------------------------------------------------------------


@fuzzes("OnlineConfig")
@FAST
@given(dt=st.one_of(st.just(1.0), junk), interval=st.one_of(st.just(16.0), junk),
       h=st.one_of(st.just((8.0,)), junk), N=st.one_of(st.just(3), junk),
       eta=st.one_of(st.none(), junk), output_rule=st.one_of(st.just("cubic"), junk))
def test_fuzz_online_config(dt, interval, h, N, eta, output_rule):
    ok, cfg = outcome(lambda: mfmjax.OnlineConfig(
        dt=dt, n_inputs=1, interval=interval, n_start=4, n_reident=4, T_obfin=16.0,
        T_obinit=32.0, n=(2,), m=[(0,)], h=h, N=N, M=3, eta=eta, output_rule=output_rule),
        ["OnlineConfig()"])
    if ok:
        assert all(math.isfinite(v) and v >= 2 * cfg.dt for v in cfg.h)
        assert cfg.eta is None or len(cfg.eta) == 2 + 1 + 1 + 1


@functools.cache
def _online_config():
    # tr_corr = 1 skips identification (|corr| < 1): the fuzz exercises the stream handling
    return mfmjax.OnlineConfig(dt=1.0, n_inputs=2, interval=16.0, n_start=4, n_reident=4,
                               T_obfin=16.0, T_obinit=32.0, n=(2,), h=(8.0,), N=3, M=3,
                               tr_corr=1.0)


chunk = st.tuples(st.integers(0, 40),  # gap before the chunk (samples)
                  st.integers(0, 30),  # chunk length
                  st.sampled_from(["ok", "transposed", "3d", "nan", "bool", "flat"]))


@fuzzes("online", "OnlineIdentifier", "OnlineState", "OnlineOutputs")
@FAST
@given(chunks=st.lists(chunk, min_size=1, max_size=6), jump=st.sampled_from([0, 10**8]))
def test_fuzz_online_stream(chunks, jump):
    cfg = _online_config()
    ident = mfmjax.OnlineIdentifier(cfg)
    state = mfmjax.online.init(cfg)
    assert isinstance(state, mfmjax.OnlineState)
    rng = np.random.default_rng(len(chunks))
    nxt = 0
    for k, (gap, P, kind) in enumerate(chunks):
        start = nxt + gap + (jump if k == len(chunks) - 1 else 0)
        t = start + np.arange(P, dtype=np.float64)
        y = rng.standard_normal(P)
        u = rng.standard_normal((P, 2))
        if kind == "transposed":
            u = u.T
        elif kind == "3d":
            u = u[..., None]
        elif kind == "nan" and P:
            y[P // 2] = np.nan
        elif kind == "bool":
            y = y > 0
        elif kind == "flat":
            u = u.reshape(-1)
        ok, res = outcome(lambda: mfmjax.online.update(state, t, y, u), ["update()"])
        ok2, out2 = outcome(lambda: ident.update(t, y, u), ["update()"])
        assert ok == ok2
        if not ok:
            assert kind in ("transposed", "3d", "bool", "flat")
            continue
        state, out = res
        assert isinstance(out, mfmjax.OnlineOutputs)
        S = cfg.samples
        assert out.t.shape == out.y.shape == out.y_pred.shape == out.model_number.shape
        assert out.t.size % S == 0 and np.all(np.isnan(out.y_pred[out.model_number == 0]))
        assert state.buf_y.shape == (cfg.buffer,)  # memory bounded by the buffer
        nxt = start + P
    assert int(state.n_seen) == int(ident.state.n_seen)


def test_registry_covers_all():
    """Every public name has a fuzz test, and every registered test is collected."""
    missing = sorted(set(mfmjax.__all__) - set(FUZZ))
    assert not missing, f"public names without a fuzz test: {missing}"
    assert not sorted(set(FUZZ) - set(mfmjax.__all__)), "registry names a non-public name"
    here = globals()
    for test in FUZZ.values():
        assert test.__name__.startswith("test_") and here[test.__name__] is test
