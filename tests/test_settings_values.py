"""Settings are values (issue 12): a new N, M, h, window start, t0 or signal name is a new value
for the compiled programs, never a new program. Compilations are counted from JAX's own log
(`jax_log_compiles`), so every program counts: jitted cores and eager primitives alike.
"""


import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import reference as R
from jaxlog import compiles

import mfmjax
from mfmjax import ModulatingFunction, OnlineConfig, OnlineIdentifier, Signals, Status, Structure
from mfmjax.datasets import simulated_experiment, switching_experiment, third_order_two_input

DT = 0.05
ST = Structure(3, [1, 1])


@pytest.fixture(scope="module")
def record():
    return simulated_experiment(third_order_two_input(), dt=DT, n_samples=1200, seed=3)


def _head(sig: Signals, T: int) -> Signals:
    """The first `T` samples of `sig` as a record of their own (a new record length)."""
    return Signals(np.asarray(sig.y)[:T], np.asarray(sig.u)[:T], dt=DT,
                   intersample=sig.intersample)


def _padded_and_unpadded(fit, module, noisy, monkeypatch):
    """`fit(record, start)` on the first 560 samples of `noisy` after a fit on all 600 (one
    bucket: 640): asserts that it compiles nothing, then returns it with the same fit with
    `module`'s padding switched off (the program of the record's own length)."""
    from mfmjax._quadrature import record_bucket

    assert record_bucket(600) == record_bucket(560) == 640
    short = _head(noisy, 560)
    start = mfmjax.identify(noisy, ST, ModulatingFunction(4, 5, 2.6))
    fit(noisy, start)
    with compiles() as names:
        padded = fit(short, start)
    assert names == [], f"a new record length compiled {names}"
    monkeypatch.setattr(module, "record_bucket", lambda n: n)
    return padded, fit(short, start)


def _settings(count):
    """`count` distinct (N, M, h) whose supports need 50..64 samples: one kernel bucket (64)."""
    rng = np.random.default_rng(0)
    return [(int(rng.integers(3, 7)), int(rng.integers(3, 7)), float(h))
            for h in np.linspace(2.45, 3.15, count)]


def test_identify_new_settings_inside_a_bucket_compile_once(record):
    settings = _settings(20)
    with compiles() as first:
        mfmjax.identify(record, ST, ModulatingFunction(*settings[0]))
    with compiles() as rest:
        models = [mfmjax.identify(record, ST, ModulatingFunction(*s)) for s in settings[1:]]
    assert rest == [], f"new settings compiled {rest}"
    assert len(set(float(m.mf.h) for m in models)) == 19  # really 19 different settings
    # the values reached the program: each model equals a fresh identify of its own setting
    # (exact: the same program on the same values)
    again = mfmjax.identify(record, ST, ModulatingFunction(*settings[7]))
    np.testing.assert_array_equal(np.asarray(again.a), np.asarray(models[6].a))
    # at most the one program of this bucket (none if an earlier test compiled it)
    assert sum("identify_core" in name for name in first) <= 1


def test_modulated_signals_and_gram_new_settings_compile_nothing(record):
    """The public `modulated_signals` and `gram` outside jit: one program per structure, record
    length and kernel bucket; a new (N, M, h), delay, t0 or name compiles nothing (eagerly, each
    new h compiled every primitive of the kernels again: 2-3.6 s per call on this machine)."""
    settings = _settings(6)
    mfmjax.gram(mfmjax.modulated_signals(record, ST, ModulatingFunction(*settings[0])))
    relabelled = Signals(record.y, record.u, dt=DT, intersample=record.intersample, t0=12.5,
                         output_name="T", input_names=("q", "p"), delays=(0.03, 0.0))
    with compiles() as names:
        Gs = [np.asarray(mfmjax.gram(mfmjax.modulated_signals(sig, ST, ModulatingFunction(*s))))
              for s in settings[1:5] for sig in (record, relabelled)]  # (the last + delay: 96)
    assert names == [], f"new settings compiled {names}"
    # the values reached the program: the Gram of eq. (9) over the columns of eq. (6) equals
    # identify's (the same body inside its program) to rounding: within 1e-12 of its largest
    from mfmjax._gram import compiled_length, gram_matrix, modulated_columns
    from mfmjax._modulating import as_values

    mf = ModulatingFunction(*settings[3])
    ref = jax.jit(lambda m: gram_matrix(modulated_columns(
        record, ST, m, compiled_length(record, mf))))(as_values(mf))
    np.testing.assert_allclose(Gs[4], np.asarray(ref), rtol=0,
                               atol=1e-12 * float(np.max(np.abs(ref))))
    assert not np.allclose(Gs[4], Gs[5])  # the delay changed the input columns
    # an explicit length may be any integer type (a NumPy one is not traced as a value)
    G64 = mfmjax.gram(mfmjax.modulated_signals(record, ST, mf, length=np.int64(64)))
    np.testing.assert_array_equal(np.asarray(G64), Gs[4])


def test_identify_values_equal_exact_kernel_length(record):
    """Bucketing only pads the kernel with exact zeros: parameters equal those of the exact
    length to rounding (the summation order of the convolution changes), 1e-10 relative."""
    from mfmjax._identify import identify_model
    from mfmjax._modulating import as_values
    from mfmjax._quadrature import kernel_length

    mf = ModulatingFunction(4, 5, 2.6)
    exact = identify_model(record.unlabelled(), ST.for_inputs(2), as_values(mf), jnp.ones(8),
                           kernel_length(2.6, DT))
    bucketed = mfmjax.identify(record, ST, mf)
    # norm-wise: rounding is relative to the largest entry (b_21 here is ~1e-7, a parameter the
    # noise-free system does not have, and carries absolute, not relative, rounding)
    diff = np.max(np.abs(np.asarray(bucketed.theta) - np.asarray(exact.theta)))
    assert diff <= 1e-10 * np.max(np.abs(np.asarray(exact.theta)))


def test_identify_new_record_length_inside_a_bucket_compiles_nothing():
    """Records of 1100 and 1200 samples pad to one length (`record_bucket`: 1280) and share one
    compiled `identify_core`. The padding is masked exactly: on the short (noisy) record the
    parameters equal those of the core run on the unpadded record (its own length) to rounding
    (the FFT size and summation order change), 1e-10 relative norm-wise as above, and so does
    J_rel (the noise keeps it far above rounding: 1e-8)."""
    from mfmjax._identify import identify_model
    from mfmjax._modulating import as_values
    from mfmjax._quadrature import kernel_length, record_bucket

    assert record_bucket(1100) == record_bucket(1200) == 1280
    mf = ModulatingFunction(4, 5, 2.6)
    long = simulated_experiment(third_order_two_input(), dt=DT, n_samples=1200, seed=6,
                                noise_std=0.02)
    short = _head(long, 1100)
    mfmjax.identify(long, ST, mf)
    with compiles() as names:
        model = mfmjax.identify(short, ST, mf)
    assert names == [], f"a new record length compiled {names}"
    exact = identify_model(short.unlabelled(), ST.for_inputs(2), as_values(mf), jnp.ones(8),
                           kernel_length(2.6, DT))
    assert exact.theta.shape == model.theta.shape and int(model.status) == int(exact.status) == 0
    diff = np.max(np.abs(np.asarray(model.theta) - np.asarray(exact.theta)))
    assert diff <= 1e-10 * np.max(np.abs(np.asarray(exact.theta)))
    assert float(model.J_rel) == pytest.approx(float(exact.J_rel), rel=1e-8)


def test_search_new_record_length_with_a_validation_window_at_its_end_compiles_nothing(
        monkeypatch):
    """The validation window's buffer (its `record_bucket`: 417 samples -> 448) may run past
    the padded record's end, the last sample held there: validating on the last 417 samples
    of 1250 (from sample 833 of a record padded to 1280) after 1200 samples compiled the
    search's chunk again (2 programs), because its buffer was cut at the padded end to 447.
    E and fit equal those of buffers of the window's exact length (the bucket switched off)
    to rounding: the same simulation, its sums over other lengths (1e-12)."""
    from mfmjax._quadrature import record_bucket
    from mfmjax._search import _grid

    assert record_bucket(1200) == record_bucket(1250) == 1280 and record_bucket(417) == 448
    grid = dict(n=(1, 2), N=(3, 4), M=(3, 4), h=(2.0, 3.0), m=[[0], [0]])
    long = simulated_experiment(third_order_two_input(), dt=DT, n_samples=1250, seed=6,
                                noise_std=0.02)
    first = _head(long, 1200)
    mfmjax.search(first, **grid, validate=(783 * DT, 1199 * DT))
    with compiles() as names:
        res = mfmjax.search(long, **grid, validate=(833 * DT, 1249 * DT))
    assert names == [], f"a new record length compiled {names}"
    monkeypatch.setattr(_grid, "record_bucket", lambda n: n)
    exact = mfmjax.search(long, **grid, validate=(833 * DT, 1249 * DT))
    np.testing.assert_array_equal(res.columns["status"], exact.columns["status"])
    for key in ("E", "fit"):
        np.testing.assert_allclose(res.columns[key], exact.columns[key], rtol=1e-12)


def test_simulate_new_record_length_inside_a_bucket_compiles_nothing():
    """`simulate` pads a concrete input to its record bucket (1100 and 1200 samples: 1280) and
    returns the first T samples; the response is causal, so they equal the unpadded program's
    (the same recursion on the same values: equal to the last bit or to a few ulps if XLA
    vectorises the two lengths differently; 1e-13 relative)."""
    from mfmjax._simulate import simulate_status

    model = mfmjax.Model.from_coefficients([1.0, 0.8, 1.0], [[1.0, 0.3]], delays=[0.23],
                                           intersample=["foh"])
    u = np.random.default_rng(0).standard_normal(1200)
    mfmjax.simulate(model, u, dt=DT)
    with compiles() as names:
        y, x = mfmjax.simulate(model, u[:1100], dt=DT, return_state=True)
    assert names == [], f"a new record length compiled {names}"
    # the program of the record's own length, dt a value as in `simulate`
    y_ref, x_ref, status = jax.jit(simulate_status)(model.unlabelled(), u[:1100], jnp.zeros(2),
                                                    np.float64(DT))
    assert y.shape == (1100,) and x.shape == (1100, 2) and int(status) == 0
    np.testing.assert_allclose(np.asarray(y), np.asarray(y_ref), rtol=1e-13, atol=0)
    np.testing.assert_allclose(np.asarray(x), np.asarray(x_ref), rtol=1e-13, atol=0)
    # only the record counts for the overflow test: an unstable response (x' = x + 1) that
    # passes the overflow bound at sample 1150, inside the padding of a 1100-sample record
    from mfmjax._simulate import _BIG

    unstable, dt = mfmjax.Model.from_coefficients([-1.0, 1.0], [[1.0]]), np.log(_BIG) / 1150
    assert np.all(np.isfinite(np.asarray(mfmjax.simulate(unstable, np.ones(1100), dt=dt))))
    with pytest.raises(ValueError, match="overflows float64 because the model is unstable"):
        mfmjax.simulate(unstable, np.ones(1200), dt=dt)


def test_simulate_and_observers_new_structure_of_the_same_order_compile_nothing():
    """`simulate`, `observe` and `moving_final_states` run a model with every numerator
    zero-padded to its order n (`simulation_form`), and `frequency_response`, `step_response`
    and `cramer_rao` its free parameters laid out so (`order_parameters`; their correctness is
    checked in test_analysis.py): one program per order, inputs, rules and offset term, not
    per structure. Three new structures of order 2 compile nothing in any of them, and each
    response equals the one of the structure's own program (the same realisation, eq. 18:
    the padded coefficients are zeros). That program folds its constant zeros, so the two may
    differ by rounding: a few ulps of each step's sum, compounded over the recursion, bounded
    here by 1e-13 of the response's scale. The observers' E sums squared residuals of about
    0.01 (the noise), so such errors move it by about 2e-16 / 0.01 = 2e-14 relative; their
    states come from a solve whose equilibrated Gramian has condition number 1 here: both
    checked to 1e-12."""
    from mfmjax._observers import observe_window
    from mfmjax._simulate import simulate_status

    u = np.random.default_rng(0).standard_normal((1200, 2))
    modes = ["foh", "zoh"]
    ms = [mfmjax.Model.from_coefficients([1.0, 0.8, 1.0], b, delays=[0.23, 0.0],
                                         intersample=modes)
          for b in ([[1.0, 0.3], [0.5]], [[1.0], [0.5, 0.2]], [[1.0, 0.3, 0.1], [0.5]],
                    [[1.0], [0.5]])]
    y0 = np.asarray(mfmjax.simulate(ms[0], u, dt=DT))
    sig = Signals(y0 + 0.01 * np.random.default_rng(1).standard_normal(1200), u, dt=DT,
                  intersample=modes)
    from mfmjax._output_error import free_parameters

    def analyses(m):  # the responses with bands and the Cramer-Rao bound
        p = len(free_parameters(m)[0])
        cov = 1e-4 * np.eye(p)
        mfmjax.frequency_response(m, covariance=cov)
        mfmjax.step_response(m, covariance=cov)
        mfmjax.cramer_rao(m, u, np.zeros(2), dt=DT, sigma=0.01)

    mfmjax.observe(ms[0], sig)
    mfmjax.moving_final_states(ms[0], sig, 10.0, [30.0, 40.0])
    analyses(ms[0])
    for m in ms[1:]:
        with compiles() as names:
            y, x = mfmjax.simulate(m, u, dt=DT, return_state=True)
            obs = mfmjax.observe(m, sig)
            xs = mfmjax.moving_final_states(m, sig, 10.0, [30.0, 40.0])
            analyses(m)
        assert names == [], f"structure {m.m} compiled {names}"
        own = m.unlabelled()  # the structure's own program (compiled here, outside the count)
        y_ref, x_ref, status = jax.jit(simulate_status, static_argnums=3)(own, u, jnp.zeros(2), DT)
        assert int(status) == 0 and x.shape == (1200, 2)
        scale = np.max(np.abs(np.asarray(y_ref)))
        np.testing.assert_allclose(np.asarray(y), np.asarray(y_ref), rtol=0, atol=1e-13 * scale)
        np.testing.assert_allclose(np.asarray(x), np.asarray(x_ref), rtol=0,
                                   atol=1e-13 * np.max(np.abs(np.asarray(x_ref))))
        ref = jax.jit(observe_window, static_argnums=(3, 5))(own, sig.y, sig.u, DT, 0, 1200)
        np.testing.assert_allclose(float(obs.E), float(ref.E), rtol=1e-12)
        for got, want in ((obs.x_initial, ref.x_initial), (obs.x_final, ref.x_final)):
            np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=0,
                                       atol=1e-12 * np.max(np.abs(np.asarray(want))))
        assert np.asarray(xs).shape == (2, 2) and np.all(np.isfinite(np.asarray(xs)))


def test_observe_new_record_and_window_lengths_inside_a_bucket_compile_nothing(record):
    """`observe` pads the window to its record bucket and the record to hold it: records of
    1200 and 1100 samples, and windows of 901 and 921 samples (bucket 1024) with or without an
    observer window, share one program; so do `moving_final_states`' windows (eq. 16) of 901
    and 921 samples on them (before, each record length and T_ob compiled its program). Only
    the window's samples count: x0, the final state and y_sim equal the unpadded program's
    (`observe_window` at the window's own length) to the rounding of the Gramian's sums (equal
    shapes up to the padding: 1e-10 relative), and E is the Gregory sum over the window's own
    samples."""
    from mfmjax._observers import observe_window

    model = mfmjax.identify(record, ST, ModulatingFunction(4, 5, 2.6))
    short = _head(record, 1100)
    mfmjax.observe(model, record)
    mfmjax.observe(model, record, (5.0, 50.0))
    mfmjax.moving_final_states(model, record, 45.0, [50.0, 59.0])
    with compiles() as names:
        runs = [mfmjax.observe(model, short), mfmjax.observe(model, short, (7.0, 53.0)),
                mfmjax.observe(model, short, (7.0, 53.0), observer_window=10.0)]
        moving = np.asarray(mfmjax.moving_final_states(model, short, 46.0, [53.0, 54.95]))
    assert names == [], f"new record and window lengths compiled {names}"
    for x_end, end in zip(moving, (1060, 1099)):  # windows of 921 samples ending there
        ref = jax.jit(observe_window, static_argnums=(3, 5, 6))(
            model.unlabelled(), short.y, short.u, DT, end - 920, 921, None)
        np.testing.assert_allclose(x_end, np.asarray(ref.x_final), rtol=1e-10,
                                   atol=1e-10 * np.max(np.abs(np.asarray(ref.x_final))))
    for obs, (start, length, ob) in zip(runs, [(0, 1100, None), (140, 921, None),
                                               (140, 921, 201)]):
        ref = jax.jit(observe_window, static_argnums=(3, 5, 6))(
            model.unlabelled(), short.y, short.u, DT, start, length, ob)
        assert obs.y_sim.shape == (length,) and int(obs.status) == int(ref.status) == 0
        for got, want in ((obs.x_initial, ref.x_initial), (obs.x_final, ref.x_final),
                          (obs.y_sim, ref.y_sim)):
            np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-10,
                                       atol=1e-10 * np.max(np.abs(np.asarray(want))))
        # E (eq. 17) is the Gregory sum of the window's own squared residuals, the padding
        # left out: recomputed from each y_sim (compared above) with the NumPy twin's weights
        # on the window's own length. Same terms, another summation order: L eps relative
        # (2.4e-13 for L = 1100). (E itself is small here, about 1e-11: the identification
        # error of a noise-free record, RMS residual about 5e-7, so E's of two programs
        # differ relatively more than their y_sim.) An extra or a missing sample, or other
        # end weights, move E by 1e-4 to 1e-6 of itself.
        y_w = np.asarray(short.y)[start:start + length]
        q = R.gregory(length, 0, DT)
        for o in (obs, ref):
            E_twin = float(np.sum(q * (y_w - np.asarray(o.y_sim)) ** 2))
            assert abs(float(o.E) - E_twin) <= 1e-12 * E_twin


def test_window_at_the_record_end_on_a_new_record_length_compiles_nothing(monkeypatch):
    """`observe` and `output_error` on the last 417 samples (buffer 448) of 1250 samples after
    1200: the record used to be padded to hold the window's buffer, to the bucket of start +
    buffer (1281 -> 1536 against 1280), so the new length compiled 3 programs. It is padded
    by the buffer beyond its own bucket now, whatever the start, and compiles nothing. x0 and
    E equal the unpadded `observe_window`'s to rounding (1e-10), and the output-error fit the
    one with the padding switched off (theta within 1e-6 standard errors, E 1e-12, as in
    `test_output_error_new_record_length_inside_a_bucket_compiles_nothing`)."""
    import mfmjax._observers as ob
    from mfmjax._observers import observe_window

    model = third_order_two_input()
    long = simulated_experiment(model, dt=DT, n_samples=1250, seed=3, noise_std=0.02)
    first = _head(long, 1200)
    window = lambda T: ((T - 417) * DT, (T - 1) * DT)  # noqa: E731
    mfmjax.observe(model, first, window(1200))
    mfmjax.output_error(first, model, window=window(1200))
    with compiles() as names:
        obs = mfmjax.observe(model, long, window(1250))
        fit = mfmjax.output_error(long, model, window=window(1250))
    assert names == [], f"a new record length compiled {names}"
    ref = jax.jit(observe_window, static_argnums=(3, 5))(model.unlabelled(), long.y, long.u, DT,
                                                          833, 417)
    for got, want in ((obs.x_initial, ref.x_initial), (obs.E, ref.E)):
        np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-10,
                                   atol=1e-10 * np.max(np.abs(np.asarray(want))))
    monkeypatch.setattr(ob, "record_bucket", lambda n: n)
    exact = mfmjax.output_error(long, model, window=window(1250))
    assert fit.converged and exact.converged
    assert np.all(np.abs(fit.theta - exact.theta) <= 1e-6 * exact.std_errors)
    assert fit.E == pytest.approx(exact.E, rel=1e-12)


def test_search_new_settings_inside_a_bucket_compile_nothing(record):
    """A search over other N, M and h values (same grid sizes, same largest N + M, largest h in
    the same kernel bucket: 50..64 samples -> 64) and a new t0 and names reuses the compiled
    chunk; the values reach it (the h column is the new grid's)."""
    grid = dict(n=(1, 2, 3), m=[(0, 1), (0, 1)], simulate=False, score="J")
    mfmjax.search(record, N=(4, 5), M=(4, 5), h=(2.5, 3.1), **grid)
    relabelled = Signals(np.asarray(record.y), np.asarray(record.u), dt=DT, t0=77.0,
                         intersample=record.intersample, output_name="T", input_names=["a", "b"])
    with compiles() as names:
        res = mfmjax.search(relabelled, N=(5, 4), M=(5, 4), h=(2.45, 2.9), **grid)
    assert names == [], f"new search settings compiled {names}"
    assert sorted(set(np.round(res.columns["h"], 12))) == [2.45, 2.9]


def test_search_new_record_length_inside_a_bucket_compiles_nothing():
    """Records of 1100 and 1200 samples pad to one length (`record_bucket`: 1280) and share the
    compiled chunk (E scored on the whole record, observer over its first 10 s). The padding
    is masked exactly: on the short record the search equals the identify of each candidate
    (padded alike, and itself checked against the record's own length above) to rounding amplified
    by the Gram's conditioning (cond < 1e8: 1e-8 relative), and its E is the observer +
    simulation's on the record, not on the padding."""
    from mfmjax._quadrature import record_bucket

    assert record_bucket(1100) == record_bucket(1200) == 1280
    long = simulated_experiment(third_order_two_input(), dt=DT, n_samples=1200, seed=6,
                                noise_std=0.02)
    short = _head(long, 1100)
    grid = dict(n=(1, 2, 3), m=[(0, 1), (0, 1)], N=(4, 5), M=(4, 5), h=(2.5, 3.1),
                observer_window=10.0)
    mfmjax.search(long, **grid)
    with compiles() as names:
        res = mfmjax.search(short, **grid)
    assert names == [], f"a new record length compiled {names}"
    for i in range(4):
        row = res.row(i)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            model = mfmjax.identify(short, Structure(row["n"], row["m"]),
                                    ModulatingFunction(row["N"], row["M"], row["h"]))
        assert float(model.cond) < 1e8
        got = np.concatenate([row["a"]] + [np.asarray(b) for b in row["b"]])
        ref = np.concatenate([np.asarray(model.a)] + [np.asarray(b) for b in model.b])
        assert np.max(np.abs(got - ref)) <= 1e-8 * np.max(np.abs(ref)), row
        E = float(mfmjax.performance_index(model, short, observer_window=10.0))
        assert row["E"] == pytest.approx(E, rel=1e-6)


def test_new_t0_and_names_compile_nothing(record):
    mf = ModulatingFunction(4, 5, 2.6)
    mfmjax.identify(record, ST, mf)
    mfmjax.observe(mfmjax.identify(record, ST, mf), record, (10.0, 50.0))
    relabelled = Signals(np.asarray(record.y), np.asarray(record.u), dt=DT, t0=1234.5,
                         intersample=record.intersample, output_name="temperature",
                         input_names=["valve", "pump"])
    with compiles() as names:
        model = mfmjax.identify(relabelled, ST, mf)
        obs = mfmjax.observe(model, relabelled, (1234.5 + 10.0, 1234.5 + 50.0))
    assert names == [], f"a new t0 / names compiled {names}"
    assert model.output_name == "temperature" and model.input_names == ("valve", "pump")
    assert np.isfinite(float(obs.E))


def test_new_operating_point_compiles_nothing(record):
    """The default offset rule's note names the operating point ("sits at 100.2, 37 standard
    deviations from zero"), so it differs between records; it is a label, kept out of the
    programs like t0 and the names (before, a record at another level compiled `identify`,
    the search's chunk and its validation again)."""
    at = [Signals(np.asarray(record.y) + level, np.asarray(record.u), dt=DT,
                  intersample=record.intersample) for level in (100.0, 130.0)]
    assert all(sig.offset for sig in at) and at[0].offset_note != at[1].offset_note
    mf, grid = ModulatingFunction(4, 5, 2.6), dict(n=(3,), m=[(1,), (0,)], N=4, M=5, h=2.6)
    mfmjax.identify(at[0], ST, mf)
    mfmjax.search(at[0], **grid)
    with compiles() as names:
        model = mfmjax.identify(at[1], ST, mf)
        res = mfmjax.search(at[1], **grid)
    assert names == [], f"a new operating point compiled {names}"
    # noise-free: a_0 y = c at the level, to the quadrature's O(dt^4) (7e-10 relative here)
    assert float(model.offset) == pytest.approx(130.0 * float(model.a[0]), rel=1e-6)
    assert res.row(0)["n"] == 3


def test_observe_new_window_start_compiles_nothing(record):
    model = mfmjax.identify(record, ST, ModulatingFunction(4, 5, 2.6))
    mfmjax.observe(model, record, (5.0, 25.0))
    with compiles() as names:
        for start in (7.0, 11.5, 30.0):
            mfmjax.observe(model, record, (start, start + 20.0))
    assert names == []


def test_traced_h_beyond_its_bound_is_flagged_not_truncated(record):
    """h_max = 2.0 compiles a 48-sample kernel (bucket of 41): h up to 2.35 fits exactly; a traced
    h beyond that would be truncated, so it is flagged OUT_OF_BOUNDS instead."""

    @jax.jit
    def status(h):
        return mfmjax.identify(record, ST, ModulatingFunction(4, 5, h, h_max=2.0)).status

    assert int(status(2.2)) == 0  # above h_max but inside the compiled kernel: exact
    assert int(status(3.0)) & Status.OUT_OF_BOUNDS
    # and no numbers: the truncated kernels gave a plausible a (0.86, 1.10, 3.07 at h = 8
    # against 1.01, 3.53, 3.54 eagerly) and a finite E and dE/dh through `scores`
    far = jax.jit(lambda h: mfmjax.identify(record, ST, ModulatingFunction(4, 5, h,
                                                                           h_max=2.0)))(8.0)
    assert int(far.status) == Status.OUT_OF_BOUNDS and np.all(np.isnan(np.asarray(far.a)[:-1]))
    E = jax.jit(jax.value_and_grad(lambda h: mfmjax.scores(record, ST, h=h, N=4.0, M=5.0,
                                                           h_max=2.0)["E"]))
    assert all(np.isnan(float(v)) for v in E(8.0))
    # a traced dt below the record's own (longer kernels) or not positive, a delay past
    # delay_max: the same
    for dt in (0.02, -DT):
        bad = jax.jit(lambda dt: mfmjax.identify(eqx.tree_at(lambda s: s.dt, record, dt), ST,
                                                 ModulatingFunction(4, 5, 2.0)))(dt)
        assert int(bad.status) & Status.OUT_OF_BOUNDS and np.all(np.isnan(np.asarray(bad.a)[:-1]))
    late = jax.jit(lambda d: mfmjax.identify(eqx.tree_at(lambda s: s.delays, record, d), ST,
                                             ModulatingFunction(4, 5, 2.0), delay_max=0.5))
    assert np.all(np.isnan(np.asarray(late(jnp.array([5.0, 0.0])).a)[:-1]))


def test_traced_settings_outside_their_range_are_flagged_not_fitted(record):
    """Concrete N < n, h < 2 dt and negative delays are refused at the boundary; traced ones
    gave a wrong model with status ok (N = 2 < n = 3: a = [12.4, 12.5, 4.8, 1]; h = dt: a =
    [1.5, 7.8, 5.8, 1]; a delay of -0.3). They now give NaN coefficients and out_of_bounds,
    also through `scores`, and the valid values in the same program are unchanged. Traced
    delays alone no longer crash (the dependent-inputs check read them on the host)."""
    f = jax.jit(lambda N, M, h: mfmjax.identify(record, ST, ModulatingFunction(N, M, h,
                                                                              h_max=3.0)))
    good = f(4.0, 5.0, 2.6)
    assert int(good.status) == 0 and np.all(np.isfinite(np.asarray(good.a)))
    eager = mfmjax.identify(record, ST, ModulatingFunction(4, 5, 2.6))
    np.testing.assert_allclose(np.asarray(good.a), np.asarray(eager.a), rtol=1e-12)
    for N, M, h in ((2.0, 5.0, 2.6), (4.0, 2.5, 2.6), (4.0, 5.0, DT), (15.0, 6.0, 2.6)):
        bad = f(N, M, h)
        assert int(bad.status) == Status.OUT_OF_BOUNDS, (N, M, h)
        assert np.all(np.isnan(np.asarray(bad.a)[:-1])) and np.isnan(float(bad.J_rel))

    def with_delays(d):
        sig = eqx.tree_at(lambda s: s.delays, record, d)
        return mfmjax.identify(sig, ST, ModulatingFunction(4, 5, 2.6), delay_max=0.5)

    run = jax.jit(with_delays)
    ok = run(jnp.array([0.2, 0.0]))
    assert int(ok.status) == 0
    for d in ([-0.3, 0.0], [np.nan, 0.0]):
        assert int(run(jnp.array(d)).status) & Status.OUT_OF_BOUNDS, d
    E = jax.jit(lambda N: mfmjax.scores(record, ST, h=2.6, N=N, M=5.0)["E"])
    assert np.isfinite(float(E(4.0))) and np.isnan(float(E(2.0)))
    with pytest.raises(ValueError, match=r"scores\(\): N must be .*>= 3.*phi\^\(i\) must "
                                         "vanish at both ends"):
        mfmjax.scores(record, ST, h=2.6, N=2.0, M=5.0)  # eager: refused as identify does


@pytest.fixture(scope="module")
def noisy():
    sig = simulated_experiment(third_order_two_input(), dt=DT, n_samples=600, seed=5,
                               noise_std=0.02)
    return sig


def test_output_error_from_20_different_starts_compiles_once(noisy):
    starts = [mfmjax.identify(noisy, ST, ModulatingFunction(*s)) for s in _settings(20)]
    assert len({(float(m.mf.N), float(m.mf.M), float(m.mf.h)) for m in starts}) == 20
    mfmjax.output_error(noisy, starts[0], max_steps=30)
    with compiles() as names:
        fits = [mfmjax.output_error(noisy, m, max_steps=30) for m in starts[1:]]
    assert names == [], f"new starts compiled {names}"
    assert all(np.isfinite(f.E) and f.E <= f.E_start for f in fits)


def test_output_error_new_record_length_inside_a_bucket_compiles_nothing(noisy, monkeypatch):
    """`output_error` pads its window to the window's record bucket and the record to hold it
    (600 and 560 samples: 640); only the window's residuals count. A 560-sample record after
    the 600-sample one compiles nothing, and its fit is the unpadded program's (the padding
    switched off): the same estimate, both converged. Each stops within its tolerance (rtol
    1e-10 on steps scaled by |theta|; the rounding of longer sums can change the step count):
    theta within 1e-10 |theta| <= 1e-7 standard errors here (|theta| / se < 1e3), 1e-6 with a
    margin; E is quadratic at the minimum, so equal to rounding (1e-12); the standard errors
    move with theta (1e-8)."""
    import mfmjax._observers as ob  # `padded_window`, which output error pads with

    fit, ref = _padded_and_unpadded(mfmjax.output_error, ob, noisy, monkeypatch)
    assert fit.converged and ref.converged
    assert np.all(np.abs(ref.theta) < 1e3 * ref.std_errors)
    assert np.all(np.abs(fit.theta - ref.theta) <= 1e-6 * ref.std_errors)
    assert fit.E == pytest.approx(ref.E, rel=1e-12)
    np.testing.assert_allclose(fit.std_errors, ref.std_errors, rtol=1e-8)


def test_srivc_new_record_length_inside_a_bucket_compiles_nothing(noisy, monkeypatch):
    """`srivc` pads a concrete record to its bucket (600 and 560 samples: 640); only the
    record's own samples enter the IV system, E and sigma2. A 560-sample record after the
    600-sample one compiles nothing, and its fit equals the unpadded program's (the padding
    switched off): the same iterations on the same samples, the filters causal, only the
    lengths of the sums differ, so theta to 1e-10 relative norm-wise, E and sigma2 to 1e-12."""
    import mfmjax._srivc as sr

    fit, ref = _padded_and_unpadded(mfmjax.srivc, sr, noisy, monkeypatch)
    assert int(fit.status) == int(ref.status) == 0 and fit.iterations == ref.iterations
    assert np.max(np.abs(fit.theta - ref.theta)) <= 1e-10 * np.max(np.abs(ref.theta))
    assert float(fit.E) == pytest.approx(float(ref.E), rel=1e-12)
    assert float(fit.sigma2) == pytest.approx(float(ref.sigma2), rel=1e-12)


def test_scores_new_settings_compile_nothing(noisy):
    mfmjax.scores(noisy, ST, h=2.6, N=4, M=5, h_max=3.15)
    with compiles() as names:
        for N, M, h in _settings(5):
            out = mfmjax.scores(noisy, ST, h=h, N=N, M=M, h_max=3.15)
    assert names == []
    assert np.isfinite(float(out["E"]))


def test_new_sampling_interval_compiles_nothing(noisy):
    """dt is a value, like h: the same system sampled at 0.051 after 0.05 (600 samples; every
    kernel still inside its bucket, the support of h = 3.1 needing 61 and 63 samples of 64)
    compiles nothing in `identify`, `observe`, `simulate`, `search`, `scores`, `srivc`,
    `output_error`, `step_response` or `cramer_rao` (before, each compiled again: 13
    programs with `estimate`'s, which `test_estimate.py` checks). The new dt reaches the
    programs: the Gram at 0.051 equals the NumPy twin's at 0.051 to 1e-12 relative (as in
    `test_gram_equals_reference`), where the old dt would put it about 2 % off."""
    import reference as R

    from mfmjax._gram import gram, modulated_signals

    mf, grid = ModulatingFunction(4, 5, 2.6), dict(n=(3,), m=[[1], [1]], N=(4,), M=(5,),
                                                   h=(1.5, 3.1))

    def calls(sig):
        model = mfmjax.identify(sig, ST, mf)
        dt = float(sig.dt)
        out = [model, mfmjax.observe(model, sig).E, mfmjax.simulate(model, sig.u, dt=dt),
               mfmjax.search(sig, **grid).row(0)["E"],
               mfmjax.scores(sig, ST, h=2.6, N=4, M=5, h_max=3.15)["E"],
               mfmjax.srivc(sig, model).theta,
               mfmjax.output_error(sig, model, max_steps=30).theta,
               mfmjax.step_response(model).y,
               mfmjax.cramer_rao(model, sig.u, np.zeros(3), dt=dt, sigma=0.02)[1],
               gram(modulated_signals(sig, ST, mf))]
        return jax.block_until_ready(out)

    calls(noisy)
    other = simulated_experiment(third_order_two_input(), dt=0.051, n_samples=600, seed=5,
                                 noise_std=0.02)
    with compiles() as names:
        got = calls(other)
    assert names == [], f"a new dt compiled {names}"
    G, y, u = np.asarray(got[-1]), np.asarray(other.y), np.asarray(other.u)
    ref = R.gram(y, u, 0.051, 3, (1, 1), 4, 5, 2.6, other.intersample, (0.0, 0.0))
    assert np.max(np.abs(G - ref)) <= 1e-12 * np.max(np.abs(ref))
    old = R.gram(y, u, DT, 3, (1, 1), 4, 5, 2.6, other.intersample, (0.0, 0.0))
    assert np.max(np.abs(G - old)) > 1e-3 * np.max(np.abs(ref))  # the check can tell them apart


def test_a_model_of_the_same_orders_from_any_source_compiles_nothing(record):
    """A model of the same orders compiles nothing, whether identified, built from coefficients
    or loaded: `identify` returned a weak-typed float for a model without an offset term
    (`jnp.asarray(0.0)` in its program), the other sources a float64, and the weak type is
    part of a program's key, so observing a given model after an identified one compiled the
    observer again (and `moving_final_states`, `cramer_rao` and `frequency_response` theirs).
    The same coefficients give the same E (the same program on the same values)."""
    model = mfmjax.identify(record, ST, ModulatingFunction(4, 5, 2.6))
    window = (10.0, 50.0)
    first = mfmjax.observe(model, record, window)
    mfmjax.frequency_response(model)
    given = mfmjax.Model.from_coefficients(np.asarray(model.a), [np.asarray(b) for b in model.b],
                                           intersample=record.intersample)
    with compiles() as names:
        again = mfmjax.observe(given, record, window)
        mfmjax.frequency_response(given)
    assert names == [], f"a given model compiled {names}"
    assert float(again.E) == float(first.E)


def test_online_identifier_compiles_its_programs_once_per_run(monkeypatch):
    """Identification windows are padded to `OnlineConfig.window_bound`: with n_start = 8 and
    n_reident = 6 both windows fit the 8-interval record (the 6-interval one does not fit in
    half of it), so each program is compiled once in a run, whatever the window length and
    however many identifications it does."""
    import mfmjax._online as online

    windows = []
    real = online.run_plan
    monkeypatch.setattr(online, "run_plan", lambda plan, sig: windows.append(
        (sig.n_samples, int(plan.where["v_valid"]))) or real(plan, sig))
    t, y, u, switches = switching_experiment()
    cfg = OnlineConfig(dt=1.0, n_inputs=2, n=(2,), intersample=("foh", "zoh"), n_reident=6)
    assert cfg.window_bound(6) == cfg.window_bound(8) == 2000 and cfg.window_bound(4) == 1000
    ident = OnlineIdentifier(cfg)
    with compiles() as names:
        for c0 in range(0, len(t), 250):
            ident.update(t[c0 : c0 + 250], y[c0 : c0 + 250], u[c0 : c0 + 250])
    assert {n for n, _ in windows} == {2000}  # one padded record length
    assert {w for _, w in windows} == {2000, 1500}  # windows of 8 and 6 intervals
    assert len(windows) >= 4  # several identifications
    for program in ("jit(evaluate_chunk)", "jit(_score)", "jit(_predict)"):
        assert names.count(program) <= 1, (program, names.count(program), windows)


def test_online_identifier_new_names_and_t0_compile_nothing():
    """Column names and t0 are labels for the on-line identifier too: a run under other names
    and another start time, after a run of the same configuration, compiles nothing (its
    windows went into `_predict` and `_score` labelled with the names: 2 programs, 1.6 s,
    each time the names changed, in the CLI with every other set of column names). The same
    data give the same models."""
    t, y, u, _ = switching_experiment()

    def run(names, t0):
        cfg = OnlineConfig(dt=1.0, n_inputs=2, n=(2,), intersample=("foh", "zoh"), n_reident=6,
                           output_name=names[0], input_names=names[1:])
        ident = OnlineIdentifier(cfg)
        for c0 in range(0, len(t), 250):
            ident.update(t0 + t[c0 : c0 + 250], y[c0 : c0 + 250], u[c0 : c0 + 250])
        return ident

    first = run(("y", "u1", "u2"), 0.0)
    with compiles() as names:
        other = run(("temperature", "valve", "pump"), 1000.0)
    assert names == [], f"new names and t0 compiled {names}"
    assert len(other.models) == len(first.models) >= 2
    for a, b in zip(first.models, other.models):
        np.testing.assert_array_equal(np.asarray(a["a"]), np.asarray(b["a"]))
    assert other.model().output_name == "temperature" and other.mse() == first.mse()


def test_output_error_new_step_limit_compiles_nothing(noisy):
    """max_steps, rtol and atol are values of the compiled Levenberg-Marquardt loop."""
    start = mfmjax.identify(noisy, ST, ModulatingFunction(*_settings(1)[0]))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # 3 or 5 steps may not converge: not this test's claim
        mfmjax.output_error(noisy, start, max_steps=3)
    with compiles() as names, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fit = mfmjax.output_error(noisy, start, max_steps=5, rtol=1e-9, atol=1e-11)
    assert names == [], f"a new step limit compiled {names}"
    assert fit.steps <= 5


def test_scores_new_record_and_window_lengths_inside_a_bucket_compile_nothing(noisy):
    """`scores` pads the validation window to its record bucket and the record to hold it (as
    `observe`): a record of 560 samples after one of 600 (bucket 640), and a validation window
    of 441 samples with an observer window after one of 421 (bucket 448), compile nothing. Only
    the record's and the window's own samples count: the scores equal the unpadded program's
    (`_scores` at the record's own length) to the rounding of the Gram's and the observer's
    sums in another order, amplified by the Gram's conditioning: 1e-10 relative, the bound of
    `identify`'s padding test on theta (measured: 5e-14); the status is the same."""
    import jax.numpy as jnp

    from mfmjax._quadrature import kernel_bucket, kernel_length
    from mfmjax._refine import _scores_jit

    setting = dict(h=2.6, N=4, M=5)
    mfmjax.scores(noisy, ST, **setting)
    mfmjax.scores(noisy, ST, validate=(5.0, 26.0), **setting)  # 421 samples, bucket 448
    short = _head(noisy, 560)
    with compiles() as names:
        runs = [mfmjax.scores(short, ST, **setting),
                mfmjax.scores(short, ST, validate=(3.0, 25.0), observer_window=8.0, **setting)]
    assert names == [], f"a new record and window length compiled {names}"
    kernel = kernel_bucket(kernel_length(2.6, DT))
    p = ST.n_params
    for out, (v0, length, ob) in zip(runs, [(0, 560, 560), (60, 441, 161)]):
        ref = _scores_jit(short.unlabelled(), ST, jnp.asarray(2.6), jnp.asarray(4.0),
                          jnp.asarray(5.0), short.delays, jnp.ones(p), kernel,
                          jnp.asarray(v0, dtype=jnp.int32), length, ob)[0]
        assert int(out["status"]) == int(ref["status"]) == 0
        for key in ("J", "J_rel", "E", "fit"):
            assert float(out[key]) == pytest.approx(float(ref[key]), rel=1e-10), key


def test_refine_new_record_length_inside_a_bucket_compiles_nothing(noisy, monkeypatch):
    """`refine` scores its settings on the record and validation window padded as in `scores`
    (600 and 560 samples: 640): a 560-sample record after the 600-sample one compiles nothing,
    and the refinement equals the unpadded one (padding switched off): the same BFGS path up
    to the rounding of the scores (5e-14 relative, `scores` test above), which six BFGS steps
    do not amplify here (measured 9e-14); checked to 1e-10 relative on the path, the refined
    settings and the returned score, with the same step count and result."""
    import mfmjax._observers as ob  # `padded_window`, which refine pads with

    def fit(sig, start):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # a short run may stop on max_steps: compared
            # h's box given: its default upper end is a third of the record's duration, which
            # would set another kernel bound (a static size) for the shorter record
            return mfmjax.refine(sig, start, vary=("h", "N"), bounds={"h": (0.7, 4.0)},
                                 max_steps=6)

    got, ref = _padded_and_unpadded(fit, ob, noisy, monkeypatch)
    assert got.steps == ref.steps and got.result == ref.result
    np.testing.assert_allclose(got.path, ref.path, rtol=1e-10)
    for key in ("h", "N"):
        assert got.settings[key] == pytest.approx(ref.settings[key], rel=1e-10), key
    assert got.value == pytest.approx(ref.value, rel=1e-10)


def test_refine_new_tolerances_compile_nothing(noisy):
    """`refine`'s rtol and atol are values: optimistix keeps them as fields of the BFGS solver,
    a static argument of the step programs, so as Python floats every new tolerance compiled
    its three BFGS programs again (4.3-4.6 s). They reach the program: the looser tolerance
    stops in fewer steps (3 against 19 here), both converged."""
    start = mfmjax.identify(noisy, ST, ModulatingFunction(4, 5, 2.6))
    kw = dict(vary=("h", "N"), bounds={"h": (0.7, 4.0)}, max_steps=40)  # as the test above
    tight = mfmjax.refine(noisy, start, rtol=1e-3, atol=1e-5, **kw)
    with compiles() as names:
        loose = mfmjax.refine(noisy, start, rtol=0.1, atol=0.1, **kw)
    assert names == [], f"new tolerances compiled {names}"
    assert tight.converged and loose.converged and loose.steps < tight.steps


def test_first_calls_run_no_eager_programs(noisy, tmp_path):
    """`scores`, `refine` and `moving_final_states` move their settings, windows and results
    between host and device without compiling anything outside their jitted programs (each
    eager operation on a device array is a program of its own, tens of ms on a first call:
    `jnp.asarray` of the settings, the refined settings' sigmoid and the window ends cost
    2, 5 and 6 of them), and the host-side paths compile nothing at all (`state_space` ran 29
    eager programs, 0.9 s on its first call; `detrend` 13, `load_model` 8). JAX's in-memory
    caches are dropped before each call, so an eager program compiled by an earlier call or
    test would show again. The one conversion left in `refine` is optimistix's: its BFGS
    step compares an equinox enumeration while it is traced (`equinox/_enum.py`,
    `__eq__`)."""
    from jaxlog import eager

    start = mfmjax.identify(noisy, ST, ModulatingFunction(4, 5, 2.6))
    calls = {
        "scores": lambda: mfmjax.scores(noisy, ST, h=2.6, N=4, M=5),
        "refine": lambda: mfmjax.refine(noisy, start, vary=("h", "N"), bounds={"h": (0.7, 4.0)},
                                        max_steps=6),
        "moving_final_states": lambda: mfmjax.moving_final_states(start, noisy, 5.0,
                                                                  [10.0, 20.0, 29.0]),
    }
    path = tmp_path / "model.json"
    mfmjax.save_model(start, path)
    calls.update({  # host work: NumPy on the device, no program at all
        "Model.from_coefficients": lambda: mfmjax.Model.from_coefficients([2.0, 3.0, 1.0],
                                                                          [[1.0]], offset=0.5),
        "load_model": lambda: mfmjax.load_model(path),
        "state_space": lambda: mfmjax.state_space(start),
        "Signals.t": lambda: noisy.t,
        "detrend": lambda: mfmjax.detrend(noisy)[1].apply(_head(noisy, 500)),
        "fit_percent": lambda: mfmjax.fit_percent(noisy.y, 0.9 * np.asarray(noisy.y)),
    })
    allowed = {"refine": ["jit(convert_element_type)"]}
    for name, call in calls.items():
        jax.clear_caches()
        with compiles() as names, warnings.catch_warnings():
            warnings.simplefilter("ignore")  # a short refine may stop on max_steps
            jax.block_until_ready(jax.tree.leaves(call()))
        assert eager(names) == allowed.get(name, []), (name, names)
        if name[0].isupper() or name in ("load_model", "state_space", "detrend", "fit_percent"):
            assert names == [], (name, names)


def test_refine_of_a_search_result_compiles_one_program_for_its_candidates(noisy):
    """`refine(signals, result, top=k)` sizes the kernels of its k runs for the largest of
    their boxes: two candidates of one structure at h = 1.5 and 3.1 (default h boxes up to 6
    and 9.98 s: kernel buckets 128 and 256 samples) share one BFGS step program; refined one
    at a time they compiled two. A longer kernel adds exact zeros beyond the support, so each
    run's score equals the lone run's to the rounding of longer sums over a few BFGS steps
    (measured 4e-14 relative; checked to 1e-9)."""
    from mfmjax import _executables

    res = mfmjax.search(noisy, n=(3,), m=[[1], [1]], N=(4,), M=(5,), h=(1.5, 3.1))
    assert sorted(res.columns["h"]) == [1.5, 3.1]
    kw = dict(vary=("h",), max_steps=4)
    jax.clear_caches()
    _executables.clear()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # 4 steps may not converge: not this test's claim
        with compiles() as names:
            best = mfmjax.refine(noisy, res, top=2, **kw)
        alone = [mfmjax.refine(noisy, res.best(i), **kw) for i in range(2)]
    assert names.count("jit(_bfgs_step)") == 1, names
    assert best.value == pytest.approx(min(r.value for r in alone), rel=1e-9)
