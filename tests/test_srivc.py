"""SRIVC (`mfmjax.srivc`) against its NumPy/SciPy twin (tests/reference_srivc.py).

Tolerances. The twin runs the filters as transfer functions (`lfilter`, direct form), whose
rounding error relative to the output is about $\\kappa\\,\\epsilon$ with
$\\kappa = \\sum|d_i| / |\\sum d_i|$ for the discrete denominator $d$ (its DC amplification);
mfmjax runs them as a state recursion (smaller error). A relative perturbation $\\delta$ of the
regressors moves the IV solution by at most $\\mathrm{cond}(\\hat\\Phi_{eq})\\,\\delta$, the
condition number of the column-equilibrated instrument matrix. Hence parameters agree to
$\\kappa\\,\\epsilon\\,\\mathrm{cond}(\\hat\\Phi_{eq})$, the covariance (an inverse of
$\\hat\\Phi^T\\hat\\Phi$) to that times $\\mathrm{cond}(\\hat\\Phi_{eq})$ once more. On noise-free
data the true parameters are an exact fixed point of the iteration (module docstring of
`mfmjax._srivc`), so recovery is to rounding: $\\epsilon\\,\\sqrt{T}\\,\\kappa\\,
\\mathrm{cond}(\\hat\\Phi_{eq})$ (rounding accumulated over T samples).
"""

import re
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import reference_srivc as ref
from jaxlog import compiles
from scipy import signal

import mfmjax
from mfmjax import Signals
from mfmjax._srivc import SrivcStatus

EPS = np.finfo(np.float64).eps
T, DT = 400, 0.1
MODES = ("foh", "zoh")
WHOLE = np.array([0.0, 3 * DT])  # whole-sample delays (the twin takes these)
LAGS = [0, 3]


def _theta(model):
    n = model.n
    parts = [np.asarray(model.a)[:n]] + [np.asarray(b) for b in model.b]
    if model.has_offset:
        parts.append(np.atleast_1d(np.asarray(model.offset)))
    return np.concatenate(parts)


def _bounds(theta, Phih, n=2):
    """kappa eps cond(Phi_hat_eq) and cond(Phi_hat_eq) at theta (see module docstring)."""
    a = np.append(theta[:n], 1.0)
    Ac = np.diag(np.ones(n - 1), 1)
    Ac[-1] = -a[:n]
    Ad = signal.cont2discrete((Ac, np.eye(n)[:, -1:], np.eye(n), np.zeros((n, 1))), DT)[0]
    d = np.poly(np.linalg.eigvals(Ad)).real
    kappa = np.sum(np.abs(d)) / abs(np.sum(d))
    cond = np.linalg.cond(Phih / np.linalg.norm(Phih, axis=0))
    return kappa * EPS * cond, cond


def _coefficients(scale=1.0):
    """n = 2, m = (1, 0): a foh and a zoh input, an offset; `scale` != 1 perturbs the truth."""
    return [0.8 * scale, 1.2 / scale, 1.0], [[0.5 * scale, 0.3], [0.7 / scale]], 0.2 * scale


def _record(delays=WHOLE, noise=0.1, seed=1, start_scale=1.1):
    """Exact response plus white noise (`noise` x std(y)); a start `start_scale` off the truth."""
    a, b, off = _coefficients()
    true = mfmjax.Model.from_coefficients(a, b, offset=off, delays=delays, intersample=MODES)
    rng = np.random.default_rng(seed)
    t = np.arange(T) * DT
    u = np.stack([np.sin(0.7 * t) + 0.5 * np.sin(1.9 * t + 1.0),
                  np.repeat(np.random.default_rng(0).normal(size=T // 20 + 1), 20)[:T]], axis=1)
    y = np.asarray(mfmjax.simulate(true, u, dt=DT))
    y = y + noise * np.std(y) * rng.standard_normal(T)
    sig = Signals(y, u, dt=DT, intersample=MODES, delays=delays, offset=True)
    a0, b0, off0 = _coefficients(start_scale)
    start = mfmjax.Model.from_coefficients(a0, b0, offset=off0, delays=delays, intersample=MODES)
    return true, sig, start


def _twin(sig, start, **kw):
    return ref.srivc(_theta(start), np.asarray(sig.y), np.asarray(sig.u), 2, (1, 0), MODES, DT,
                     lags=LAGS, has_offset=True, **kw)


def _twin_step(theta, sig, lags=LAGS):
    return ref.step(theta, np.asarray(sig.y), np.asarray(sig.u), 2, (1, 0), MODES, DT, lags, True)


@pytest.fixture(scope="module")
def noisy():
    _, sig, start = _record()
    return sig, start


def test_iterates_match_twin(noisy):
    """Same iterates: same count and stopping reason, same result, covariance and E."""
    sig, start = noisy
    fit = mfmjax.srivc(sig, start)
    want = _twin(sig, start)
    assert want["status"] == 0 and 2 < want["iterations"] < 30  # a real iteration, converged
    assert int(fit.status) == 0 and bool(fit.converged)
    assert int(fit.iterations) == want["iterations"]
    _, _, Ph = _twin_step(want["theta"], sig)
    tol, cond = _bounds(want["theta"], Ph)
    assert 1e-14 < tol < 1e-7  # an informative bound for this record
    assert np.max(np.abs(np.asarray(fit.theta) - want["theta"]) / np.abs(want["theta"])) <= tol
    assert np.allclose(np.asarray(fit.std_errors), want["std"], rtol=tol * cond, atol=0)
    assert float(fit.E) == pytest.approx(want["E"], rel=tol)
    assert fit.names == ("a_0", "a_1", "b_10", "b_11", "b_20", "offset")
    # the returned Model carries the parameters (a_n = 1) and simulates to the same E
    assert np.allclose(_theta(fit.model), want["theta"], rtol=tol, atol=0)
    y = mfmjax.simulate(fit.model, sig.u, dt=DT)
    assert float(jnp.sum((sig.y - y) ** 2) * DT) == pytest.approx(float(fit.E), rel=1e-9)


@pytest.mark.parametrize("m", [(0, 1), (1, 1)])
def test_numerator_orders_are_values(noisy, m):
    """Numerator orders of one n with the same largest m_k run the program of the fixture's
    m = (1, 0) (the orders are values in a zero-padded theta): nothing compiles, and the fit
    equals the twin's for that structure to the bound of the module docstring. (A feed-through
    m = (2, 1) is `test_many_structures_share_one_program`'s third structure.)"""
    sig, start = noisy
    mfmjax.srivc(sig, start)  # the (1, 0) program
    b = [[0.5, 0.3][: m[0] + 1], [0.7, 0.1][: m[1] + 1]]
    other = mfmjax.Model.from_coefficients([0.8 * 1.1, 1.2 / 1.1, 1.0], b, offset=0.2,
                                           delays=WHOLE, intersample=MODES)
    with compiles() as names:
        fit = mfmjax.srivc(sig, other)
    assert names == [], f"compiled for m={m}: {names}"
    want = ref.srivc(_theta(other), np.asarray(sig.y), np.asarray(sig.u), 2, m, MODES, DT,
                     lags=LAGS, has_offset=True)
    assert want["status"] == 0 and int(fit.status) == 0
    assert int(fit.iterations) == want["iterations"]
    _, _, Ph = ref.step(want["theta"], np.asarray(sig.y), np.asarray(sig.u), 2, m, MODES, DT,
                        LAGS, True)
    tol, cond = _bounds(want["theta"], Ph)
    assert 1e-14 < tol < 1e-7
    # norm-wise (the bound's own sense): the extra coefficients' true values are 0, so their
    # estimates are near zero and an elementwise relative error would measure nothing
    err = np.linalg.norm(np.asarray(fit.theta) - want["theta"]) / np.linalg.norm(want["theta"])
    assert err <= tol
    assert np.allclose(np.asarray(fit.std_errors), want["std"], rtol=tol * cond, atol=0)
    assert fit.model.m == m and len(fit.names) == 2 + sum(m) + 2 + 1


def test_first_iterates_match_twin(noisy):
    """After one and two IV solves (max_iter; the best iterate by simulation error is kept)."""
    sig, start = noisy
    for k in (1, 2):
        with pytest.warns(UserWarning, match="max_iter"):
            fit = mfmjax.srivc(sig, start, max_iter=k)
        want = _twin(sig, start, max_iter=k)
        assert want["status"] == ref.MAX_ITER and int(fit.status) == SrivcStatus.MAX_ITER
        assert int(fit.iterations) == k
        _, _, Ph = _twin_step(want["theta"], sig)
        tol, _ = _bounds(want["theta"], Ph)
        assert np.max(np.abs(np.asarray(fit.theta) - want["theta"]) / np.abs(want["theta"])) <= tol
    assert not np.allclose(want["theta"], _theta(start))  # the second one moved


@pytest.mark.parametrize("delays", [WHOLE, np.array([0.37 * DT, 2.6 * DT])])
def test_noise_free_recovers_truth(delays):
    """Whole and fractional delays, offset: the truth is an exact fixed point (rounding only)."""
    true, sig, start = _record(delays, noise=0.0)
    fit = mfmjax.srivc(sig, start)
    assert bool(fit.converged)
    _, _, Ph = _twin_step(_theta(true), sig, lags=np.round(delays / DT).astype(int))
    tol, _ = _bounds(_theta(true), Ph)
    err = np.max(np.abs(np.asarray(fit.theta) - _theta(true)) / np.abs(_theta(true)))
    assert err <= tol * np.sqrt(T)


def test_jit_equals_eager(noisy):
    sig, start = noisy
    eager = mfmjax.srivc(sig, start)
    jitted = jax.jit(lambda s, m: mfmjax.srivc(s, m))(sig, start)
    # same operations, separately compiled: rounding-level differences, bounded as in the twin
    assert np.allclose(np.asarray(jitted.theta), np.asarray(eager.theta), rtol=1e-10, atol=0)
    assert int(jitted.iterations) == int(eager.iterations)
    assert int(jitted.status) == int(eager.status)


def _stack(trees):
    return jax.tree.map(lambda *x: jnp.stack(x), *trees)


def test_vmap_equals_loop_and_no_recompilation():
    """A batch of records is one compiled call: a batch, then a new batch, compile nothing new;
    nor does a single fit on new data from a new start with new max_iter and tol."""
    recs = [_record(seed=s, start_scale=1.05 + 0.02 * s)[1:] for s in range(6)]
    loop = [mfmjax.srivc(s, m) for s, m in recs]
    batched = jax.vmap(lambda s, m: mfmjax.srivc(s, m))
    first = batched(_stack([r[0] for r in recs[:3]]), _stack([r[1] for r in recs[:3]]))
    for k in range(3):
        assert np.allclose(np.asarray(first.theta[k]), np.asarray(loop[k].theta), rtol=1e-10,
                           atol=0)
        assert int(first.iterations[k]) == int(loop[k].iterations)
        assert np.allclose(np.asarray(first.std_errors[k]), np.asarray(loop[k].std_errors),
                           rtol=1e-8, atol=0)
    _, new_sig, new_start = _record(seed=99, start_scale=0.93)
    with compiles() as names:
        second = batched(_stack([r[0] for r in recs[3:]]), _stack([r[1] for r in recs[3:]]))
        single = mfmjax.srivc(new_sig, new_start, max_iter=12, tol=1e-9)
    assert names == [], f"recompiled: {names}"
    assert np.allclose(np.asarray(second.theta[1]), np.asarray(loop[4].theta), rtol=1e-10, atol=0)
    assert bool(single.converged)


def test_mfm_start_and_srivc_in_one_vmapped_call():
    """A Monte Carlo study's pipeline at a known structure is one compiled call: the MFM
    estimate (`identify`) as the start and SRIVC from it, vmapped over stacked records. Each
    record's fit equals its own eager pipeline (separately compiled programs, the start
    included: rounding, 1e-10 as `test_jit_equals_eager`); a new batch compiles nothing."""
    st, mf = mfmjax.Structure(2, (1, 0)), mfmjax.ModulatingFunction(3, 4, 6.0)
    recs = [_record(seed=s)[1] for s in range(6)]

    def pipeline(sig):  # stacked delays are traced: their static bound
        return mfmjax.srivc(sig, mfmjax.identify(sig, st, mf, delay_max=float(WHOLE.max())))

    batched = jax.jit(jax.vmap(pipeline))
    stacks = _stack(recs[:3]), _stack(recs[3:])  # (stacking runs eager operations)
    with compiles() as names:
        first = batched(stacks[0])
    assert names == ["jit(pipeline)"], names  # one program, the MFM start included
    for k in range(3):
        own = mfmjax.srivc(recs[k], mfmjax.identify(recs[k], st, mf))
        assert bool(own.converged) and bool(first.converged[k])
        assert int(first.iterations[k]) == int(own.iterations)
        assert np.allclose(np.asarray(first.theta[k]), np.asarray(own.theta), rtol=1e-10, atol=0)
    with compiles() as names:
        second = batched(stacks[1])
    assert names == [], f"recompiled: {names}"
    assert bool(np.all(np.asarray(second.converged)))


def test_list_of_records_equals_one_at_a_time():
    """`srivc(list, starts)`: chunks of records on threads; each fit equals the direct fit of
    its record (another batch program on the same padded shape: rounding level, 1e-10 as in
    the vmap test); one start for all records or one per record; a fit that did not converge
    is counted in one warning; a bad list is refused at the boundary."""
    recs = [_record(seed=s, start_scale=1.05 + 0.02 * s)[1:] for s in range(10)]
    sigs, starts = [r[0] for r in recs], [r[1] for r in recs]
    loop = [mfmjax.srivc(s, m) for s, m in recs]
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # all converge: no warning
        fits = mfmjax.srivc(sigs, starts)
        shared = mfmjax.srivc(sigs, starts[0])
    assert len(fits) == len(shared) == 10
    for f, g, one in zip(fits, shared, loop):
        assert np.allclose(np.asarray(f.theta), np.asarray(one.theta), rtol=1e-10, atol=0)
        assert int(f.iterations) == int(one.iterations) and bool(f.converged)
        # from another start: the same fixed point, within the stopping tolerance (tol 1e-8)
        assert np.allclose(np.asarray(g.theta), np.asarray(one.theta), rtol=1e-8, atol=0)
    bad = mfmjax.Model.from_coefficients([-0.8, 1.2, 1.0], [[0.5, 0.3], [0.7]], offset=0.2,
                                         delays=WHOLE, intersample=MODES)  # a pole at s = +0.5
    with pytest.warns(UserWarning, match="1 of 3 fits stopped without converging \\(records \\[1\\]"):
        mixed = mfmjax.srivc(sigs[:3], [starts[0], bad, starts[2]])
    assert int(mixed[1].status) & SrivcStatus.UNSTABLE_FILTER and mixed[0].converged
    with pytest.raises(ValueError, match="srivc\\(\\): 3 records but 2 start models"):
        mfmjax.srivc(sigs[:3], starts[:2])
    # a record away from rest: warned as one record's call warns (the list said nothing)
    lifted = Signals(np.asarray(sigs[1].y) + 100.0, sigs[1].u, dt=DT, intersample=MODES,
                     offset=True)
    with pytest.warns(UserWarning, match=r"srivc\(\): 1 of 3 records do not start at rest "
                      r"\(records \[1\]; record 1: y starts at (99\.9|10\d\.)"):  # (not
        # converged: the start read from the first samples' line, 100 give or take the noise)
        mfmjax.srivc([sigs[0], lifted, sigs[2]], starts[:3])
    with pytest.warns(UserWarning, match=r"the filters start from rest at the first sample, "
                      r"and the signals do not \(y starts at (99\.9|10\d\.)"):
        mfmjax.srivc(lifted, starts[1])
    short = Signals(np.asarray(sigs[0].y)[:300], np.asarray(sigs[0].u)[:300], dt=DT,
                    intersample=MODES, offset=True)
    with pytest.raises(ValueError, match="srivc\\(\\): record 1 differs from record 0"):
        mfmjax.srivc([sigs[0], short], starts[0])
    with pytest.raises(ValueError, match="srivc\\(\\): the list of records is empty"):
        mfmjax.srivc([], starts[0])  # said so (it read "must be a Signals or a list ..., got list")


def test_unstable_start_gives_status_not_nan(noisy):
    sig, start = noisy
    bad = mfmjax.Model.from_coefficients([-0.8, 1.2, 1.0], [[0.5, 0.3], [0.7]], offset=0.2,
                                         delays=WHOLE, intersample=MODES)  # a pole at s = +0.5
    with pytest.warns(UserWarning, match="unstable_filter"):
        fit = mfmjax.srivc(sig, bad)
    assert int(fit.status) & SrivcStatus.UNSTABLE_FILTER and not bool(fit.converged)
    assert np.all(np.isfinite(np.asarray(fit.theta)))
    assert np.allclose(np.asarray(fit.theta), _theta(bad))  # the start, kept and flagged
    assert int(fit.model.status) & mfmjax.Status.UNSTABLE


def test_nonfinite_data_flagged(noisy):
    sig, start = noisy
    y = np.asarray(sig.y).copy()
    y[50] = np.nan
    # Signals() refuses NaN; data arriving inside a jit/vmap are not checked: the same here
    bad = eqx.tree_at(lambda s: s.y, sig, jnp.asarray(y))
    with pytest.warns(UserWarning, match="nonfinite"):
        fit = mfmjax.srivc(bad, start)
    assert int(fit.status) & SrivcStatus.NONFINITE and not bool(fit.converged)
    assert np.all(np.isfinite(np.asarray(fit.theta)))
    assert int(fit.model.status) & mfmjax.Status.NONFINITE  # the model said ok


def test_an_input_zero_throughout_is_no_excitation_not_nonfinite(noisy):
    """An all-zero input makes its filtered columns zero: the IV system is singular. The status
    says no_excitation (it said nonfinite) and the warning names the input and the fix; the
    start is returned."""
    sig, start = noisy
    u = np.asarray(sig.u).copy()
    u[:, 1] = 0.0
    bad = Signals(sig.y, u, dt=DT, intersample=MODES, delays=WHOLE, offset=True,
                  input_names=("valve", "burner"))
    with pytest.warns(UserWarning, match="no_excitation.*Input\\(s\\) 'burner' are zero over "
                                         "the whole record.*drop them"):
        fit = mfmjax.srivc(bad, start)
    assert int(fit.status) == SrivcStatus.NO_EXCITATION and not bool(fit.converged)
    assert fit.describe() == "no_excitation"
    assert np.allclose(np.asarray(fit.theta), _theta(start))  # the start, kept and flagged


def test_boundary_errors(noisy):
    sig, start = noisy
    with pytest.raises(TypeError, match="srivc\\(\\): signals must be a Signals"):
        mfmjax.srivc(np.zeros(10), start)
    with pytest.raises(TypeError, match="srivc\\(\\): model must be a Model"):
        mfmjax.srivc(sig, "model")
    one = mfmjax.Model.from_coefficients([1.0, 1.0], [[1.0]], offset=0.0)
    with pytest.raises(ValueError, match="srivc\\(\\): the model has 1 inputs but the signals "
                                         "have 2"):
        mfmjax.srivc(sig, one)
    with pytest.raises(ValueError, match="srivc\\(\\): max_iter"):
        mfmjax.srivc(sig, start, max_iter=0)
    with pytest.raises(ValueError, match="srivc\\(\\): tol"):
        mfmjax.srivc(sig, start, tol=-1.0)
    with pytest.raises(ValueError, match="srivc\\(\\): tol.*stopped at the second iterate"):
        mfmjax.srivc(sig, start, tol=2.0)  # a relative change: it stopped, "converged"
    short = Signals(np.asarray(sig.y)[:5], np.asarray(sig.u)[:5], dt=DT, intersample=MODES,
                    offset=True)
    with pytest.raises(ValueError, match="srivc\\(\\): the record needs more samples"):
        mfmjax.srivc(short, start)
    plain = Signals(sig.y, sig.u, dt=DT, intersample=MODES)
    with pytest.raises(ValueError, match="srivc\\(\\): model.has_offset=True"):
        mfmjax.srivc(plain, start)


def test_many_structures_share_one_program():
    """`srivc_many` (estimate's SRIVC stage) pads every structure to one order: nine pairs of
    three structures (n = 1 and 2, m_k from 0 to 2) run as one chunk of `BATCH` pairs and one
    single pair; the single pair is the program a direct n = 2 fit uses, so after the direct
    fits only the chunk compiles, once. Each result equals the direct fit of its pair (same
    operations on zero-padded arrays: rounding-level differences, 1e-10 as in the jit test)."""
    from mfmjax._batch import BATCH
    from mfmjax._srivc import srivc_many

    structures = [([0.5, 1.0], [[0.3], [0.6]]), ([0.8, 1.2, 1.0], [[0.5], [0.7]]),
                  ([0.8, 1.2, 1.0], [[0.5, 0.3, 0.1], [0.7, 0.2]])]
    recs, starts = [], []
    for seed in (3, 4, 5):
        sig = _record(seed=seed)[1]
        for a, b in structures:
            recs.append(sig)
            starts.append(mfmjax.Model.from_coefficients(a, b, offset=0.2, delays=WHOLE,
                                                         intersample=MODES))
    assert len(recs) == BATCH + 1
    with warnings.catch_warnings():  # some structures stop at max_iter: compared as they are
        warnings.simplefilter("ignore")
        direct = [mfmjax.srivc(s, m) for s, m in zip(recs, starts)]
    with compiles() as names:
        many = srivc_many(recs, starts, n_max=2)
    assert names == ["jit(_mapped)"], names
    for d, f in zip(direct, many):
        assert f.model.n == d.model.n and f.model.m == d.model.m and f.names == d.names
        assert int(f.status) == int(d.status) and int(f.iterations) == int(d.iterations)
        np.testing.assert_allclose(np.asarray(f.theta), np.asarray(d.theta), rtol=1e-10)
        np.testing.assert_allclose(np.asarray(f.std_errors), np.asarray(d.std_errors),
                                   rtol=1e-8)



def test_srivc_refuses_signals_without_inputs():
    """An autonomous record (K = 0) has no input to instrument: refused by name with the
    alternative (it raised an internal TypeError)."""
    y = np.exp(-0.2 * np.arange(400) * 0.05) * np.cos(np.arange(400) * 0.05)
    sig = Signals(y, dt=0.05, offset=False)
    start = mfmjax.Model.from_coefficients([2.5, 0.3, 1.0])
    with pytest.raises(ValueError, match=r"srivc\(\): the signals have no input.*output_error"):
        mfmjax.srivc(sig, start)


def test_at_rest_coloured_noise_and_rules_are_said_as_they_are():
    """From an audit of 2026-11-28. (1) A record at rest whose input steps at the first
    sample: its output rises within the 10 samples the not-at-rest test averaged, which it
    compared with zero: warned on 22 of 30 PRBS records, with advice that broke the fit. The
    test compares them with the fit's own response from rest now: no warning there, while a
    record with a nonzero initial state is still warned. (2) Coloured noise (AR(1), pole
    0.95): standard errors 2.1-2.8x too small, status ok, unsaid; warned now (the residuals
    from rest fail Box-Pierce at 1 %). (3) A zoh start on records whose rule was not declared
    (foh by default): a = [4.2, 5.7] for [2, 3], converged, unsaid; the rules' mismatch is
    warned now."""
    dt, T = 0.2, 1500
    true = mfmjax.Model.from_coefficients([2.0, 3.0, 1.0], [[1.0, 0.3]], intersample="zoh")
    start = mfmjax.Model.from_coefficients([2.4, 2.6, 1.0], [[1.1, 0.4]], intersample="zoh")
    rng = np.random.default_rng(3)
    u = np.repeat(rng.choice([-1.0, 1.0], T // 50), 50)
    u[:50] = 1.0  # a step at the first sample
    clean = np.asarray(mfmjax.simulate(true, u[:, None], dt=dt))
    white = clean + 0.1 * np.std(clean) * rng.standard_normal(T)
    assert abs(np.mean(white[:10])) > 0.1 * np.ptp(white)  # what the old test called moving
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # at rest, white noise: nothing to say
        fit = mfmjax.srivc(Signals(white, u, dt=dt, intersample="zoh", offset=False), start)
    assert bool(fit.converged)
    moved = np.asarray(mfmjax.simulate(true, u[:, None], [0.0, 3.0], dt=dt))
    with pytest.warns(UserWarning, match=r"the signals do not \(y starts .* away from the "
                                         r"model's response from rest"):
        mfmjax.srivc(Signals(moved + white - clean, u, dt=dt, intersample="zoh", offset=False),
                     start)
    e = np.zeros(T)
    for k in range(1, T):  # AR(1) noise, pole 0.95, as the audit's
        e[k] = 0.95 * e[k - 1] + rng.standard_normal()
    coloured = clean + 0.1 * np.std(clean) * e / np.std(e)
    with pytest.warns(UserWarning, match=r"srivc\(\): the residuals are not white .* the "
                                         r"standard errors assume white noise"):
        mfmjax.srivc(Signals(coloured, u, dt=dt, intersample="zoh", offset=False), start)
    with pytest.warns(UserWarning, match=r"srivc\(\): the fit uses the signals' intersample "
                                         r"rules \['foh'\], not the start model's \['zoh'\]"):
        mfmjax.srivc(Signals(white, u, dt=dt, offset=False), start)
    # a fit that did not converge: its best iterate's response from rest said "not at rest" of
    # 3 of 6 such records at rest (a review); its first samples are judged instead
    far = mfmjax.Model.from_coefficients([400.0, 40.0, 1.0], [[400.0]], intersample="zoh")
    plant = mfmjax.Model.from_coefficients([2.0, 3.0, 1.0], [[2.0]], intersample="zoh")
    for seed in range(6):
        r = np.random.default_rng(seed)
        v = np.repeat(r.choice([-1.0, 1.0], 80), 5)
        y = np.asarray(mfmjax.simulate(plant, v[:, None], dt=0.1))
        y = y + 0.1 * np.std(y) * r.standard_normal(400)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            fit = mfmjax.srivc(Signals(y, v, dt=0.1, intersample="zoh", offset=False), far,
                               max_iter=1)
        assert not bool(fit.converged)
        assert not any("start from rest" in str(w.message) for w in caught), seed
        # at 10 dB, a first noise sample of 2 standard deviations: y[0] alone beyond 0.1 of
        # the range said "not at rest" of 3 of 30 records at rest (an audit); the start is
        # read from the first samples' line now, beyond 3 of its standard errors
        x = np.asarray(mfmjax.simulate(plant, v[:, None], dt=0.1))
        sd = np.sqrt(np.var(x) / 10.0)
        y = x + sd * r.standard_normal(400)
        y[0] = 2.0 * sd
        assert abs(y[0]) > 0.1 * np.ptp(y)  # what the first-sample test called away
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            mfmjax.srivc(Signals(y, v, dt=0.1, intersample="zoh", offset=False), far,
                         max_iter=1)
        assert not any("start from rest" in str(w.message) for w in caught), seed


def test_warning_says_to_shift_a_record_that_starts_away_from_rest():
    """A fit that did not converge on a record whose output starts far from zero (an operating
    point: the filters start from rest, so the record opens with a start-up transient) names
    the shift `estimate` applies; on a record that starts at rest the warning does not."""
    _, sig, start = _record()
    level = Signals(np.asarray(sig.y) + 50.0, sig.u, dt=DT, intersample=MODES,
                    delays=WHOLE, offset=True)
    with pytest.warns(UserWarning, match=r"y starts at (49|50)\.\d+ .*shift the record by its "
                      r"first samples"):
        mfmjax.srivc(level, start, max_iter=1)
    # converged and away from rest: an input at a level of 100 (the output at rest, an offset
    # term) converges to a = [5.8, 7.6, 1] for [2, 3, 1], status ok, and nothing was said
    t = np.arange(3000) * 0.05
    u = sum(a * np.sin(w * t + p) for a, w, p in ((0.8, 0.3, 1.0), (0.5, 1.1, 2.0),
                                                    (0.4, 0.07, 0.5)))
    true = mfmjax.Model.from_coefficients([2.0, 3.0, 1.0], [[2.0, 0.5]], offset=0.0)
    y = np.asarray(mfmjax.simulate(true, u[:, None], [0.3, -0.2], dt=0.05))
    lifted = Signals(y, u + 100.0, dt=0.05, offset=True)
    begin = mfmjax.Model.from_coefficients([2.2, 2.7, 1.0], [[1.8, 0.6]], offset=0.05 - 180.0)
    with pytest.warns(UserWarning, match=r"srivc\(\): the filters start from rest at the first "
                      r"sample, and the signals do not \(u1 starts at 10\d\.\d+") as got:
        fit = mfmjax.srivc(lifted, begin)
    assert bool(fit.converged) and len(got) == 1
    assert np.max(np.abs(np.asarray(fit.model.a) - [2.0, 3.0, 1.0])) > 0.1  # the bias said
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        stopped = mfmjax.srivc(sig, start, max_iter=1)
    assert len(caught) == 1 and "shift the record" not in str(caught[0].message)
    # where the user looks: the fit's summary says it did not converge (`model.summary()`,
    # the only summary there was, printed "status ok"), a converged one says so too
    assert re.search(r"^status\s+ok$", stopped.model.summary(), re.M)
    text = stopped.summary()
    assert "NOT CONVERGED (max_iter after 1 iterations): the estimate is the best iterate" in text
    for name, v in zip(stopped.names, np.asarray(stopped.theta)):
        assert f"{name:<12}{v:>16.6e}" in text
    done = mfmjax.srivc(sig, start)
    assert bool(done.converged)
    assert f"converged after {int(done.iterations)} iterations" in done.summary()
    with pytest.raises(ValueError, match="one fit at a time"):
        jax.tree.map(lambda x: np.stack([x, x]), done).summary()  # as jax.vmap stacks
