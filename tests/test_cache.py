"""Persistent compilation cache: directory rules, pruning, and cacheable public programs."""

import json
import os
import subprocess
import sys

import jax
import numpy as np
import pytest

import mfmjax
from mfmjax import _cache

# Runs simulate, identify, observe, srivc and output_error with the cache on in argv[1] and reports, per step, the
# new cache files and the persistent-cache log lines (jax_explain_cache_misses logs every
# miss, hit and refused write at WARNING).
_SCRIPT = r"""
import json, logging, os, sys
import numpy as np
import jax
import mfmjax

from mfmjax import _executables

d = mfmjax.enable_compile_cache(sys.argv[1], executables=sys.argv[2] == "1")
jax.config.update("jax_explain_cache_misses", True)
msgs = []

class _Collect(logging.Handler):
    def emit(self, rec):
        msgs.append(rec.getMessage())

lg = logging.getLogger("jax._src.compiler")
lg.addHandler(_Collect())
lg.setLevel(logging.DEBUG)
lg.propagate = False

def files():
    return {f for f in os.listdir(d) if f.endswith("-cache")}

def names(new, tag):
    return sorted(m.split("'")[1] for m in new if tag in m)

out = {"dir": d}

def step(name, fn):
    before, m0, s0 = files(), len(msgs), dict(_executables.stats)
    r = fn()
    jax.block_until_ready(r)
    new = msgs[m0:]
    out[name] = {"new_files": len(files() - before),
                 "stored": {k: _executables.stats[k] - s0[k] for k in s0},
                 "value": np.asarray(jax.tree_util.tree_leaves(r)[0]).ravel().tolist(),
                 "compiled": names(new, "CACHE MISS"),
                 "hits": names(new, "cache hit"),
                 "refused": [m for m in new if "Not writing" in m]}
    return r

dt, T = 0.01, 1201
t = np.arange(T) * dt
u = np.sin(0.9 * t) + 0.5 * np.cos(2.3 * t)
true = mfmjax.Model.from_coefficients([2.0, 3.0, 1.0], [[1.0]])
y = step("simulate", lambda: mfmjax.simulate(true, u, None, dt=dt))
sig = mfmjax.Signals(np.asarray(y), u, dt=dt)
model = step("identify", lambda: mfmjax.identify(sig, mfmjax.Structure(2, [1]),
                                                 mfmjax.ModulatingFunction(4, 4, 2.0)))
step("observe", lambda: mfmjax.observe(model, sig).x_initial)
step("srivc", lambda: mfmjax.srivc(sig, model).theta)
step("output_error", lambda: mfmjax.output_error(sig, model).theta)  # a LAPACK solve inside
print("RESULT " + json.dumps(out))
"""


def _run(script, cache, executables=False):
    env = {k: v for k, v in os.environ.items()
           if k not in ("JAX_COMPILATION_CACHE_DIR", "MFMJAX_NO_COMPILE_CACHE")}
    proc = subprocess.run([sys.executable, str(script), str(cache), str(int(executables))],
                          capture_output=True,
                          text=True, env=env, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    line = [v for v in proc.stdout.splitlines() if v.startswith("RESULT ")][-1]
    return json.loads(line[len("RESULT "):])


@pytest.fixture(scope="module")
def plain_runs(tmp_path_factory):
    """The probe with JAX's own persistent cache only (stored executables off), in a first and
    a second process sharing one cache folder: (cache, cold, warm). The cold run is also the
    reference of the stored-executable test below."""
    tmp = tmp_path_factory.mktemp("plain")
    script = tmp / "probe.py"
    script.write_text(_SCRIPT)
    cache = tmp / "cache"
    return cache, _run(script, cache), _run(script, cache)


def test_programs_are_written_and_read_back(plain_runs):
    # JAX's own persistent cache (stored executables off)
    cache, cold, warm = plain_runs
    assert cold["dir"] == str(cache)
    for name in ("simulate", "identify", "observe", "srivc", "output_error"):
        c, w = cold[name], warm[name]
        assert c["value"] == w["value"], name  # bitwise
        # every program compiled in the first process was written (no eqx.error_if or other
        # host callback refused it) ...
        assert c["refused"] == [], (name, c["refused"])
        assert c["compiled"], name
        assert c["new_files"] >= 1, name
        # ... and the second process compiles nothing: it reads each of them back
        assert w["compiled"] == [] and w["refused"] == [], (name, w)
        assert w["new_files"] == 0, name
        assert set(c["compiled"]) <= set(w["hits"]), (name, c["compiled"], w["hits"])


def _stored(cache):
    return sorted(f for f in os.listdir(cache) if f.startswith("mfmjax-exe-"))


def test_stored_executables_are_written_loaded_and_replaced_when_damaged(tmp_path, plain_runs):
    script = tmp_path / "probe.py"
    script.write_text(_SCRIPT)
    plain = plain_runs[1]  # JAX's persistent cache only, first process: the reference
    cache = tmp_path / "cache"
    cold = _run(script, cache, executables=True)
    files = _stored(cache)
    warm = _run(script, cache, executables=True)
    # srivc: an `array_jit` program; output_error: its solver calls LAPACK, whose kernels a new
    # process must set up before it runs a loaded executable (it crashed the process before)
    steps = ("simulate", "identify", "observe", "srivc", "output_error")
    for name in steps:
        c, w = cold[name], warm[name]
        # the first process compiles each program itself and writes it ...
        assert c["stored"]["compiled"] >= 1 and c["stored"]["written"] >= 1, (name, c)
        # ... the second loads it: nothing traced, lowered or compiled, nothing new written
        assert w["stored"] == {"loaded": c["stored"]["written"], "written": 0, "compiled": 0}
        assert w["compiled"] == [] and w["new_files"] == 0, (name, w)
        # and the results are bitwise those of the plain path
        assert c["value"] == w["value"] == plain[name]["value"], name
    assert len(files) == sum(cold[n]["stored"]["written"] for n in steps)
    assert _stored(cache) == files
    # a damaged file (one flipped byte, caught by its checksum) and a truncated one are
    # deleted and compiled again; the results do not change
    for i, f in enumerate(files):
        path = cache / f
        data = bytearray(path.read_bytes())
        if i % 2:
            data[len(data) // 2] ^= 0xFF
        else:
            data = data[: len(data) // 3]
        path.write_bytes(bytes(data))
    again = _run(script, cache, executables=True)
    for name in steps:
        a = again[name]
        assert a["stored"]["loaded"] == 0 and a["stored"]["written"] >= 1, (name, a)
        assert a["value"] == plain[name]["value"], name
    assert _stored(cache) == files  # the same keys, rewritten


def test_stored_executable_keys_follow_static_arguments_and_shapes(tmp_path, monkeypatch):
    from jaxlog import compiles

    from mfmjax import _executables

    dt = 0.01
    t = np.arange(1201) * dt
    u = np.sin(0.9 * t) + 0.5 * np.cos(2.3 * t)
    true = mfmjax.Model.from_coefficients([2.0, 3.0, 1.0], [[1.0]])
    y = np.asarray(mfmjax.simulate(true, u, None, dt=dt))
    mf = mfmjax.ModulatingFunction(4, 4, 2.0)
    before = dict(_executables.stats)
    session = os.environ["JAX_COMPILATION_CACHE_DIR"]
    monkeypatch.delenv("JAX_COMPILATION_CACHE_DIR")  # it would take precedence over the path
    try:
        mfmjax.enable_compile_cache(tmp_path / "cache")
        sig = mfmjax.Signals(y, u, dt=dt)
        m2 = mfmjax.identify(sig, mfmjax.Structure(2, [1]), mf)
        m1 = mfmjax.identify(sig, mfmjax.Structure(1, [1]), mf)  # another static structure
        short = mfmjax.Signals(y[:700], u[:700], dt=dt)  # another record bucket
        m3 = mfmjax.identify(short, mfmjax.Structure(2, [1]), mf)
        files = _stored(tmp_path / "cache")
        _executables.clear()  # as a new process: every program is loaded from its file

        def read_only(*args, **kw):  # a read-only folder (or another user's files)
            raise PermissionError(13, "Permission denied")

        # the load marks a file used; where it cannot, the file was deleted as damaged and
        # every program compiled again (21.5 s against 1.2 s warm, nothing said)
        monkeypatch.setattr(_executables.os, "utime", read_only)
        loaded = _executables.stats["loaded"]
        with compiles() as names:
            again = [mfmjax.identify(s, mfmjax.Structure(n, [1]), mf)
                     for s, n in ((sig, 2), (sig, 1), (short, 2))]
        monkeypatch.undo()
        assert _executables.stats["loaded"] - loaded == 3
        assert _stored(tmp_path / "cache") == files
    finally:
        mfmjax.enable_compile_cache(session)
    assert _executables.stats["written"] - before["written"] == 3 == len(files)
    assert names.count("jit(identify_core)") == 3  # three loads, counted as new programs
    for old, new in zip((m2, m1, m3), again):
        np.testing.assert_array_equal(np.asarray(old.theta), np.asarray(new.theta))
    np.testing.assert_allclose(np.asarray(m2.a), [2.0, 3.0, 1.0], rtol=1e-6)


def test_stored_executables_of_one_factory_are_told_apart(tmp_path, monkeypatch):
    """`srivc`'s program is a closure made per intersample rules and offset term
    (`_srivc._program`): two of them on arrays of one shape are two files, and each fit equals
    the one without stored executables bitwise (regression: the file name once held only the
    closure's name, and the second rule's first call loaded the first rule's executable: a
    wrong fit, found by CI)."""
    from mfmjax import _executables

    dt = 0.01
    t = np.arange(1201) * dt
    u = np.sin(0.9 * t) + 0.5 * np.cos(2.3 * t)
    true = mfmjax.Model.from_coefficients([2.0, 3.0, 1.0], [[1.0]], intersample=["zoh"])
    y = np.asarray(mfmjax.simulate(true, u, None, dt=dt))
    mf = mfmjax.ModulatingFunction(4, 4, 2.0)

    def fits():
        out = []
        for rule in ("zoh", "foh"):
            sig = mfmjax.Signals(y, u, dt=dt, intersample=[rule])
            start = mfmjax.identify(sig, mfmjax.Structure(2, [1]), mf)
            out.append(np.asarray(mfmjax.srivc(sig, start).model.theta))
        return out

    session = os.environ["JAX_COMPILATION_CACHE_DIR"]
    monkeypatch.delenv("JAX_COMPILATION_CACHE_DIR")
    try:
        _executables.enable(None)
        plain = fits()
        mfmjax.enable_compile_cache(tmp_path / "cache")
        stored = fits()
        names = _stored(tmp_path / "cache")
        _executables.clear()  # as a new process: both programs are loaded from their files
        loaded = fits()
    finally:
        mfmjax.enable_compile_cache(session)
    assert not np.array_equal(plain[0], plain[1])  # the two rules give two fits
    for got in (stored, loaded):
        for want, fit in zip(plain, got):
            np.testing.assert_array_equal(fit, want)
    assert len(names) >= 4  # identify and srivc, per rule


def test_stored_executable_names_hold_what_the_program_depends_on():
    """A factory's closures are told apart by their captured values (and nested functions by
    their own); a static argument printed with a memory address or as a NumPy array (8 digits)
    keeps its program unstored."""
    from mfmjax._executables import _disk_name

    def factory(rule, inner=None):
        def run(x):
            return (rule, inner)

        return run

    name = lambda fun, static=(None,): _disk_name(fun, {}, static, None, ())  # noqa: E731
    assert name(factory("zoh")) == name(factory("zoh"))
    assert name(factory("zoh")) != name(factory("foh"))
    assert name(factory("zoh", factory(1))) != name(factory("zoh", factory(2)))
    assert name(factory("zoh"), (None, object())) is None
    assert name(factory("zoh"), (None, np.array([0.1, 0.2]))) is None
    assert name(factory(jax.numpy.array([0.1, 0.2]))) is None  # printed as Array([...])
    assert name(factory("zoh"), (None, (0.1, 0.2))) is not None
    # a plain function among the static arguments (optimistix's BFGS holds its norm) is named
    # by its module and qualified name, not by its address: refine's programs are stored
    from optimistix._misc import max_norm, rms_norm

    assert name(factory("zoh"), (None, (1e-6, max_norm))) is not None
    assert name(factory("zoh"), (None, (1e-6, max_norm))) == name(factory("zoh"),
                                                                 (None, (1e-6, max_norm)))
    assert name(factory("zoh"), (None, (1e-6, max_norm))) != name(factory("zoh"),
                                                                 (None, (1e-6, rms_norm)))
    assert name(factory("zoh"), (None, {"norm": factory(object())})) is None  # captured address
    # a lambda, a closure or a user's function is not pinned down by its name (two lambdas of
    # one scope share it; an edited function keeps it): it keeps its program unstored
    twins = [lambda x: x + 1, lambda x: x * 10]
    assert twins[0].__qualname__ == twins[1].__qualname__
    for fn in (*twins, factory):  # `factory`: a function of this test module
        assert name(factory("zoh"), (None, (1e-6, fn))) is None, fn


# The other public paths, run in two processes sharing one cache folder (a digest per result)
_MORE = r"""
import hashlib, json, sys, warnings
import numpy as np
import jax
import mfmjax
from mfmjax import _executables
from mfmjax.datasets import forehearth, simulated_experiment

warnings.simplefilter("ignore")
mfmjax.enable_compile_cache(sys.argv[1])
true = mfmjax.Model.from_coefficients([2.0, 3.0, 1.0], [[1.0, 0.3]], intersample=["foh"])
sig = simulated_experiment(true, dt=0.05, n_samples=1500, seed=3, noise_std=0.01)
st, mf = mfmjax.Structure(2, [1]), mfmjax.ModulatingFunction(3, 4, 2.0)
m = mfmjax.identify(sig, st, mf)
d = forehearth(1, seed=0)
cfg = mfmjax.OnlineConfig(dt=1.0, n_inputs=2, intersample=("foh", "zoh"), delays=(265.0, 0.0))
ident = mfmjax.OnlineIdentifier(cfg)
jobs = {
    "search": lambda: mfmjax.search(sig, n=(1, 2), N=(3, 4), M=(3, 4), h=(1.5, 2.0)),
    "scores": lambda: mfmjax.scores(sig, st, h=2.0, N=3.0, M=4.0),
    "refine": lambda: mfmjax.refine(sig, m, vary=("h",), max_steps=3),
    "frequency_response": lambda: mfmjax.frequency_response(m),
    "moving_final_states": lambda: mfmjax.moving_final_states(m, sig, 5.0, np.array([20.0, 40.0])),
    "online": lambda: [ident.update(np.arange(i, i + 500.0), d["y"][i:i + 500],
                                    d["u"][i:i + 500]) for i in range(0, 3500, 500)],
}
out = {}
for name, fn in jobs.items():
    s0 = dict(_executables.stats)
    h = hashlib.sha256()
    for v in jax.tree_util.tree_leaves(fn()):
        if isinstance(v, (np.ndarray, jax.Array, float, int)):
            h.update(np.ascontiguousarray(np.asarray(v)).tobytes())
    out[name] = [h.hexdigest(), {k: _executables.stats[k] - s0[k] for k in s0}]
print("RESULT " + json.dumps(out))
"""


def test_stored_executables_of_the_other_public_paths_load_and_agree(tmp_path):
    """search, scores, refine, frequency_response, moving_final_states and the on-line
    identifier: a second process loads every program the first stored and returns bitwise
    the same results (the probe that found the LAPACK crash ran every public function this
    way; identify, simulate, observe, srivc and output_error are in the tests above). refine's
    BFGS programs are stored too, and each is loaded once although the state a loaded step
    returns (unpickled lineax tags) gives the next step a new in-memory key (loaded ==
    written)."""
    script = tmp_path / "more.py"
    script.write_text(_MORE)
    cold = _run(script, tmp_path / "cache")
    warm = _run(script, tmp_path / "cache")
    for name, (value, stats) in cold.items():
        assert warm[name][0] == value, name
        assert warm[name][1] == {"loaded": stats["written"], "written": 0, "compiled": 0}, (
            name, stats, warm[name][1])
    assert sum(s["written"] for _, s in cold.values()) >= 6
    assert cold["refine"][1]["written"] >= 3  # init, step, terminate


def test_public_programs_hold_no_callbacks():
    # a host callback (what eqx.error_if lowers to) keeps a program out of the cache; the
    # lowered text of the public entry points under an outer jit must hold none
    dt, T = 0.01, 401
    t = np.arange(T) * dt
    u = np.sin(0.9 * t)
    model = mfmjax.Model.from_coefficients([2.0, 3.0, 1.0], [[1.0]])
    y = np.asarray(mfmjax.simulate(model, u, None, dt=dt))
    sig = mfmjax.Signals(y, u, dt=dt)
    texts = {
        "simulate": jax.jit(lambda uu: mfmjax.simulate(model, uu, None, dt=dt)).lower(u),
        "observe": jax.jit(lambda yy: mfmjax.observe(model, mfmjax.Signals(yy, u, dt=dt)).E)
        .lower(sig.y),
    }
    for name, lowered in texts.items():
        assert "callback" not in lowered.as_text(), name


def test_traced_overflow_is_reported_in_the_result():
    unstable = mfmjax.Model.from_coefficients([-1.0, 0.0, 1.0], [[1.0]])
    u = np.ones(20000)
    y = jax.jit(lambda uu: mfmjax.simulate(unstable, uu, None, dt=0.1))(u)
    assert bool(np.any(np.isnan(np.asarray(y))))  # eager: a ValueError (test_observers)
    stable = mfmjax.Model.from_coefficients([2.0, 3.0, 1.0], [[1.0]])
    assert np.all(np.isfinite(np.asarray(
        jax.jit(lambda uu: mfmjax.simulate(stable, uu, None, dt=0.1))(u))))
    sig = mfmjax.Signals(np.ones(20000), u, dt=0.1)
    status = jax.jit(lambda s: mfmjax.observe(unstable, s).status)(sig)
    assert int(status) & int(mfmjax.Status.OVERFLOW)


def test_cache_dir_rules(monkeypatch, tmp_path):
    monkeypatch.delenv("JAX_COMPILATION_CACHE_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    default = _cache.cache_dir()
    import jaxlib

    assert os.path.dirname(default) == str(tmp_path / "xdg" / "mfmjax")
    assert os.path.basename(default).startswith(f"jax-{jax.__version__}-{jaxlib.__version__}-")
    assert _cache.cache_dir(tmp_path / "mine") == str(tmp_path / "mine")
    monkeypatch.setenv("JAX_COMPILATION_CACHE_DIR", str(tmp_path / "env"))
    assert _cache.cache_dir(tmp_path / "mine") == str(tmp_path / "env")


def test_opt_out_and_bad_size(monkeypatch, tmp_path):
    from mfmjax import _executables

    before = jax.config.jax_compilation_cache_dir
    stored = _executables._state["directory"]
    monkeypatch.setenv("MFMJAX_NO_COMPILE_CACHE", "1")
    try:
        assert mfmjax.enable_compile_cache(tmp_path / "x") is None
        # JAX's own cache is off too (it turns itself on from $JAX_COMPILATION_CACHE_DIR,
        # which this session sets: the opt-out left it writing there)
        assert not jax.config.jax_enable_compilation_cache
        assert _executables._state["directory"] is None
    finally:
        jax.config.update("jax_enable_compilation_cache", True)
        _executables.enable(stored)
    assert jax.config.jax_compilation_cache_dir == before
    assert not (tmp_path / "x").exists()
    monkeypatch.delenv("MFMJAX_NO_COMPILE_CACHE")
    with pytest.raises(ValueError, match="max_size_bytes must be a positive int"):
        mfmjax.enable_compile_cache(tmp_path / "x", max_size_bytes=0)


def test_prune_keeps_the_newest(tmp_path, monkeypatch):
    names = [f"jit_k{i}-{i:064x}-cache" for i in range(5)]
    for i, name in enumerate(names):
        f = tmp_path / name
        f.write_bytes(b"x" * 100)
        os.utime(f, (1000 + i, 1000 + i))
    # the user's own files in a folder given as path=: not entries, kept (even named -cache)
    (tmp_path / "other.txt").write_text("kept")
    (tmp_path / "notes-cache").write_bytes(b"y" * 1000)
    os.utime(tmp_path / "notes-cache", (1, 1))
    _cache._prune(str(tmp_path), 250)  # room for two 100-byte entries: the newest two stay
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(names[3:] + ["notes-cache",
                                                                            "other.txt"])
    # another process pruning the same folder deletes an entry between the listing and its
    # stat: skipped (FileNotFoundError stopped the CLI with exit 2 before)
    listing = list(os.scandir(tmp_path))
    (tmp_path / names[3]).unlink()
    monkeypatch.setattr(_cache.os, "scandir", lambda path: iter(listing))
    _cache._prune(str(tmp_path), 1)
    monkeypatch.undo()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes-cache", "other.txt"]


def test_cache_folder_problems_are_said_once_with_a_fix_that_works(tmp_path, monkeypatch):
    """A cache folder $JAX_COMPILATION_CACHE_DIR names that cannot be created: the advice
    was "pass another path", which that variable overrides. A folder that cannot be written
    was taken silently (every program compiled from cold, and JAX warned once per program):
    one warning now, and loading from it still works. A stored executable's temporary file
    left by a killed writer was never pruned: removed when older than an hour."""
    session = os.environ["JAX_COMPILATION_CACHE_DIR"]
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    monkeypatch.setenv("JAX_COMPILATION_CACHE_DIR", str(blocker))
    try:
        with pytest.raises(ValueError, match=r"cannot create the cache directory .*a-file' .*; "
                                             r"set by \$JAX_COMPILATION_CACHE_DIR: set it to "
                                             r"another folder or unset it, or set "
                                             r"MFMJAX_NO_COMPILE_CACHE=1"):
            mfmjax.enable_compile_cache(tmp_path / "mine")
        monkeypatch.delenv("JAX_COMPILATION_CACHE_DIR")
        real = os.access
        monkeypatch.setattr(_cache.os, "access",  # a read-only folder (this runs as root)
                            lambda p, mode: False if mode == os.W_OK else real(p, mode))
        with pytest.warns(UserWarning, match=r"enable_compile_cache\(\): the cache directory "
                                             r".*ro' is not writable: programs stored there "
                                             r"load, new ones are compiled and not stored; pass "
                                             r"another path to store them"):
            assert mfmjax.enable_compile_cache(tmp_path / "ro") == str(tmp_path / "ro")
    finally:
        monkeypatch.undo()
        mfmjax.enable_compile_cache(session)
    old, fresh = (tmp_path / f".mfmjax-exe-{c * 64}-cache.x1y2.tmp" for c in "ab")
    for f in (old, fresh):
        f.write_bytes(b"z" * 10)
    os.utime(old, (1000.0, 1000.0))
    _cache._prune(str(tmp_path), 1 << 30)
    assert not old.exists() and fresh.exists()  # (a writer may still be writing the fresh one)


def test_cli_uses_the_cache_unless_told_not_to(tmp_path):
    t = np.arange(600) * 0.01
    u = np.sin(0.9 * t) + 0.5 * np.cos(2.3 * t)
    y = np.asarray(mfmjax.simulate(mfmjax.Model.from_coefficients([2.0, 3.0, 1.0], [[1.0]]),
                                   u, None, dt=0.01))
    csv = tmp_path / "rec.csv"
    np.savetxt(csv, np.column_stack([y, u]), delimiter=",", header="y,u", comments="")
    cmd = [sys.executable, "-c", "import sys; from mfmjax._cli import main; sys.exit(main())",
           "identify", str(csv), "--output", "y", "--inputs", "u", "--dt", "0.01", "--n", "2",
           "--N", "4", "--M", "4", "--h", "2"]
    base = {k: v for k, v in os.environ.items()
            if k not in ("JAX_COMPILATION_CACHE_DIR", "MFMJAX_NO_COMPILE_CACHE")}
    jax_dir = tmp_path / "jax-env"
    for flag, xdg, extra in (([], "on", {}), (["--no-compile-cache"], "off", {}),
                             (["--no-compile-cache"], "off", {
                                 "JAX_COMPILATION_CACHE_DIR": str(jax_dir)})):
        env = dict(base, XDG_CACHE_HOME=str(tmp_path / xdg), **extra)
        proc = subprocess.run(cmd + flag, capture_output=True, text=True, env=env, timeout=600)
        assert proc.returncode == 0, proc.stderr[-2000:]
    (folder,) = (tmp_path / "on" / "mfmjax").iterdir()
    assert any(p.name.endswith("-cache") for p in folder.iterdir())
    assert not (tmp_path / "off").exists()
    # JAX turns its cache on by itself from $JAX_COMPILATION_CACHE_DIR: the flag turns it off
    assert not jax_dir.exists() or not any(jax_dir.iterdir())


def test_programs_compile_with_the_library_options_at_top_level_only():
    """`mfmjax._jit.jit`: a top-level call compiles with COMPILER_OPTIONS; inside a user's
    jit / vmap / grad the same function inlines (JAX refuses compiler options on a nested
    jit: this used to raise ValueError) and gives the top-level call's numbers."""
    import jax.numpy as jnp

    from mfmjax._jit import COMPILER_OPTIONS, _top_level, jit

    assert COMPILER_OPTIONS == {"xla_cpu_use_fusion_emitters": False}
    f = jit(lambda x: jnp.sin(x) * 2.0)
    assert dict(f.lower(jnp.ones(3)).lowered._lowering._compiler_options_kvs) == COMPILER_OPTIONS
    assert _top_level()
    seen = []
    jax.jit(lambda x: seen.append(_top_level()) or x)(1.0)
    jax.vmap(lambda x: seen.append(_top_level()) or x)(jnp.ones(2))
    jax.grad(lambda x: seen.append(_top_level()) or x)(1.0)
    assert seen == [False, False, False]
    # a library program under each transform: same numbers as the top-level call
    model = mfmjax.Model.from_coefficients([2.0, 3.0, 1.0], [[1.0, 0.5]])
    u = np.sin(np.linspace(0.0, 6.0, 200))[:, None]
    top = np.asarray(mfmjax.simulate(model, u, dt=0.03))
    inner = np.asarray(jax.jit(lambda uu: mfmjax.simulate(model, uu, dt=0.03))(u))
    batched = np.asarray(jax.vmap(lambda uu: mfmjax.simulate(model, uu, dt=0.03))(u[None]))[0]
    # same operations, compiled by different XLA pipelines: equal to rounding (1e-12 of the
    # response's scale, far above float64 epsilon times the scan's 200 steps)
    scale = np.max(np.abs(top))
    assert np.max(np.abs(inner - top)) <= 1e-12 * scale
    assert np.max(np.abs(batched - top)) <= 1e-12 * scale
    import equinox as eqx

    grad = jax.grad(lambda c: mfmjax.simulate(
        eqx.tree_at(lambda m: m.b[0], model, jnp.stack([c, 0.5])), u, dt=0.03).sum())(1.0)
    # y is linear in b: d(sum y)/d b_1 is the summed response of b = (1, 0)
    unit = mfmjax.Model.from_coefficients([2.0, 3.0, 1.0], [[1.0, 0.0]])
    expect = float(np.sum(np.asarray(mfmjax.simulate(unit, u, dt=0.03))))
    assert abs(float(grad) - expect) <= 1e-10 * abs(expect)


def test_programs_on_another_backend_compile_with_xla_defaults(monkeypatch):
    """COMPILER_OPTIONS are XLA:CPU's: on a GPU, XLA refused them ("No such compile option:
    'xla_cpu_use_fusion_emitters'", seen on an H200) and every mfmjax program failed. Off the
    CPU backend a top-level call compiles the plain program (XLA's defaults), not the tuned one
    (its cache stays empty), and gives the same numbers."""
    import jax.numpy as jnp

    import mfmjax._jit as j

    f = j.jit(lambda x: jnp.sin(x) * 2.0)
    monkeypatch.setattr(j._executables, "active", lambda: False)  # through `_cached`, counted
    monkeypatch.setattr(j.jax, "default_backend", lambda: "gpu")
    out = np.asarray(f(jnp.ones(3)))
    assert f._cached._cache_size() == 0  # the program with CPU options was not compiled
    assert f.lower(jnp.ones(3)).lowered._lowering._compiler_options_kvs == ()  # nor lowered
    assert np.array_equal(out, np.full(3, 2.0 * np.sin(1.0)))
    monkeypatch.setattr(j.jax, "default_backend", lambda: "cpu")
    assert np.array_equal(np.asarray(f(jnp.ones(3))), out)
    assert f._cached._cache_size() == 1  # on the CPU backend the tuned program is used


def test_xla_defaults_opt_out():
    """MFMJAX_XLA_DEFAULTS=1 compiles with XLA's defaults (no options are passed)."""
    code = ("import mfmjax._jit as j, jax.numpy as jnp; "
            "print(j.COMPILER_OPTIONS, j.jit(lambda x: x + 1).lower(jnp.ones(2))"
            ".lowered._lowering._compiler_options_kvs)")
    env = dict(os.environ, MFMJAX_XLA_DEFAULTS="1")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         check=True).stdout.split()
    assert out == ["{}", "()"]


def test_a_plain_jax_writer_in_the_same_directory_does_not_block_writes(tmp_path):
    """A plain-JAX process (JAX_COMPILATION_CACHE_DIR set, JAX's defaults) writes entries
    without JAX's "-atime" files. With `filelock` installed and JAX's own size cap on, every
    later write of an mfmjax process then failed ("Error writing persistent compilation cache
    entry": seen in the test suite when the notebooks shared the cache). mfmjax caps the size
    itself (`_prune`) and leaves JAX's cap off, so its entries are written. `filelock` is in
    the dev extra so that this can fail (warnings are errors in the second process)."""
    env = {k: v for k, v in os.environ.items() if k != "MFMJAX_NO_COMPILE_CACHE"}
    env["JAX_COMPILATION_CACHE_DIR"] = str(tmp_path)
    plain = ("import jax, jax.numpy as jnp; "
             "jax.config.update('jax_persistent_cache_min_compile_time_secs', 0.0); "
             "jax.config.update('jax_persistent_cache_min_entry_size_bytes', 0); "
             "print(jax.jit(lambda x: x * 3.0)(jnp.ones(5)))")
    ours = ("import warnings, jax, jax.numpy as jnp; warnings.simplefilter('error'); "
            "import mfmjax; mfmjax.enable_compile_cache(); "
            "print(jax.jit(lambda x: x * 5.0 + 1.0)(jnp.ones(7)))")
    for code in (plain, ours):
        subprocess.run([sys.executable, "-c", code], env=env, check=True, capture_output=True)
    names = [p.name for p in tmp_path.iterdir() if p.name.endswith("-cache")]
    assert len([n for n in names if n.startswith("jit__lambda")]) == 2, names


def test_fresh_compiles_on_two_threads_share_jax_cache_switch():
    """A stored executable compiles with JAX's persistent cache switched off, a process-wide
    switch (`_executables._fresh_compile`). Compiles on two threads at once (a search's
    chunk and its validation program, `estimate`'s search and its rehearsed stages) share it:
    the switch stays off until the last of them ends, and is then restored (with a save and
    restore per compile, the second compile's exit turned JAX's cache off for the process;
    compiles were serialised to avoid that)."""
    import threading

    from jax._src import compilation_cache as cc

    from mfmjax._executables import _fresh_compile

    cc.is_cache_used(jax.devices()[0].client)
    before = cc._cache_used
    entered, first_out, seen = threading.Event(), threading.Event(), []

    def first():
        with _fresh_compile() as fresh:
            assert fresh
            entered.set()
            while len(seen) < 1:  # the second compile is inside too
                threading.Event().wait(0.01)
        first_out.set()

    def second():
        entered.wait()
        with _fresh_compile():
            seen.append(cc._cache_used)
            first_out.wait()
            seen.append(cc._cache_used)  # the first compile ended, this one goes on

    threads = [threading.Thread(target=f) for f in (first, second)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=60)
    assert seen == [False, False]
    assert cc._cache_used == before
