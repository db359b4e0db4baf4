import json
import os
import re
import subprocess
import sys
import warnings

import jax
import numpy as np
import pytest

import mfmjax
from mfmjax import ModulatingFunction, Signals, Structure, _batch
from mfmjax._search import _engine
from mfmjax._search._engine import chunk_jit as _chunk_jit
from mfmjax._status import describe
from mfmjax.datasets import simulated_experiment, third_order_two_input

HERE = os.path.dirname(__file__)


@pytest.fixture(scope="module")
def noisy():
    return simulated_experiment(third_order_two_input(), dt=0.01, n_samples=1500,
                                x0=[0.1, 0.2, 0.3], noise_std=0.01, seed=4)


@pytest.fixture(scope="module")
def clean():
    return simulated_experiment(third_order_two_input(), dt=0.01, n_samples=1500,
                                x0=[0.1, 0.2, 0.3])


def _params(a, b):
    return np.concatenate([np.asarray(a)] + [np.asarray(x) for x in b])


def test_every_candidate_equals_identify(noisy):
    # m_k = n (feed-through correction) and a delay grid included; same maths as identify,
    # differing only in kernel padding and summation order: 1e-8 where well conditioned
    res = mfmjax.search(noisy, n=(1, 3), N=(3,), M=(3, 4), h=(1.5,), m=[(0, 1, 3), (0,)],
                        delays=[(0.0,), (0.0, 0.05)])
    assert len(res) == 4 * (2 + 3)  # 4 groups (M x delays); n=1: m1 in {0,1}; n=3: {0,1,3}
    rows = [res.row(i) for i in range(len(res))]
    res_rank = {id(r): i for i, r in enumerate(rows)}
    # every structure at one (M, delays) group, and every group for the m_k = n structure
    # (each identify call compiles: the full cross product adds nothing but time)
    rows = [r for r in rows if (r["M"] == 4 and r["delays"] == [0.0, 0.0])
            or (r["n"] == 3 and r["m"][0] == 3)]
    assert len(rows) == 5 + 3
    for r in rows:
        sig = Signals(noisy.y, noisy.u, dt=0.01, intersample=("foh", "zoh"), delays=r["delays"])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            mod = mfmjax.identify(sig, Structure(r["n"], r["m"]),
                                  ModulatingFunction(r["N"], r["M"], r["h"]))
        assert r["status"] == describe(int(mod.status)), r
        if float(mod.cond) < 1e12:
            ref = _params(mod.a, mod.b)
            got = _params(r["a"], r["b"])
            assert np.max(np.abs(got - ref)) <= 1e-8 * np.max(np.abs(ref)), r
        if float(mod.cond) < 1e8:
            # both from conditioning_eigvals (1e-4 relative) on Grams equal to rounding
            # amplified by cond (< 1e-8): 1e-3
            best = res.best(res_rank[id(r)])
            assert abs(float(best.cond) - float(mod.cond)) <= 1e-3 * float(mod.cond)
        assert abs(r["J"] - float(mod.J_rel)) <= 1e-6 * float(mod.J_rel) + 1e-14
        # E of the search equals the observer + simulation of the identified model
        if r["status"] == "ok":
            E = float(mfmjax.performance_index(mod, sig))
            assert abs(r["E"] - E) <= 1e-6 * E + 1e-12


def test_search_without_input():
    """An autonomous record (K = 0, a free response from x0): the search runs (its reshapes
    could not infer the empty inputs' axis: ZeroDivisionError inside JAX) and every candidate
    equals `identify` of its structure (the same maths, kernels padded and summed in another
    order: 1e-8 where well conditioned, as `test_every_candidate_equals_identify`)."""
    true = mfmjax.Model.from_coefficients([2.0, 0.6, 1.0], [])
    y = np.asarray(mfmjax.simulate(true, np.zeros((2000, 0)), [1.0, 0.5], dt=0.01))
    sig = Signals(y + 1e-3 * np.random.default_rng(2).standard_normal(2000), dt=0.01)
    res = mfmjax.search(sig, n=(1, 2), N=(3,), M=(3, 4), h=(2.0, 3.0))
    assert len(res) == 2 * 2 * 2 and res.row(0)["n"] == 2
    for i in range(len(res)):
        r = res.row(i)
        mod = mfmjax.identify(sig, Structure(r["n"]), ModulatingFunction(r["N"], r["M"], r["h"]))
        assert float(mod.cond) < 1e12
        ref = np.asarray(mod.a)
        assert np.max(np.abs(np.asarray(r["a"]) - ref)) <= 1e-8 * np.max(np.abs(ref)), r


def test_best_by_E_has_true_orders(clean):
    res = mfmjax.search(clean, n=(1, 2, 3, 4), N=(4, 5), M=(4, 5), h=(1.5, 2.0),
                        m=[(0, 1, 2), (0, 1, 2)])
    best = res.row(0)
    assert (best["n"], best["m"]) == (3, [1, 0])
    model = res.best()
    assert isinstance(model, mfmjax.Model) and model.n == 3
    assert np.allclose(np.asarray(model.a), [1.0, 3.5, 3.5, 1.0], rtol=1e-4)
    # device=False: the same model with NumPy arrays (no transfer), leaf by leaf bitwise
    host = res.best(0, device=False)
    assert isinstance(host.a, np.ndarray) and isinstance(model.a, jax.Array)
    assert jax.tree.structure(host) == jax.tree.structure(model)
    for x, y in zip(jax.tree.leaves(host), jax.tree.leaves(model)):
        if isinstance(y, jax.Array):  # (the settings N, M, h are Python numbers in both)
            assert isinstance(x, np.ndarray) and x.dtype == y.dtype
        np.testing.assert_array_equal(x, np.asarray(y))
    # the other scores rank sensibly too
    for score in ("J", "fit", "aic", "bic"):
        r = mfmjax.search(clean, n=(1, 2, 3), N=(4,), M=(4,), h=(2.0,), m=[(0, 1), (0,)],
                          score=score)
        assert r.row(0)["n"] == 3


def test_search_warns_when_its_best_cannot_be_trusted(noisy):
    """The grid of `test_every_candidate_equals_identify` (its program) on (i) the plant with a
    0.1 s delay on input 2, searched on (0, 0.05): the best delay is the grid's largest, said
    by name (the best delay may lie beyond it); (ii) a constant input 2: every candidate is
    flagged no_excitation, said once (best() returns a flagged model); (iii) the record
    itself: neither."""
    from mfmjax.datasets import third_order_two_input

    grid = dict(n=(1, 3), N=(3,), M=(3, 4), h=(1.5,), m=[(0, 1, 3), (0,)],
                delays=[(0.0,), (0.0, 0.05)])
    truth = third_order_two_input()
    late = simulated_experiment(mfmjax.Model.from_coefficients(
        truth.a, truth.b, intersample=("foh", "zoh"), delays=[0.0, 0.1]), dt=0.01,
        n_samples=1500, x0=[0.1, 0.2, 0.3], noise_std=0.01, seed=4)
    flat = Signals(noisy.y, np.column_stack([noisy.u[:, 0], np.ones(1500)]), dt=0.01,
                   intersample=("foh", "zoh"))
    for sig, want in ((late, "best candidate: the delay of 'u2' (0.05) is the largest of its "
                              "grid (0..0.05)"),
                      (flat, "every one of the 20 candidates is flagged (the best: "
                             "no_excitation)"),
                      (noisy, None)):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            res = mfmjax.search(sig, **grid)
        said = [w for w in caught if "search()" in str(w.message)]
        assert all(w.filename == __file__ for w in said)  # the user's line
        said = [str(w.message) for w in said]
        assert len(said) == (want is not None) and (want is None or want in said[0]), said
        assert (int(res.best().status) != 0) == (sig is flat)


def test_search_validates_apart_bitwise_and_a_new_grid_compiles_its_solves_only(noisy):
    """`search` simulates its candidates (E, eq. 17) in a program of its own
    (`plan_search(apart=True)`, `validate_blocks`): every column equals, bitwise and in dtype,
    the chunk that validates inside itself (as `estimate` and the on-line identifier run it),
    with a last chunk padded by a repeated setting (not simulated apart) and chunks of 112
    and 56 candidates (blocks of 32: partly filled); and a new grid of the same largest order
    on the record compiles its chunk only."""
    from jaxlog import compiles

    from mfmjax import _executables
    from mfmjax._search import plan_search, run_plan

    grid = dict(n=(1, 2, 3), N=(3, 4), M=(3, 4), h=(1.0, 1.3, 1.6), chunk_size=2)
    # an earlier test may hold this record's validation program (as between test modules)
    jax.clear_caches()
    _executables.clear()
    with compiles() as first:
        res = mfmjax.search(noisy, **grid)
    # each once: the validation program compiles on a second thread during the first chunk's
    # compile, and the chunk waits for it (it once compiled it a second time itself)
    assert first.count("jit(evaluate_chunk)") == first.count("jit(validate_blocks)") == 1
    with compiles() as new_grid:
        other = mfmjax.search(noisy, n=(2, 3), N=(4, 5), M=(3, 4), h=(1.2,), chunk_size=2)
    assert "jit(evaluate_chunk)" in new_grid and "jit(validate_blocks)" not in new_grid
    assert len(other) == 4 * (4 + 9) and np.isfinite(other.columns["E"]).any()
    kw = dict(grid, m=None, delays=None, score="E", validate=None, observer_window=None,
              eta=None, simulate=True, split=True)
    inside = run_plan(plan_search(noisy, **kw), noisy, once=True)
    assert len(res) == len(inside) == 3 * 4 * 14
    for key, col in res.columns.items():
        col, ref = np.asarray(col), np.asarray(inside.columns[key])
        assert col.dtype == ref.dtype, key
        np.testing.assert_array_equal(col, ref, err_msg=key)
    with pytest.raises(ValueError, match="one record at a time"):
        run_plan(plan_search(noisy, **kw, apart=True), noisy, records=[noisy, noisy])


def test_one_compilation_for_many_chunks(noisy, monkeypatch):
    """Chunks of a compiled program run on a thread per core (the first run of a program
    runs its first chunk alone): every run writes the same columns, bitwise, as one thread."""
    kw = dict(n=(1, 2), N=(3, 4), M=(3, 4), h=(1.0, 1.2, 1.3, 1.5, 1.7), m=[(0,), (0,)],
              chunk_size=2)
    first = mfmjax.search(noisy, **kw)  # 5 (h, delays) settings -> 3 chunks
    before = _chunk_jit._cached._cache_size()
    calls = []
    res = mfmjax.search(noisy, progress=lambda d, t: calls.append((d, t)), **kw)
    assert _chunk_jit._cached._cache_size() == before
    assert calls[-1] == (5, 5) and len(calls) == 3 and len(res) == 5 * 4 * 2
    assert [d for d, _ in calls] == sorted(d for d, _ in calls)  # done only grows
    monkeypatch.setattr(_batch, "WORKERS", 1)
    one = mfmjax.search(noisy, **kw)
    whole = mfmjax.search(noisy, **dict(kw, chunk_size=5))  # one chunk: no threads
    for key, col in whole.columns.items():
        for other in (first, res, one):
            np.testing.assert_array_equal(other.columns[key], col, err_msg=key)


def test_bad_candidate_is_flagged_not_fatal(clean):
    u = np.asarray(clean.u).copy()
    u[:, 1] = 1.0  # constant second input: no excitation
    sig = Signals(clean.y, u, dt=0.01, intersample=("foh", "zoh"))
    res = mfmjax.search(sig, n=(1, 2), N=(3,), M=(3,), h=(1.5,), m=[(0,), (0, 1)])
    statuses = {res.row(i)["status"] for i in range(len(res))}
    assert any("no_excitation" in s for s in statuses)
    assert all(np.isfinite(res.columns["theta"]).all(axis=1) | (res.columns["status"] != 0))


def test_exports(noisy, tmp_path):
    res = mfmjax.search(noisy, n=(1, 2), N=(3,), M=(3,), h=(1.5,), m=[(0,), (0,)])
    doc = json.loads(res.to_json(tmp_path / "r.json"))
    assert doc["candidates"] == len(res) == len(doc["ranked"])
    assert json.loads((tmp_path / "r.json").read_text())["ranked"][0]["rank"] == 1
    # the labels the rows' delays and b refer to (a saved table named no column)
    assert (doc["output_name"], doc["input_names"], doc["intersample"], doc["has_offset"]) == (
        noisy.output_name, list(noisy.input_names), list(noisy.intersample), noisy.offset)
    pd = pytest.importorskip("pandas")
    df = res.to_pandas()
    assert isinstance(df, pd.DataFrame) and len(df) == len(res) and "fit" in df.columns
    assert "rank" in res.table(3)


@pytest.mark.parametrize(
    "kw,match",
    [
        (dict(h=()), "h grid is empty"),
        (dict(h=(1.0,), n=()), "n grid is empty"),
        (dict(h=(1.0,), n=(4,), N=(3,), M=(3,)), "every candidate has N < n"),
        (dict(h=(20.0,)), "too few valid samples"),
        (dict(h=(-1.0,)), "h values must be finite and > 0"),
        (dict(h=(1.0,), score="xyz"), "unknown score"),
        (dict(h=(1.0,), m=[(0,)]), "m needs one list"),
        (dict(h=(1.0,), delays=[(0.0,), (-1.0,)]), r"delays\[1\]\[0\] must be >= 0"),
        (dict(h=(1.0,), validate=(0.0, 100.0)), "validate window"),
        (dict(h=(1.0,), chunk_size=0), "chunk_size must be an integer >= 1"),
        # a flat list on two inputs read as one value per input ("try 0 and 0.5" as likely
        # meant; OnlineConfig refuses a flat m too)
        (dict(h=(1.0,), delays=(0.0, 0.5)),
         r"delays=\[0\.0, 0\.5\] is a flat list; give one list per input \(2\): e.g. "
         r"delays=\[\(0.0, 0.5\), ...\] .* or delays=\[\(0.0,\), \(0.5,\)\] for one value"),
        (dict(h=(1.0,), m=(0, 1)), r"m=\[0, 1\] is a flat list"),
        # eta = 1 on a_3 alone (the unit-free choice for n = 3) leaves n = 2 no nonzero
        # entry: its candidates came back flagged (nonfinite, a_n_zero, unstable), unsaid
        (dict(h=(1.0,), n=(2, 3), m=[(0,), (0,)], eta=[0, 0, 0, 1, 0, 0, 0]),
         r"eta is zero on every column of 1 of the 2 structures \(the first: n=2, m=\[0, 0\]\)"
         r".*leave them out of the grid"),
    ],
)
def test_bad_grids(noisy, kw, match):
    with pytest.raises(ValueError, match=match):
        mfmjax.search(noisy, **kw)


def test_sharded_equals_single_device(noisy, tmp_path):
    kw = dict(n=(1, 2, 3), N=(3, 4), M=(3, 4), h=(1.2, 1.7), m=[(0, 1), (0,)], chunk_size=4)
    single = mfmjax.search(noisy, **kw)
    np.save(tmp_path / "y.npy", np.asarray(noisy.y))
    np.save(tmp_path / "u.npy", np.asarray(noisy.u))
    script = f"""
import json, numpy as np, jax
import mfmjax
assert len(jax.devices()) == 4, jax.devices()
sig = mfmjax.Signals(np.load({str(tmp_path / 'y.npy')!r}), np.load({str(tmp_path / 'u.npy')!r}),
                     dt=0.01, intersample=("foh", "zoh"))
res = mfmjax.search(sig, **{kw!r})
print(json.dumps(res.to_dict()))
"""
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=4")
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env,
                         timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    sharded = json.loads(out.stdout.strip().splitlines()[-1])["ranked"]
    ref = single.to_dict()["ranked"]
    assert len(sharded) == len(ref)
    by_key = {(r["n"], tuple(r["m"]), r["N"], r["M"], r["h"]): r for r in ref}
    for a in sharded:
        b = by_key[(a["n"], tuple(a["m"]), a["N"], a["M"], a["h"])]
        # same program on another device layout: equal to rounding of the reductions
        assert np.allclose(np.concatenate([a["a"]] + a["b"]), np.concatenate([b["a"]] + b["b"]),
                           rtol=1e-10, atol=0)


def test_equation_error_only_mode(noisy):
    # two chunks, so that both run at the default compile options (a J-only grid that fits in
    # one chunk is compiled at level 0: rounding-equal,
    # test_one_chunk_J_search_is_compiled_for_compile_time)
    kw = dict(n=(1, 2, 3), N=(4,), M=(4,), h=(1.5, 1.7), m=[(0, 1), (0,)], chunk_size=1)
    full = mfmjax.search(noisy, score="J", **kw)
    fast = mfmjax.search(noisy, score="J", simulate=False, **kw)
    for extra in (dict(validate=(1.0, 10.0)), dict(observer_window=1.0)):  # (ignored, unsaid)
        with pytest.raises(ValueError, match=r"search\(\): validate= and observer_window= set "
                                             r"where E and fit are scored, which simulate=False "
                                             r"skips"):
            mfmjax.search(noisy, score="J", simulate=False, **kw, **extra)
    # the same solves in two programs (with and without the validation): XLA may order the
    # offset's centring sums (`signal_levels`) differently in each, so they agree to rounding
    # (7e-16 relative seen; 1e-12 as test_one_chunk_J_search_is_compiled_for_compile_time),
    # and rank alike
    theta, fast_theta = full.columns["theta"], fast.columns["theta"]
    assert np.max(np.abs(theta - fast_theta)) <= 1e-12 * np.max(np.abs(theta))
    assert np.array_equal(full.rank, fast.rank)
    assert np.all(np.isnan(fast.columns["E"]))
    with pytest.raises(ValueError, match="needs simulate=True"):
        mfmjax.search(noisy, score="E", simulate=False, **kw)


def test_one_chunk_J_search_is_compiled_for_compile_time(noisy, monkeypatch):
    """`search` runs a J-only grid that fits in one chunk (at most `chunk_size` settings,
    split over the cores: one chunk per core) through the program compiled at XLA's backend
    level 0 (`RUN_ONCE_OPTIONS`: it runs once) and a grid of several chunks through the
    default one; both give the same candidates to rounding (the same arithmetic, other
    instruction selection: 1e-12 relative norm-wise on theta and J, equal rankings)."""
    monkeypatch.setattr(_batch, "WORKERS", 2)  # two cores, whatever the machine
    used = []
    for name in ("chunk_jit", "chunk_jit_once"):
        fn = getattr(_engine, name)
        monkeypatch.setattr(_engine, name, lambda *a, _fn=fn, _n=name: used.append(_n) or _fn(*a))
    kw = dict(n=(1, 2, 3), N=(4,), M=(4, 5), h=(1.5, 1.7, 1.9), m=[(0, 1), (0,)], score="J",
              simulate=False)
    once = mfmjax.search(noisy, **kw)  # 3 settings: chunks of 2 (one padded), one per core
    assert used == ["chunk_jit_once"] * 2
    chunked = mfmjax.search(noisy, chunk_size=1, **kw)  # three chunks: the default program
    assert used[2:] == ["chunk_jit"] * 3
    for key in ("theta", "J"):
        a, b = np.asarray(once.columns[key]), np.asarray(chunked.columns[key])
        assert np.max(np.abs(a - b)) <= 1e-12 * np.max(np.abs(b)), key
    for key in ("n", "m", "N", "M", "h"):  # the same ranking
        np.testing.assert_array_equal(once.columns[key], chunked.columns[key])


def test_two_process_loopback_equals_single(tmp_path):
    # multi-host use: jax.distributed over two local processes (one CPU device each)
    script = tmp_path / "worker.py"
    script.write_text("""
import sys, json, jax
jax.distributed.initialize(coordinator_address="127.0.0.1:" + sys.argv[2], num_processes=2,
                           process_id=int(sys.argv[1]))
import mfmjax
from mfmjax.datasets import simulated_experiment, third_order_two_input
sig = simulated_experiment(third_order_two_input(), dt=0.01, n_samples=800, noise_std=0.01,
                           seed=4)
res = mfmjax.search(sig, n=(1, 2, 3), N=(3, 4), M=(3, 4), h=(1.2, 1.7), m=[(0, 1), (0,)])
print("RESULT" + json.dumps({"devices": len(jax.devices()), "ranked": res.to_dict()["ranked"]}))
""")
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = str(sock.getsockname()[1])
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    procs = [subprocess.Popen([sys.executable, str(script), str(i), port], env=env,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for i in range(2)]
    outs = [p.communicate(timeout=600) for p in procs]
    docs = []
    for p, (out, err) in zip(procs, outs):
        assert p.returncode == 0, err[-2000:]
        docs.append(json.loads([ln for ln in out.splitlines() if ln.startswith("RESULT")][-1][6:]))
    assert docs[0]["devices"] == 2 and docs[0]["ranked"] == docs[1]["ranked"]
    sig = simulated_experiment(third_order_two_input(), dt=0.01, n_samples=800, noise_std=0.01,
                               seed=4)
    single = mfmjax.search(sig, n=(1, 2, 3), N=(3, 4), M=(3, 4), h=(1.2, 1.7),
                           m=[(0, 1), (0,)]).to_dict()["ranked"]
    # compare candidate by candidate (near-ties may swap ranks at rounding level)
    def key(r):
        return (r["n"], tuple(r["m"]), r["N"], r["M"], r["h"])

    ref = {key(r): r for r in single}
    assert len(ref) == len(docs[0]["ranked"])
    for a in docs[0]["ranked"]:
        assert np.allclose(a["a"], ref[key(a)]["a"], rtol=1e-10, atol=0)


def test_best_by_J_on_noise_free_data_has_true_orders(clean):
    # over-parameterised structures fit noise-free data to rounding too: J below
    # sqrt(p eps) (the float64 noise of the quadratic form, scale-free) is a tie that goes to
    # fewer parameters, so rounding noise cannot pick a larger order
    res = mfmjax.search(clean, n=(2, 3, 4, 5), N=(5, 6), M=(5, 6), h=(1.5, 2.0),
                        m=[(0, 1), (0,)], score="J", simulate=False)
    c = res.columns
    assert np.min(c["J"][c["n"] > 3]) < np.min(c["J"][c["n"] == 3])  # the trap is real
    assert (res.row(0)["n"], res.row(0)["m"]) == (3, [1, 0])


def test_small_grid_is_split_over_the_cores_for_search_only(noisy, monkeypatch):
    """A grid that fits in one chunk is cut into one chunk per core when `search` plans it
    (its later calls run on every core); other callers (the on-line identifier, `estimate`)
    plan grids of many sizes and keep one chunk each, so that sizes do not multiply the
    compiled chunk shapes."""
    from mfmjax._search import plan_search

    monkeypatch.setattr(_batch, "WORKERS", 2)
    kw = dict(n=(1, 2), N=(3,), M=(3,), h=(1.0, 1.2, 1.3), m=None, delays=None, score="J",
              validate=None, observer_window=None, eta=None, chunk_size=8, simulate=False)
    for split, chunk in ((False, 3), (True, 2)):
        plan = plan_search(noisy, split=split, **kw)
        assert plan.small and plan.chunk == chunk and len(plan.hd) == 3
    assert not plan_search(noisy, split=True, **dict(kw, chunk_size=2)).small


def test_table_and_to_dict_check_top(clean):
    """`table(0)` and `table(-1)` printed the header alone, `to_dict(-1)` no rows, `top=1.5`
    a bare TypeError and `top=True` one row: `top` is checked as `best`'s index is."""
    res = mfmjax.search(clean, n=(1, 2, 3), N=(4,), M=(4,), h=(2.0,), m=[(0, 1), (0,)],
                        score="J")  # the grid of test_best_by_E_has_true_orders: its program
    for top, kind, said in ((0, ValueError, "must be an integer >= 1 (got top=0)"),
                            (-1, ValueError, "must be an integer >= 1 (got top=-1)"),
                            (1.5, ValueError, "must be an integer (got top=1.5)"),
                            (True, TypeError, "top"), ("3", TypeError, "top")):
        for name, fn in (("table", res.table), ("to_dict", res.to_dict),
                         ("to_json", lambda t: res.to_json(top=t))):  # (to_json said to_dict)
            with pytest.raises(kind, match=rf"SearchResult\.{name}\(\): top "
                               + re.escape(said) if kind is ValueError else said):
                fn(top)
    assert len(res.table(2).splitlines()) == 3 and len(res.to_dict(2)["ranked"]) == 2
    # None: every candidate, as to_dict(top=None) (it raised a bare TypeError)
    assert len(res.table(None).splitlines()) == len(res) + 1


def _level_record(T=2000, seed=1):
    """(y, u, dt): (0.5 s + 1) / (s^2 + 0.8 s + 1) (foh), a held random input, 2 % output
    noise, scaled to an output std of about 0.2 (an audit's record)."""
    dt = 0.05
    rng = np.random.default_rng(seed)
    u = np.repeat(rng.standard_normal(T // 40 + 1), 40)[:T]
    plant = mfmjax.Model.from_coefficients([1.0, 0.8, 1.0], [[1.0, 0.5]])
    y0 = np.asarray(mfmjax.simulate(plant, u[:, None], dt=dt))
    return 0.2 * (y0 + 0.02 * np.std(y0) * rng.standard_normal(T)), u[:, None], dt


LEVEL_GRID = dict(n=(1, 2, 3), N=(3, 4), M=(3,), h=(3.0, 5.0))


def test_ranking_by_e_does_not_depend_on_the_output_level():
    """With the offset term a constant added to y changes no model's E, so it must not change
    the ranking. The E tie tolerance was 1e-12 of the raw output energy: at a level of 1e5 it
    was 1.0, every candidate tied, and the fewest parameters won (n = 1, fit 62 % over the
    best 98 %). It is now 1e-12 of the energy about the mean. Score J on such an output warns
    (J_rel is measured against the level and nears rounding: 6.7e-8 for every candidate)."""
    y, u, dt = _level_record()
    base, shifted = (mfmjax.search(Signals(y + s, u, dt=dt, offset=True), **LEVEL_GRID)
                     for s in (0.0, 1e5))
    assert base.row(0)["fit"] > 97.0
    # the same E in exact arithmetic; at the level of 1e5 the Gram loses about 4 digits
    # (E of the top candidates 1e-4 relative apart, as their E differ), so the winner among
    # the four near-equal n = 3 candidates may change, its fit may not
    assert shifted.row(0)["n"] == 3 and shifted.row(0)["status"] == "ok"
    assert shifted.row(0)["fit"] == pytest.approx(base.row(0)["fit"], abs=1e-2)
    with pytest.warns(UserWarning, match=r"search\(\): the output's level \(100000\) is 5.0\de\+05 "
                                         "times its standard deviation: J_rel is measured against "
                                         "the level"):
        mfmjax.search(Signals(y + 1e5, u, dt=dt, offset=True), score="J", **LEVEL_GRID)


def test_equation_error_search_flags_unstable_candidates():
    """score="J", simulate=False reported status ok for candidates whose A(s) is unstable
    (the validated search flags them); it now runs the Routh test too, so both agree on
    which candidates are unstable."""
    y, u, dt = _level_record()
    sig = Signals(y, u, dt=dt, offset=True)
    fast = mfmjax.search(sig, score="J", simulate=False, **LEVEL_GRID)
    full = mfmjax.search(sig, score="J", **LEVEL_GRID)
    unstable = lambda r: (np.asarray(r.columns["status"]) & mfmjax.Status.UNSTABLE) != 0  # noqa: E731
    assert unstable(fast).sum() == 4
    np.testing.assert_array_equal(unstable(fast), unstable(full))
    assert all(fast.row(i)["status"] == "ok" for i in range(int((~unstable(fast)).sum())))


def test_search_says_when_delays_reach_before_the_record_or_fit_is_undefined():
    """A noise-free 5 s delay searched on 0..6 s from the record's start: candidates with a
    delay are scored with the input from before the record held at its first value, so the
    true model ranked 21st (the winner: n = 3, delay 3, fit 66 %) without a word; a warning
    now says so and how to validate. Validated from 6 s on, the true model wins. score="fit"
    on a constant validation output (every fit 0/0) is refused."""
    dt, T = 0.05, 1000
    rng = np.random.default_rng(3)
    u = np.repeat(rng.standard_normal(T // 40 + 1), 40)[:T]
    plant = mfmjax.Model.from_coefficients([1.0, 0.8, 1.0], [[1.0, 0.5]])
    u_long = np.concatenate([np.repeat(rng.standard_normal(3), 40), u])  # 120 samples before
    y = np.asarray(mfmjax.simulate(plant, u_long[:, None], dt=dt))[120:]
    y = np.concatenate([np.zeros(100), y[:-100]])  # 5 s = 100 samples of delay
    sig = Signals(y, u[:, None], dt=dt, offset=False)
    grid = dict(n=(1, 2, 3), N=(3, 4), M=(3,), h=(2.0, 4.0), delays=[(0, 1, 2, 3, 4, 5, 6)])
    with pytest.warns(UserWarning, match=r"search\(\): the delays of 'u1' reach before the "
                                         r"record .*\(validate=\(t0 \+ 6, t1\)\)"):
        mfmjax.search(sig, **grid)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        late = mfmjax.search(sig, validate=(6.0, (T - 1) * dt), **grid)
    best = late.row(0)
    assert (best["n"], best["m"], best["delays"]) == (2, [1], [5.0]) and best["fit"] > 99.99
    flat = Signals(np.where(np.arange(T) >= 800, y[800], y), u[:, None], dt=dt, offset=False)
    with pytest.raises(ValueError, match=r"score='fit' is undefined on this validation window: "
                                         "the output is constant there"):
        mfmjax.search(flat, validate=(40.0, (T - 1) * dt), score="fit", **grid)


def test_fit_on_a_validation_window_where_the_output_is_constant_is_nan():
    """The output at a level (97.5, as the DaISy exchanger's first 100 samples) and constant
    on the validation window: the fit's denominator was the rounding of its mean (1e-14) and
    the table read -3.8e14 % ... -9.0e16 %, where `fit_percent` and `validate` say undefined.
    It is NaN now (spread below 1e-12 of |y| per sample); E is unchanged."""
    y, u, dt = _level_record(T=1200)
    y = y + 97.5
    y[600:] = y[600]
    sig = Signals(y, u, dt=dt, offset=True)
    res = mfmjax.search(sig, n=(1, 2), N=3, M=3, h=3.0, validate=(32.0, 59.95))
    fits = np.asarray(res.columns["fit"])
    assert np.all(np.isnan(fits)) and np.all(np.isfinite(np.asarray(res.columns["E"])))
    moving = mfmjax.search(sig, n=(1, 2), N=3, M=3, h=3.0, validate=(5.0, 29.95))
    assert np.all(np.isfinite(np.asarray(moving.columns["fit"])))
    # an unstable row's fit of -5.6e70 % printed with 70 digits and pushed the table's columns
    from mfmjax._search._result import _fit_text

    assert (_fit_text(-5.57e70), _fit_text(-999.994), _fit_text(97.123), _fit_text(None)) == \
        ("<-1000", "-999.99", "97.12", "-")


def test_search_on_several_identify_windows_warns_that_validation_crosses_them():
    """Two experiments laid end to end (Signals.concatenate) and identified on their windows:
    with no validate= the E of every candidate was a simulation across the junction (87.8 %
    where the best model fitted each window at 99.2-99.3 %), unsaid."""
    y, u, dt = _level_record(T=1200)
    a = Signals(y[:600], u[:600], dt=dt, offset=False)
    b = Signals(y[600:], u[600:], dt=dt, offset=False)
    joined, windows = Signals.concatenate([a, b])
    with pytest.warns(UserWarning, match=r"search\(\): E and fit are measured over the whole "
                                         "record, across the gaps between the identify windows"):
        mfmjax.search(joined, identify=list(windows), n=(2,), N=3, M=3, h=3.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        mfmjax.search(joined, identify=list(windows), validate=windows[1], n=(2,), N=3, M=3,
                      h=3.0)


def test_repeated_grid_values_are_one_candidate_and_a_bad_delay_is_named():
    """h=(2, 2), N=(3, 3) or a delay listed twice made the table list one candidate several
    times (ranks 1-4 the same row), each computed again; n and m were merged already. A
    negative delay got "delays must be >= 0 and shorter than the record", naming neither the
    input nor the value."""
    y, u, dt = _level_record(T=1200)
    sig = Signals(y, u, dt=dt, offset=False)
    once = mfmjax.search(sig, n=(1, 2), N=(3,), M=(3,), h=(3.0,), delays=[[0.0, 0.1]])
    twice = mfmjax.search(sig, n=(1, 1, 2), N=(3, 3.0), M=(3,), h=(3.0, 3.0),
                          delays=[[0.0, 0.1, 0.0]])
    assert len(twice) == len(once) == 6  # (n, m): (1, 0), (2, 0), (2, 1); two delays
    np.testing.assert_array_equal(twice.columns["E"], once.columns["E"])
    assert twice.table(6) == once.table(6)
    with pytest.raises(ValueError, match=r"search\(\): delays\[0\]\[1\] must be >= 0 and shorter "
                                         r"than the record \(59.95 time units; got "
                                         r"delays\[0\]\[1\]=-0.5\)"):
        mfmjax.search(sig, n=(1,), N=3, M=3, h=3.0, delays=[[0.0, -0.5]])
