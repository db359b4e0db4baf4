"""Issue 16, library half: every bad argument listed in the issue gets a clear ValueError or
TypeError naming the function, the argument, the value and the fix (not a raw exception, not a
silent wrong answer); on-line gaps and first-window outliers are handled as documented."""

import math
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import mfmjax
from mfmjax import Model, ModulatingFunction, OnlineConfig, Signals, Structure
from mfmjax._online import OUTLIER_Z, spike_scores

DT = 0.05
NAN, INF = float("nan"), float("inf")


@pytest.fixture(scope="module")
def data():
    model = mfmjax.Model.from_coefficients([2.0, 3.0, 1.0], [[1.0]])
    t = np.arange(400) * DT
    u = np.sin(t) + np.sign(np.sin(0.7 * t))
    y = np.asarray(mfmjax.simulate(model, u, dt=DT))
    return model, Signals(y, u, dt=DT)


@pytest.fixture(scope="module")
def fitted(data):
    _, sig = data
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return mfmjax.identify(sig, Structure(2, 0), ModulatingFunction(3, 3, 4.0))


# -- Signals, Structure, identify ------------------------------------------------------------


@pytest.mark.parametrize("kw,err,match", [
    (dict(y=np.ones(20) > 0, dt=DT), TypeError, r"Signals\(\): y is a bool array"),
    (dict(y=np.ones(20), dt=True), TypeError, r"Signals\(\): dt must be a number, got bool"),
    (dict(y=np.ones(20), dt=DT, t0=NAN), ValueError, r"Signals\(\): t0 must be a finite number"),
    (dict(y=np.ones(20), dt="0.1"), TypeError, r"dt must be a number, got str"),
    (dict(y="1,2,3", dt=DT), TypeError, r"y must be an array of numbers, got the string"),
    (dict(y=np.ones(1), dt=DT), ValueError, r"y has 1 sample\(s\); a record needs at least 2"),
    (dict(y=np.ones(20), u=np.ones(20, dtype=bool), dt=DT), TypeError, r"u is a bool array"),
])
def test_signals_refuses(kw, err, match):
    with pytest.raises(err, match=match):
        Signals(**kw)


@pytest.mark.parametrize("b,names,match", [
    # a flat b was read as that many inputs of order 0 (a 2-input model from [1.0, 0.5])
    ([1.0, 0.5], None, r"b must list each input's coefficients .* \(got \[1.0, 0.5\]\); for one "
                       r"input write b=\[\[b_0, b_1, ...\]\]"),
    (np.array([1.0, 0.5]), None, r"b must list each input's coefficients"),
    ([[1.0], 2.0], None, r"b must list each input's coefficients"),
    # names of another length were accepted, and failed later inside python-control
    ([[1.0, 0.5]], ["q", "p"], r"input_names needs one name per input \(1; got \['q', 'p'\]\)"),
])
def test_model_from_coefficients_refuses(b, names, match):
    with pytest.raises(ValueError, match=r"Model.from_coefficients\(\): " + match):
        mfmjax.Model.from_coefficients([2.0, 3.0, 1.0], b, input_names=names)
    assert mfmjax.Model.from_coefficients([2.0, 3.0, 1.0], np.array([[1.0, 0.5]])).m == (1,)


def test_model_labels_and_coefficients_are_checked_where_they_are_given():
    """A model audit (2026-11-28): b as a generator was used up by the checks and gave a
    model of no inputs; `labelled` took any names (a 2-input model named ['only'] plotted,
    saved, and its file was refused by load_model), and a string became one name per
    character; an a_n so small that a / a_n overflowed gave a = [inf, 1] with status ok."""
    two = mfmjax.Model.from_coefficients([2.0, 3.0, 1.0], (r for r in [[1.0, 0.5], [0.8]]))
    assert two.n_inputs == 2 and two.m == (1, 0)
    for names, err, match in ((["only"], ValueError, r"input_names needs one name per input "
                                                     r"\(2; got \['only'\]\)"),
                              (["a", "b", "c"], ValueError, r"input_names needs one name"),
                              ("pq", TypeError, r"input_names must be a list of strings, one "
                                                r"per input, not the string 'pq'"),
                              ([1, 2], TypeError, r"input_names must be strings \(got \[1, 2\]\)"),
                              ((s for s in "pq"), None, None)):
        if err is None:  # a generator of names: read once (they came back empty)
            assert two.labelled("z", names).input_names == ("p", "q")
            continue
        with pytest.raises(err, match=r"Model.labelled\(\): " + match):
            two.labelled("z", names)
    with pytest.raises(TypeError, match=r"Model.labelled\(\): output_name must be a string"):
        two.labelled(5, ["a", "b"])
    assert two.labelled("z", ["a", "b"]).input_names == ("a", "b")
    with pytest.raises(TypeError, match=r"from_coefficients\(\): input_names must be a list"):
        mfmjax.Model.from_coefficients([2.0, 3.0, 1.0], [[1.0], [2.0]], input_names="ab")
    with pytest.raises(ValueError, match=r"from_coefficients\(\): a_n = 1e-300 is so small "
                                         r"that the coefficients divided by it .* overflow"):
        mfmjax.Model.from_coefficients([1e10, 1e-300], [[1.0]])


@pytest.mark.parametrize("a,b,delays,name", [  # a bool was read as 1.0 or 0.0
    ([True, 3.0, 1.0], [[1.0]], None, "a"),
    ([2.0, 3.0, 1.0], [[1.0], [True, 0.5]], None, r"b\[1\]"),
    ([2.0, 3.0, 1.0], [[1.0]], [np.bool_(True)], "delays"),
])
def test_model_from_coefficients_refuses_bools(a, b, delays, name):
    with pytest.raises(TypeError, match=rf"Model.from_coefficients\(\): {name} holds a bool; "
                                        "give numbers"):
        mfmjax.Model.from_coefficients(a, b, delays=delays)
    with pytest.raises(TypeError, match=r"b must be a sequence of per-input coefficient lists, "
                                        r"got float; for one input write b=\[\[b_0"):
        mfmjax.Model.from_coefficients(a, 1.0)


@pytest.mark.parametrize("args,err,match", [
    ((2.5,), ValueError, r"Structure\(\): n must be an integer \(got n=2.5\)"),
    ((NAN,), ValueError, r"n must be a finite number \(got n=nan\)"),
    ((True,), TypeError, r"n must be a number, got bool"),
    ((2, [0.5]), ValueError, r"m\[0\] must be an integer"),
    ((2, "1"), TypeError, r"m must be a number or a sequence of numbers, got the string"),
])
def test_structure_refuses(args, err, match):
    with pytest.raises(err, match=match):
        Structure(*args)


def test_identify_h_below_two_samples(data):
    _, sig = data
    with pytest.raises(ValueError, match=r"identify\(\): mf.h=0.075 is shorter than 2 sampling "
                                         r"intervals.*h must cover at least 2 samples"):
        mfmjax.identify(sig, Structure(2, 0), ModulatingFunction(3, 3, 1.5 * DT))


def test_identify_eta_nan(data):
    _, sig = data
    with pytest.raises(ValueError, match=r"identify\(\): eta has a NaN or inf value"):
        mfmjax.identify(sig, Structure(2, 0), ModulatingFunction(3, 3, 4.0),
                        eta=[1.0, NAN, 1.0, 1.0])
    # all zeros: eta^T theta = 1 has no solution (every search candidate came back flagged,
    # the cause unsaid)
    for fn, call in [("identify", lambda: mfmjax.identify(
            sig, Structure(2, 0), ModulatingFunction(3, 3, 4.0), eta=[0.0] * 4)),
            ("search", lambda: mfmjax.search(sig, n=(2,), N=(3,), M=(3,), h=(4.0,),
                                             eta=np.zeros(4)))]:
        with pytest.raises(ValueError, match=rf"{fn}\(\): eta is all zeros"):
            call()


# -- search, best, refine, output_error, scores ----------------------------------------------


@pytest.mark.parametrize("kw,err,match", [
    (dict(n=2.5, h=4.0), ValueError, r"search\(\): n must be an integer \(got n=2.5\)"),
    (dict(n=2, h="4"), TypeError, r"search\(\): h must be a number or a sequence of numbers, "
                                  "got the string"),
    (dict(n=2, h=[4.0, NAN]), ValueError, r"h\[1\] must be a finite number"),
    (dict(n=2, h=1.5 * DT), ValueError, r"h=0.075 is shorter than 2 sampling intervals"),
    (dict(n=2, h=4.0, N=True), TypeError, r"N must be a number, got bool"),
    (dict(n=2, h=4.0, validate=NAN), TypeError, r"validate must be a pair \(start, end\)"),
    (dict(n=2, h=4.0, validate=(0.0, INF)), ValueError, r"validate\[1\] must be a finite"),
    (dict(n=2, h=4.0, validate=(1.0,)), ValueError, r"got 1 value\(s\)"),
    (dict(n=2, h=4.0, observer_window=NAN), ValueError, r"observer_window must be > 0"),
    (dict(n=2, h=4.0, chunk_size=2.5), ValueError, r"chunk_size must be an integer"),
])
def test_search_refuses(data, kw, err, match):
    _, sig = data
    with pytest.raises(err, match=match):
        mfmjax.search(sig, **kw)


def test_best_out_of_range(data):
    _, sig = data
    res = mfmjax.search(sig, n=2, N=3, M=3, h=4.0)
    assert res.best(len(res) - 1).n == 2
    with pytest.raises(ValueError, match=rf"best\(\): i must be an integer in \[0, "
                                         rf"{len(res) - 1}\] \(got i=999\)"):
        res.best(999)
    with pytest.raises(TypeError, match=r"best\(\): i must be a number, got str"):
        res.best("0")
    # row() checks its rank as best() does (row(-1) came back labelled rank 0)
    with pytest.raises(ValueError, match=rf"row\(\): i must be an integer in \[0, "
                                         rf"{len(res) - 1}\] \(got i=-1\)"):
        res.row(-1)
    assert res.row(0)["J_raw"] == float(res.best(0).J) and res.row(0)["J"] == float(res.best(0).J_rel)


@pytest.mark.parametrize("kw,err,match", [
    (dict(vary="h"), TypeError, r"refine\(\): vary must be a sequence of names, not the string "
                                r"'h'; write vary=\('h',\)"),
    (dict(vary=("h", "q")), ValueError, r"unknown vary entry 'q'"),
    (dict(vary=("h",), bounds={"h": (NAN, 5.0)}), ValueError,
     r"bounds\['h'\] lo has a NaN or inf value; give finite bounds"),
    (dict(vary=("h",), bounds={"h": 5.0}), ValueError, r"bounds\['h'\] must be a pair"),
    (dict(vary=("h",), max_steps=-1), ValueError, r"max_steps must be an integer >= 0 "
                                                  r"\(got max_steps=-1\)"),
    (dict(vary=("h",), rtol=NAN), ValueError, r"rtol must be > 0 and finite"),
    (dict(vary=("h",), validate=3.0), TypeError, r"validate must be a pair"),
])
def test_refine_refuses(data, fitted, kw, err, match):
    _, sig = data
    with pytest.raises(err, match=match):
        mfmjax.refine(sig, fitted, **kw)


@pytest.mark.parametrize("kw,err,match", [
    (dict(max_steps=-1), ValueError, r"output_error\(\): max_steps must be an integer >= 0"),
    (dict(window=(0.0, NAN)), ValueError, r"window\[1\] must be a finite number"),
    (dict(window=2.0), TypeError, r"window must be a pair"),
])
def test_output_error_refuses(data, fitted, kw, err, match):
    _, sig = data
    with pytest.raises(err, match=match):
        mfmjax.output_error(sig, fitted, **kw)


@pytest.mark.parametrize("kw,err,match", [
    (dict(h=NAN, N=3, M=3), ValueError, r"scores\(\): h must be > 0 and finite"),
    (dict(h="4", N=3, M=3), TypeError, r"scores\(\): h must be a number, got str"),
    (dict(h=4.0, N=3, M=3, validate=(INF, 5.0)), ValueError, r"validate\[0\] must be a finite"),
])
def test_scores_refuses(data, kw, err, match):
    _, sig = data
    with pytest.raises(err, match=match):
        mfmjax.scores(sig, Structure(2, 0), **kw)


# -- observers, simulate ------------------------------------------------------------------------


@pytest.mark.parametrize("window,err,match", [
    (NAN, TypeError, r"observe\(\): window must be a pair \(start, end\) of times, got float"),
    (3.0, TypeError, r"window must be a pair"),
    ((1.0,), ValueError, r"window must be a pair \(start, end\) of times, got 1 value"),
    ((0.0, NAN), ValueError, r"window\[1\] must be a finite number \(got window\[1\]=nan\)"),
    ((0.0, INF), ValueError, r"window\[1\] must be a finite number"),
    ((5.0, 1.0), ValueError, r"window must have start < end"),
])
def test_observe_window_refuses(data, window, err, match):
    model, sig = data
    with pytest.raises(err, match=match):
        mfmjax.observe(model, sig, window)


def test_moving_final_states_refuses(data):
    model, sig = data
    with pytest.raises(ValueError, match=r"moving_final_states\(\): T_ob must be > 0"):
        mfmjax.moving_final_states(model, sig, NAN, [10.0])
    with pytest.raises(ValueError, match=r"times has a NaN or inf value"):
        mfmjax.moving_final_states(model, sig, 5.0, [NAN])
    # which t_j, and what T_ob asked (they named neither: an audit of the README's claim)
    end = (sig.n_samples - 1) * DT
    with pytest.raises(ValueError, match=r"every t_j must have T_ob of data before it inside "
                                         r"the record \[0, .*\]: t_j = 3 \(times\[1\]\) has less "
                                         r"than T_ob = 5 before it; the earliest is 5"):
        mfmjax.moving_final_states(model, sig, 5.0, [10.0, 3.0])
    with pytest.raises(ValueError, match=rf"t_j = {end + 1:g} \(times\[0\]\) lies after its end"):
        mfmjax.moving_final_states(model, sig, 5.0, [end + 1])
    # a T_ob longer than the record: it named an "earliest" t_j past the record's end
    with pytest.raises(ValueError, match=r"has less than T_ob = .* before it; T_ob is longer "
                                         r"than the record"):
        mfmjax.moving_final_states(model, sig, end + 50.0, [end])
    # a window that rounds to one sample: it said "must lie inside the record with start <
    # end", which it did (an audit)
    with pytest.raises(ValueError, match=r"observe\(\): window \(10, 10\.004\) rounds to one "
                                         r"sample \(t = 10: the ends are read at the nearest "
                                         r"samples"):
        mfmjax.observe(model, sig, (10.0, 10.004))
    with pytest.raises(ValueError, match=r"need at least .* \(T_ob = 0.1: each window ends at its "
                                         r"t_j\)"):
        mfmjax.moving_final_states(model, sig, 0.1, [15.0])


def test_fit_percent_of_constant_output_is_undefined():
    with pytest.raises(ValueError, match=r"fit_percent\(\): the fit of a constant output y is "
                                         "undefined"):
        mfmjax.fit_percent(np.ones(10), np.zeros(10))
    assert mfmjax.fit_percent(np.arange(4.0), np.arange(4.0)) == 100.0
    # a concrete 0-d JAX array is a number ("must be a real number, got ArrayImpl" before)
    one = mfmjax.Model.from_coefficients([1.0, 1.0], [[1.0]])
    np.testing.assert_array_equal(np.asarray(mfmjax.simulate(one, np.ones((5, 1)),
                                                             dt=jnp.asarray(0.05))),
                                  np.asarray(mfmjax.simulate(one, np.ones((5, 1)), dt=0.05)))
    # a diverged simulation: not "remove or interpolate non-finite samples" (the data's advice)
    with pytest.raises(ValueError, match=r"fit_percent\(\): y_sim has a NaN or inf at sample 2: "
                                         "the simulation did not stay finite"):
        mfmjax.fit_percent(np.arange(4.0), np.array([0.0, 1.0, np.inf, np.nan]))


@pytest.mark.parametrize("bad,match", [
    (NAN, r"simulate\(\): u has a NaN or inf value at index \(7,\)"),
    (INF, r"simulate\(\): u has a NaN or inf value"),
    (1e300, r"simulate\(\): the response overflows float64 \(largest \|u\| or \|x0\| = 1e\+300"),
])
def test_simulate_refuses_bad_inputs(data, bad, match):
    model, _ = data
    u = np.ones(40)
    u[7] = bad
    with pytest.raises(ValueError, match=match):
        mfmjax.simulate(model, u, dt=DT)


def test_simulate_unstable_model_names_the_poles():
    unstable = mfmjax.Model.from_coefficients([-2.0, -1.0, 1.0], [[1.0]])  # poles 2 and -1
    with pytest.raises(ValueError, match=r"model is unstable \(poles with positive real part: "
                                         r"2\)"):
        mfmjax.simulate(unstable, np.ones(5000), dt=0.1)


def test_simulate_refuses_bool_dt_and_transposed_u(data):
    model, _ = data
    with pytest.raises(TypeError, match=r"simulate\(\): dt must be a number, got bool"):
        mfmjax.simulate(model, np.ones(10), dt=True)
    with pytest.raises(ValueError, match=r"u must have shape \(T, 1\).*transpose it"):
        mfmjax.simulate(model, np.ones((1, 10)), dt=DT)


# -- x64 ----------------------------------------------------------------------------------------


def test_every_entry_refuses_float32_mode(data, fitted):
    model, sig = data
    mf = ModulatingFunction(3, 3, 4.0)
    calls = {
        "Signals": lambda: Signals(np.ones(10), dt=1.0),
        "simulate": lambda: mfmjax.simulate(model, np.ones(10), dt=DT),
        "observe": lambda: mfmjax.observe(model, sig),
        "identify": lambda: mfmjax.identify(sig, Structure(2, 0), mf),
        "search": lambda: mfmjax.search(sig, n=2, h=4.0),
        "refine": lambda: mfmjax.refine(sig, fitted),
        "output_error": lambda: mfmjax.output_error(sig, fitted),
        "scores": lambda: mfmjax.scores(sig, Structure(2, 0), h=4.0, N=3, M=3),
        "OnlineConfig": lambda: OnlineConfig(dt=1.0, n_inputs=1),
    }
    jax.config.update("jax_enable_x64", False)
    try:
        for name, call in calls.items():
            with pytest.raises(RuntimeError, match=rf"{name}\(\): JAX float64 mode is off.*"
                                                   r'jax.config.update\("jax_enable_x64", True\)'):
                call()
    finally:
        jax.config.update("jax_enable_x64", True)


# -- the on-line identifier -------------------------------------------------------------------


@pytest.mark.parametrize("kw,err,match", [
    (dict(h=NAN), ValueError, r"OnlineConfig\(\): h must be > 0 and finite \(got h=nan\)"),
    (dict(h=(50.0, 1.0)), ValueError, r"h=1 is shorter than 2 sampling intervals"),
    (dict(N=0.5), ValueError, r"OnlineConfig\(\): N must be an integer \(got N=0.5\)"),
    (dict(n=[]), ValueError, r"OnlineConfig\(\): the n grid is empty"),
    (dict(n=[0]), ValueError, r"OnlineConfig\(\): n\[0\] must be an integer >= 1"),
    (dict(output_rule="quartic"), ValueError, r"unknown output_rule 'quartic'; use one of"),
    (dict(eta=[1.0, 1.0, 1.0]), ValueError, r"eta must have one entry per parameter of the "
                                            r"largest candidate \(9: .*got 3"),
    (dict(interval=1e9), ValueError, r"sample buffer would hold 8e\+09 samples.*GiB"),
    (dict(interval=NAN), ValueError, r"interval must be > 0 and finite"),
    (dict(dt=True), TypeError, r"dt must be a number, got bool"),
    (dict(n_start=2.5), ValueError, r"n_start must be an integer"),
    (dict(N=(1,), M=(1,)), ValueError, r"every candidate has N < n or M < n"),
])
def test_online_config_refuses(kw, err, match):
    with pytest.raises(err, match=match):
        OnlineConfig(**{"dt": 1.0, "n_inputs": 2, **kw})


def test_online_config_accepts_a_matching_eta():
    cfg = OnlineConfig(dt=1.0, n_inputs=2, eta=np.ones(9))  # n_max 3 + 1, 2 x (1 + 1), offset
    assert cfg.eta == (1.0,) * 9


def _small_config():
    return OnlineConfig(dt=1.0, n_inputs=2, n=(2,), intersample=("foh", "zoh"))


def test_update_refuses_transposed_and_3d_u():
    state = mfmjax.online.init(_small_config())
    t = np.arange(5.0)
    with pytest.raises(ValueError, match=r"need u \(P, 2\) = \(5, 2\).*got shape \(2, 5\); "
                                         r"transpose it"):
        mfmjax.online.update(state, t, np.zeros(5), np.zeros((2, 5)))
    with pytest.raises(ValueError, match=r"update\(\): u must be 0-D or 1-D or 2-D, got shape"):
        mfmjax.online.update(state, t, np.zeros(5), np.zeros((5, 2, 1)))
    with pytest.raises(ValueError, match=r"need u \(P, 2\) = \(5, 2\)"):
        mfmjax.online.update(state, t, np.zeros(5), np.zeros(10))  # flat: refused, not reshaped
    with pytest.raises(TypeError, match=r"update\(\): y is a bool array"):
        mfmjax.online.update(state, t, np.zeros(5) > 0, np.zeros((5, 2)))
    # one sample with K inputs may be given flat: (K,) is unambiguous when P = 1
    state, _ = mfmjax.online.update(state, [0.0], [1.0], [2.0, 3.0])
    assert state.buf_u[0].tolist() == [2.0, 3.0]


def test_gap_longer_than_buffer_resets_history():
    cfg = _small_config()
    state = mfmjax.online.init(cfg)
    rng = np.random.default_rng(0)
    state, _ = mfmjax.online.update(state, np.arange(300.0), rng.standard_normal(300),
                                    rng.standard_normal((300, 2)))
    late = 300.0 + 1e8
    state, out = mfmjax.online.update(state, [late], [0.5], [[0.1, 0.2]])
    # the partial interval closes, then ONE event covers the whole gap (not 400,000 of them)
    assert [e["interval"] for e in out.events] == [1, 2]
    gap = out.events[1]
    assert gap["action"].startswith("gap:") and "buffered history reset" in gap["action"]
    S = cfg.samples
    assert gap["gap_intervals"] == int(late) // S - 2
    assert out.t.shape == (S,)  # only the interval that really closed is emitted
    assert state.buf_y.shape == (cfg.buffer,) and int(state.n_seen) == int(late) + 1
    assert int(state.n_closed) == int(late) // S
    assert np.count_nonzero(np.isfinite(state.buf_y)) == 1  # only the new sample survives
    assert not np.any(state.iv)  # the interval statistics were reset with the buffer
    # the stream goes on normally after the jump
    t = late + 1 + np.arange(2 * S)
    state, out = mfmjax.online.update(state, t, np.zeros(t.size), np.zeros((t.size, 2)))
    assert len(out.events) == 2 and not any(e["action"].startswith("gap") for e in out.events)


def test_gap_within_the_buffer_is_filled_with_nan():
    cfg = _small_config()
    state = mfmjax.online.init(cfg)
    state, _ = mfmjax.online.update(state, np.arange(10.0), np.zeros(10), np.zeros((10, 2)))
    state, out = mfmjax.online.update(state, [10.0 + 3 * cfg.samples], [0.0], [[0.0, 0.0]])
    assert len(out.events) == 3 and all(not e["valid"] for e in out.events)
    assert not any(e["action"].startswith("gap") for e in out.events)


def test_spike_scores_rule():
    x = np.linspace(0.0, 1.0, 200)
    rng = np.random.default_rng(1)
    smooth = {
        "step": np.where(x < 0.5, 0.0, 10.0),
        "ramp": 3.0 * x,
        "sine, 25 samples per period": np.sin(2 * np.pi * 8 * x),
        "noisy step": np.where(x < 0.3, 1.0, 2.0) + 0.01 * rng.standard_normal(200),
        "exponential transient": np.where(x < 0.4, 0.0, 1 - np.exp(-(x - 0.4) * 40)),
    }
    for name, sig in smooth.items():
        assert spike_scores(sig).max() < OUTLIER_Z, name
    for name, sig in smooth.items():
        spiked = sig.copy()
        spiked[100] += 500.0
        z = spike_scores(spiked)
        assert int(np.argmax(z)) == 100 and z[100] > OUTLIER_Z, name
    # a NaN leaves only the samples whose 11-sample window holds it unscored (it zeroed the
    # whole signal); scales from another history (`scale_from`)
    gap = smooth["noisy step"].copy()
    gap[40], gap[120] = np.nan, gap[120] + 500.0
    z = spike_scores(gap)
    assert np.all(z[35:46] == 0) and z[120] > OUTLIER_Z
    assert spike_scores(smooth["ramp"], np.concatenate([smooth["ramp"], [np.nan]])).max() < OUTLIER_Z


def test_first_window_with_a_spike_is_refused():
    t, y, u, _ = mfmjax.datasets.switching_experiment()
    S = 250
    y = y.copy()
    y[1000] += 500.0  # a 500 degC spike inside the first identification window (0 .. 8 S)
    ident = mfmjax.OnlineIdentifier(_small_config())
    n = 8 * S
    for c0 in range(0, n, 500):
        ident.update(t[c0: c0 + 500], y[c0: c0 + 500], u[c0: c0 + 500])
    first = ident.events[7]  # where the clean run adopts its first model (test_online)
    assert first["action"].startswith("refused: outlier in the identification window")
    assert "t = 1000" in first["action"] and not ident.models
    assert math.isnan(float(ident.state.model["op_time"]))


def test_low_level_entries_refuse_float32_mode(data):
    """The building blocks in `__all__` check x64 too (the test above covers the main verbs)."""
    model, sig = data
    mf = ModulatingFunction(3, 3, 4.0)
    G = np.eye(3)
    calls = {
        "phi": lambda: mfmjax.phi(0.5, mf), "phi_scaled": lambda: mfmjax.phi_scaled(0.5, 3, 3, 0),
        "phi_integral": lambda: mfmjax.phi_integral(0.0, 1.0, mf),
        "kernel_weights": lambda: mfmjax.kernel_weights(mf, 0, DT, "foh", 0.0, 100),
        "modulated_signals": lambda: mfmjax.modulated_signals(sig, Structure(2, 0), mf),
        "closed_form": lambda: mfmjax.closed_form(G, np.ones(3)),
        "constrained_solve": lambda: mfmjax.constrained_solve(G, np.ones(3), np.ones(3, bool)),
        "state_space": lambda: mfmjax.state_space(model),
        "to_scipy": lambda: mfmjax.to_scipy(model), "to_control": lambda: mfmjax.to_control(model),
        "save_model": lambda: mfmjax.save_model(model, "/nonexistent/m.json"),
        "load_model": lambda: mfmjax.load_model("/nonexistent/m.json"),
    }
    config = OnlineConfig(dt=1.0, n_inputs=1)
    calls["online.init"] = lambda: mfmjax.online.init(config)
    # these three returned float32 arrays (device_put of float64 NumPy narrows them)
    calls["Model.from_coefficients"] = lambda: Model.from_coefficients([1.0, 2.0], [[1.0]])
    calls["Signals.window"] = lambda: sig.window(0.0, 1.0)
    calls["detrend"] = lambda: mfmjax.detrend(sig)
    jax.config.update("jax_enable_x64", False)
    try:
        for name, call in calls.items():
            with pytest.raises(RuntimeError, match=rf"{name}\(\): JAX float64 mode is off"):
                call()
    finally:
        jax.config.update("jax_enable_x64", True)


def test_closed_form_and_datasets_refuse_bad_arguments():
    from mfmjax.datasets import (
        forehearth,
        simulated_experiment,
        switching_experiment,
        third_order_two_input,
        transport_delay,
    )

    with pytest.raises(ValueError, match=r"closed_form\(\): G must be square \(p, p\) and eta"):
        mfmjax.closed_form(np.eye(3), np.ones(2))
    with pytest.raises(TypeError, match=r"transport_delay\(\): pull is missing"):
        transport_delay(None)
    with pytest.raises(ValueError, match=r"transport_delay\(\): pull must be > 0"):
        transport_delay(-1.0)
    with pytest.raises(ValueError, match=r"switching_experiment\(\): interval must be an integer"):
        switching_experiment(interval=2.5)
    with pytest.raises(TypeError, match=r"switching_experiment\(\): models must be a sequence"):
        switching_experiment("AB")
    with pytest.raises(ValueError, match=r"forehearth\(\): experiment must be 1 or 2"):
        forehearth(True)
    with pytest.raises(ValueError, match=r"simulated_experiment\(\): dt must be > 0"):
        simulated_experiment(third_order_two_input(), dt=float("nan"), n_samples=100)


def test_output_given_as_an_input_is_refused():
    """`identify --inputs y` in the library: an input equal to the output (or an affine image of
    it) made a degenerate model with status ok; the data container refuses it."""
    y = np.sin(np.linspace(0, 20, 400)) + 0.1 * np.linspace(0, 1, 400)
    other = np.cos(np.linspace(0, 13, 400))
    for u in (y, 2.0 * y + 5.0, np.column_stack([other, -y])):
        with pytest.raises(ValueError, match=r"Signals\(\): input 'u\d' is the output 'y' itself"):
            Signals(y, u, dt=0.1)
    Signals(y, other, dt=0.1)  # an ordinary input is fine


# -- traced values where the host decides; derivative orders, kernels, solves -----------------


def test_host_functions_refuse_traced_values_by_name(data, fitted):
    """Functions that plan, decide or draw on the host say so when a value they read is traced
    (an audit found JAX's TracerArrayConversionError, ConcretizationTypeError or
    TracerBoolConversionError from inside their host code), and name what traces instead."""
    import jax.numpy as jnp

    model, sig = data
    host = "runs on the host .* call it on concrete values"
    cases = [
        (lambda m: mfmjax.step_response(m).y, fitted, f"step_response\\(\\) {host}.*simulate"),
        (lambda m: mfmjax.frequency_response(m).magnitude_db, fitted,
         f"frequency_response\\(\\) {host}"),
        (lambda a: mfmjax.Model.from_coefficients(a, [[1.0]]).a, jnp.asarray([2.0, 3.0, 1.0]),
         f"Model.from_coefficients\\(\\) {host}.*equinox.tree_at"),
        (lambda h: mfmjax.search(sig, n=(2,), N=(3,), M=(3,), h=h).row(0)["E"], 4.0,
         f"search\\(\\) {host}"),
        (lambda u: mfmjax.cramer_rao(model, u, np.zeros(2), dt=DT, sigma=0.1)[1],
         np.asarray(sig.u), f"cramer_rao\\(\\) {host}"),
        (lambda m: mfmjax.compare(m, sig).fit, fitted, f"compare\\(\\) {host}.*observe"),
        (lambda t0: mfmjax.observe(model, sig, (t0, 15.0)).E, 1.0,
         r"observe\(\): window is traced .* give concrete times"),
        (lambda ts: mfmjax.moving_final_states(model, sig, 5.0, ts), jnp.asarray([10.0]),
         f"moving_final_states\\(\\) {host}"),
        (lambda y: mfmjax.resample(np.arange(400) * DT, y, np.asarray(sig.u), dt=0.1).y,
         np.asarray(sig.y), f"resample\\(\\) {host}"),
    ]
    for fn, arg, match in cases:
        with pytest.raises(TypeError, match=match):
            jax.jit(fn)(arg)
    with pytest.raises(ValueError, match=r"scores\(\): h is traced .* pass h_max"):
        jax.grad(lambda h: mfmjax.scores(sig, Structure(2, 0), h=h, N=3.0, M=3.0)["E"])(4.0)
    # a window of stacked records under vmap: its sample indices from the host dt (the
    # traced dt gave TracerBoolConversionError), each record's window its own
    other = mfmjax.Model.from_coefficients([2.2, 3.0, 1.0], [[1.0]])  # E far above rounding
    stacked = jax.tree.map(lambda *x: jnp.stack(x), sig, sig)
    E = jax.vmap(lambda s: mfmjax.observe(other, s.window(1.0, 15.0)).E)(stacked)
    np.testing.assert_allclose(np.asarray(E), float(mfmjax.observe(other, sig.window(1.0, 15.0)).E),
                               rtol=1e-10)


def test_derivative_orders_kernels_and_solves_are_checked():
    """Silent wrong answers the audit found: phi(i=-1) returned zeros and phi_integral(i=-1)
    the i = 0 integral; kernel_weights cut the weights off at a `length` shorter than the
    support (sum 5.7e-5 against 7.9e-4), returned NaN at dt = 0 and zeros at dt < 0, and took
    a negative delay; closed_form returned float32 for float32 input; constrained_solve and
    gram leaked lax and attribute errors."""
    import jax.numpy as jnp

    mf = ModulatingFunction(4, 5, 2.0)
    for call in (lambda: mfmjax.phi(jnp.linspace(0, 2, 5), mf, -1),
                 lambda: mfmjax.phi_integral(0.0, 1.0, mf, -1),
                 lambda: mfmjax.kernel_weights(mf, 1.0, 0.01, "cubic", 0.0, 220)):
        with pytest.raises(ValueError, match=r"i, the derivative order, must be a Python "
                                             r"integer >= 0"):
            call()
    for args, match in (((0, 0.01, "cubic", 0.0, 50), "length=50 is shorter than the support "
                                                      ".* it needs 201 samples"),
                        ((1, 0.0, "cubic", 0.0, 220), "dt must be a finite number > 0"),
                        ((1, -0.01, "cubic", 0.0, 220), "dt must be a finite number > 0"),
                        ((1, 0.01, "cubic", -0.5, 220), "delay must be one finite number >= 0")):
        with pytest.raises(ValueError, match=rf"kernel_weights\(\): {match}"):
            mfmjax.kernel_weights(mf, *args)
    # at the support's own length the weights hold the whole profile: their sum is the
    # integral of r^N (1 - r)^M over [0, 1], B(N+1, M+1) = N! M! / (N + M + 1)!
    w = mfmjax.kernel_weights(mf, 0, 0.01, "cubic", 0.0, 201)
    assert float(w.sum()) == pytest.approx(math.factorial(4) * math.factorial(5)
                                           / math.factorial(10), rel=1e-12)
    G = np.diag([2.0, 1.0, 3.0]).astype(np.float32)
    assert mfmjax.closed_form(G, np.ones(3, np.float32)).dtype == np.float64
    with pytest.raises(ValueError, match=r"constrained_solve\(\): G must be square \(p, p\), "
                                         r"eta and active \(p,\); got G \(3, 3\), eta \(4,\)"):
        mfmjax.constrained_solve(np.eye(3), np.ones(4), np.ones(3, bool))
    with pytest.raises(TypeError, match=r"gram\(\): give the ModulatedSignals"):
        mfmjax.gram(np.ones((5, 5)))


def test_audit_messages_name_the_problem(data, fitted, tmp_path):
    """The audit's partly clear messages: a traced number said "must be a real number, got
    DynamicJaxprTracer"; an empty list of records "got list"; `save_model` into a missing
    folder named its temporary file; `OnlineIdentifier.model(99)` a bare IndexError."""
    model, sig = data
    with pytest.raises(TypeError, match=r"simulate\(\): dt is traced .* pass it from outside"):
        jax.jit(lambda dt: mfmjax.simulate(model, np.asarray(sig.u), dt=dt))(DT)
    for fn in (mfmjax.srivc, mfmjax.output_error):
        with pytest.raises(ValueError, match=r"the list of records is empty"):
            fn([], fitted)
    with pytest.raises(ValueError, match=r"estimate\(\): the list of records is empty"):
        mfmjax.estimate([], h=4.0)
    missing = tmp_path / "no" / "model.json"
    with pytest.raises(FileNotFoundError, match=rf"cannot write {missing}: the folder .* does "
                                                r"not exist"):
        mfmjax.save_model(fitted, missing)
    with pytest.raises(IsADirectoryError, match=rf"cannot write {tmp_path}: it is a folder; "
                                                r"give a file name"):
        mfmjax.save_model(fitted, tmp_path)
    with pytest.raises(ValueError, match=r"save_model\(\): record must be a dict with keys "
                                         r"from \('dt', 'detrend', 'trend', 'columns', 'file', "
                                         r"'time', 'start'\)"):
        mfmjax.save_model(fitted, tmp_path / "m.json", record={"dt": 1.0, "units": "s"})
    for bad in ({"dt": None}, {"dt": -1.0}, {"detrend": "cubic"}, {"columns": ["y"]},
                {"columns": "y,u1"}, {"file": 3}, {"time": 1.0}, {"start": float("inf")},
                {"start": "0"}):
        with pytest.raises(ValueError, match=r"save_model\(\): record must be a dict"):
            mfmjax.save_model(fitted, tmp_path / "m.json", record=bad)
    ident = mfmjax.OnlineIdentifier(OnlineConfig(dt=1.0, n_inputs=1))
    with pytest.raises(ValueError, match=r"model\(\): no model has been accepted yet"):
        ident.model()


def test_swapped_record_and_model_say_the_argument_order():
    """Some functions take the record first (identify, search, srivc, output_error, ...), some
    the model (observe, simulate, compare, ...): a Model where a record goes, or the reverse,
    says the function's order; `simulate` given a Signals as its inputs says to pass its u."""
    model = mfmjax.Model.from_coefficients([2.0, 3.0, 1.0], [[1.0]])
    u = np.sin(0.1 * np.arange(300))
    sig = mfmjax.Signals(np.asarray(mfmjax.simulate(model, u, dt=0.1)), u, dt=0.1)
    mf = mfmjax.ModulatingFunction(3, 3, 2.0)
    cases = [
        (lambda: mfmjax.observe(sig, model), r"observe\(\): model must be a Model, got Signals; "
         r"arguments swapped\? the order is observe\(model, signals, \.\.\.\)"),
        (lambda: mfmjax.compare(sig, model), r"the order is compare\(model, signals"),
        (lambda: mfmjax.simulate(sig, u, dt=0.1), r"the order is simulate\(model, u"),
        (lambda: mfmjax.srivc(model, sig), r"srivc\(\): signals must be .* got Model; arguments "
         r"swapped\? the order is srivc\(signals, model"),
        (lambda: mfmjax.output_error(model, sig), r"the order is output_error\(signals, model"),
        (lambda: mfmjax.identify(model, mfmjax.Structure(2, [0]), mf),
         r"the order is identify\(signals, structure"),
        (lambda: mfmjax.search(model, h=2.0), r"the order is search\(signals, n"),
        (lambda: mfmjax.moving_final_states(sig, model, 2.0, [20.0]),
         r"the order is moving_final_states\(model, signals"),
        (lambda: mfmjax.simulate(model, sig, None, dt=0.1),
         r"simulate\(\): u must be the inputs \(T, K\), got a Signals: pass signals\.u"),
    ]
    for call, match in cases:
        with pytest.raises(TypeError, match=match):
            call()
    with pytest.raises(TypeError) as err:  # neither a record nor a model: no hint
        mfmjax.observe("model.json", sig)
    assert "swapped" not in str(err.value)


def test_record_lists_signals_given_as_u_and_a_path_that_is_not_one_are_named(tmp_path):
    """`srivc([sig, 3], m)` said "got list" (the list was right, its element 1 was not),
    `cramer_rao(model, signals, ...)` "u must hold real numbers, got dtype object", and
    `load_model(None)` a bare TypeError from `open`."""
    sig = Signals(np.sin(np.arange(200) * 0.1), np.cos(np.arange(200) * 0.1)[:, None], dt=0.1)
    model = mfmjax.Model.from_coefficients([1.0, 1.0], [[1.0]])
    for fn in (lambda: mfmjax.srivc([sig, 3], model),
               lambda: mfmjax.estimate([sig, "y"], h=2.0, n=(1,), N=(3,), M=(3,))):
        with pytest.raises(TypeError, match=r"list of Signals of one layout \(a batch of "
                                            r"records\); record 1 is a (int|str)"):
            fn()
    with pytest.raises(TypeError, match=r"cramer_rao\(\): u must be the experiment's inputs "
                                        r"\(T, K\), got a Signals: pass signals.u"):
        mfmjax.cramer_rao(model, sig, np.zeros(1), dt=0.1, sigma=0.1)
    with pytest.raises(TypeError, match=r"load_model\(\): path must be a file name, got "
                                        r"NoneType"):
        mfmjax.load_model(None)


def test_building_block_messages_name_the_argument():
    """JAX's or NumPy's own errors came out of these ("cannot convert float NaN to integer",
    "Shapes must be 1D sequences", "'tuple' object has no attribute 'h'", and "Structure():
    m[0] must be an integer >= 0 (got m[0]=-1)" for an empty b)."""
    mf = mfmjax.ModulatingFunction(4, 4, 2.0)
    cases = [
        (lambda: mfmjax.phi(0.3, (3, 4, 2.0), 0), TypeError,
         r"phi\(\): mf must be a ModulatingFunction"),
        (lambda: mfmjax.phi_integral(0.0, 1.0, (3, 4, 2.0)), TypeError,
         r"phi_integral\(\): mf must be a ModulatingFunction"),
        (lambda: mfmjax.kernel_weights(mf, 0, 0.1, "foh", np.nan, 30), ValueError,
         r"kernel_weights\(\): delay must be one finite number >= 0"),
        (lambda: mfmjax.kernel_weights(mf, 0, 0.1, "foh", [0.0, 0.1], 30), ValueError,
         r"kernel_weights\(\): delay must be one finite number >= 0"),
        (lambda: mfmjax.kernel_weights(mf, 0, 0.1, "foh", 0.0, 30.0), TypeError,
         r"kernel_weights\(\): length must be an int >= 2"),
        (lambda: mfmjax.Model.from_coefficients([1.0, 1.0], [[]]), ValueError,
         r"Model.from_coefficients\(\): b\[0\] is empty; give at least b_10"),
    ]
    for call, kind, says in cases:
        with pytest.raises(kind, match=says):
            call()
