"""Stored executables: a compiled program written to the compile cache's folder, so that a new
process loads it without tracing or lowering the function again.

JAX's persistent cache (`enable_compile_cache`) skips XLA's compile, but its key is the lowered
program text, so every new process still traces and lowers each program before it can look it
up: 0.6 s of the warm-cache `mfmjax identify` CLI's 1.8 s. A stored executable is keyed
instead by what determines the program (the function, its static arguments, the shapes and
dtypes of its array arguments, the compiler options, a fingerprint of mfmjax's source and the
versions of jax, jaxlib, equinox, optimistix, lineax and numpy, the float64 flag, `XLA_FLAGS`, the device and the
CPU's features), and
holds the serialized executable (`jax.experimental.serialize_executable`).

These programs are compiled with JAX's persistent cache bypassed: XLA:CPU re-serialises an
executable that JAX's cache loaded without its kernels ("Function ... not found" when run), so
only one compiled in this process is written, and JAX's entry would only duplicate it. A file that
fails to load or to run is deleted and the program compiled again; the result never depends on
whether the file was there. Used only at the top level (outside a user's jit/vmap/grad), on a
single device, for `_jit.jit` and `_jit.array_jit` programs whose static arguments print
without a memory address.
"""

from __future__ import annotations

import contextlib
import copyreg
import functools
import hashlib
import io
import os
import pickle
import re
import sys
import threading
import types

import jax
import numpy as np

_PREFIX = "mfmjax-exe-"
_SUFFIX = "-cache"  # the compile cache's `_prune` counts, ages and deletes these files too
_state = {"directory": None}
_memory: dict = {}  # (wrapper, static, treedef, avals) -> jax Compiled, or None: not stored
_by_name: dict = {}  # file name -> jax Compiled, loaded or compiled in this process
stats = {"loaded": 0, "written": 0, "compiled": 0}  # this process's counts (tests, benchmarks)
loaded: list[str] = []  # names of the programs loaded, as JAX's compile log names them
_switch = threading.Lock()  # guards `_fresh`: compiles on several threads share the switch
_fresh = {"depth": 0, "previous": None}  # fresh compiles under way; JAX's flag before them

try:  # equinox internals, resolved once (equinox>=0.13.8); without them nothing is stored
    from equinox._jit import _postprocess, _preprocess
    from equinox._module._flatten import _Missing
    from jax.experimental import serialize_executable as _serialize
except ImportError:  # pragma: no cover
    _preprocess = None


def enable(directory: str | None) -> None:
    """Store executables in `directory` (None: stop). Drops this process's loaded ones."""
    _state["directory"] = directory if _preprocess is not None else None
    _memory.clear()
    _by_name.clear()


def clear() -> None:
    """Drop this process's loaded and compiled executables (as `jax.clear_caches` does JAX's)."""
    _memory.clear()
    _by_name.clear()


def active() -> bool:
    return _state["directory"] is not None


@functools.cache
def _fingerprint() -> str:
    """What makes an executable valid beyond its arguments: mfmjax's source, the versions of
    the libraries that trace and compile it, and the machine's JAX settings."""
    import equinox
    import jaxlib

    h = hashlib.sha256()
    root = os.path.dirname(os.path.abspath(__file__))
    for folder, dirs, files in os.walk(root):
        dirs.sort()
        for name in sorted(f for f in files if f.endswith(".py")):
            path = os.path.join(folder, name)
            h.update(os.path.relpath(path, root).encode())
            with open(path, "rb") as fh:
                h.update(fh.read())
    device = jax.devices()[0]
    h.update(_cpu_features().encode())
    h.update(repr((jax.__version__, jaxlib.__version__, equinox.__version__, np.__version__,
                   _version_of("optimistix"), _version_of("lineax"),
                   bool(jax.config.jax_enable_x64), str(jax.config.jax_default_matmul_precision),
                   os.environ.get("XLA_FLAGS", ""), device.platform, device.device_kind,
                   jax.device_count())).encode())
    return h.hexdigest()


def _version_of(package: str) -> str:
    """An installed package's version, from its metadata (importing optimistix takes 0.13 s)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(package)
    except PackageNotFoundError:  # pragma: no cover - no metadata: the module's own
        return str(getattr(__import__(package), "__version__", "unknown"))


def _cpu_features() -> str:
    """The CPU's model and instruction-set flags: XLA:CPU compiles for the host's features, so
    a folder shared between machines (a network home) never hands one CPU's code to another."""
    import platform

    try:
        with open("/proc/cpuinfo") as fh:
            lines = [v for v in fh if v.lower().startswith(("model name", "flags", "features"))]
        return "".join(sorted(set(lines)))
    except OSError:
        return platform.processor() + platform.machine()


def _missing():
    from equinox._module._flatten import MISSING

    return MISSING  # equinox compares with `is`: unpickle to its own singleton


def _dumps(obj) -> bytes:
    buf = io.BytesIO()
    pickler = pickle.Pickler(buf, protocol=pickle.HIGHEST_PROTOCOL)
    pickler.dispatch_table = copyreg.dispatch_table.copy()
    pickler.dispatch_table[_Missing] = lambda _: (_missing, ())
    pickler.dump(obj)
    return buf.getvalue()


# packages whose functions may be named in a key: their source or version is in the fingerprint
_NAMED_PACKAGES = ("mfmjax", "optimistix", "lineax", "equinox", "jax")


def _named(static, depth=0):
    """`static` with every module-level function of a fingerprinted package in its tuples,
    lists and dicts named by module and qualified name (e.g. optimistix's default norm
    `max_norm` inside a solver), not by its memory address. Any other function (a lambda, a
    closure, a user's function, whose code the name would not pin down) keeps its address,
    so its program is never stored."""
    if depth > 8:
        return static
    if isinstance(static, tuple | list):
        return type(static)(_named(v, depth + 1) for v in static)
    if isinstance(static, dict):
        return {k: _named(v, depth + 1) for k, v in static.items()}
    if isinstance(static, types.FunctionType) and _module_level(static):
        return ("function", static.__module__, static.__qualname__)
    return static


def _module_level(fun) -> bool:
    module = sys.modules.get(fun.__module__)
    return (fun.__module__.split(".")[0] in _NAMED_PACKAGES and module is not None
            and getattr(module, fun.__qualname__, None) is fun)


def _identity(fun, depth=0):
    """What names a function's program: its module and qualified name and, for a closure made
    by a factory (`_srivc._program`), the values it captured and its defaults, functions among
    them by their own identity (a value that prints with a memory address keeps it unstored)."""
    fun = getattr(fun, "fun", fun)  # jax's custom_vmap / custom_jvp hold the function
    if not hasattr(fun, "__code__") or depth > 3:
        return fun
    cells = tuple(c.cell_contents for c in fun.__closure__ or ())
    return (fun.__module__, fun.__qualname__, fun.__defaults__, fun.__kwdefaults__,
            tuple(_identity(c, depth + 1) if callable(c) else c for c in cells))


def _disk_name(fun, options, static, tree, avals) -> str | None:
    """The file name of a program, or None when its static arguments or captured values do
    not print stably."""
    text = repr((_identity(fun), sorted(options.items()), _named(static[1:]), tree, avals))
    if " at 0x" in text or "..." in text or "array(" in text.lower():  # a memory address,
        # or a NumPy or JAX array, whose printout rounds to 8 digits
        return None
    return _PREFIX + hashlib.sha256((_fingerprint() + text).encode()).hexdigest() + _SUFFIX


@contextlib.contextmanager
def _fresh_compile():
    """JAX's persistent cache neither read nor written inside: the executable is compiled
    here, so it serialises whole (the stored file replaces JAX's entry for this program)."""
    try:
        from jax._src import compilation_cache as cc

        cc.is_cache_used(jax.devices()[0].client)  # JAX decides once per process
        cc._cache_used  # noqa: B018 (the switch exists)
    except (ImportError, AttributeError):  # pragma: no cover - another jax: store nothing
        yield False
        return
    # the switch is process-wide: the first of concurrent fresh compiles turns it off, the
    # last restores it (a plain compile on another thread meanwhile bypasses JAX's cache too:
    # compiled rather than read, and not written)
    with _switch:
        if _fresh["depth"] == 0:
            _fresh["previous"] = cc._cache_used
            cc._cache_used = False
        _fresh["depth"] += 1
    try:
        yield True
    finally:
        with _switch:
            _fresh["depth"] -= 1
            if _fresh["depth"] == 0:
                cc._cache_used = _fresh["previous"]


@functools.cache
def _initialize_lapack() -> None:
    """jaxlib's LAPACK kernels take their function pointers from SciPy when JAX first lowers a
    LAPACK call in the process; an executable loaded without that lowering would call null
    pointers (a segfault, found on `output_error`'s solver), so loading one sets them first."""
    from jax._src.lax import linalg

    linalg.initialize_lapack()


def _custom_calls(lowered) -> set[str]:
    """The custom-call targets of a jax `Lowered` program (its StableHLO text)."""
    return set(re.findall(r"custom_call @([\w.]+)", lowered.as_text()))


def _load(path):
    try:
        with open(path, "rb") as fh:
            digest, payload = fh.read(32), fh.read()
        if hashlib.sha256(payload).digest() != digest:
            raise ValueError("checksum mismatch")
        lapack, serialized = pickle.loads(payload)
        if lapack:
            _initialize_lapack()
        compiled = _serialize.deserialize_and_load(*serialized)
    except FileNotFoundError:
        return None
    except Exception:  # noqa: BLE001 - a damaged or foreign file: delete it, compile again
        _remove(path)
        return None
    try:  # recently used: `_prune` deletes the oldest first
        os.utime(path)
    except OSError:  # a read-only folder or another user's file: still a good program (it
        pass  # was deleted as damaged, and every program compiled again)
    stats["loaded"] += 1
    return compiled


def _remove(path) -> None:
    try:
        os.remove(path)
    except OSError:
        pass


def _compile_and_store(lowered, path):
    """The jax `Lowered` program compiled here, and written to `path` when it serialises."""
    from ._persist import atomic_write

    extra = lowered._lowering.compile_args
    if any(extra.get(k) for k in ("host_callbacks", "ordered_effects", "unordered_effects")):
        return None  # an `eqx.error_if` or other callback: the plain path reports its errors
    calls = _custom_calls(lowered)
    if any(not c.startswith("lapack_") for c in calls):
        return None  # a kernel whose set-up in a new process is not known here: never stored
    with _fresh_compile() as fresh:
        compiled = lowered.compile()
    stats["compiled"] += 1
    if fresh:
        try:
            payload = _dumps((bool(calls), _serialize.serialize(compiled)))
            atomic_write(path, hashlib.sha256(payload).digest() + payload)
            stats["written"] += 1
        except Exception:  # noqa: BLE001 - not serialisable, or the disk is full
            pass
    return compiled


def call(wrapper, fun, options, args, kwargs, *, filtered=True):
    """`wrapper(*args, **kwargs)` (an `eqx.filter_jit` of `fun` with `options`, or with
    `filtered=False` a `jax.jit`, every argument traced), through a stored executable where
    one exists or can be written."""
    if filtered:
        info = (wrapper._signature, wrapper._dynamic_fun, wrapper._static_fun,
                wrapper.donate_first, wrapper.donate_rest)
        donate, keep, static = _preprocess(info, args, kwargs, return_static=True)
        dynamic, run_args, run_kwargs = (donate, keep), (donate, keep), {}
    else:
        static, dynamic, run_args, run_kwargs = (), (args, kwargs), args, kwargs
    leaves, tree = jax.tree_util.tree_flatten(dynamic)
    avals = tuple(str(jax.typeof(x)) for x in leaves)  # shape, dtype, weak type
    key = (id(wrapper), static, tree, avals)
    try:
        compiled = _memory.get(key, False)
    except TypeError:  # an unhashable static argument: equinox raises the clear error
        return wrapper(*args, **kwargs)
    finish = _postprocess if filtered else (lambda out: out)
    if compiled is False:  # first call in this process
        name = _disk_name(fun, options, static, tree, avals) if jax.device_count() == 1 else None
        if name is None:
            _memory[key] = None
            return wrapper(*args, **kwargs)
        compiled = _by_name.get(name)
        if compiled is not None:  # the same program under another in-memory key: a state
            # returned by a loaded executable holds unpickled copies of lineax's tags, equal in
            # print but not in identity, so refine's next BFGS step has a new key
            _memory[key] = compiled
            return finish(compiled(*run_args, **run_kwargs))
        path = os.path.join(_state["directory"], name)
        compiled = _load(path)
        if compiled is not None:
            try:  # a damaged executable fails here, loudly: compile instead
                out = jax.block_until_ready(compiled(*run_args, **run_kwargs))
            except Exception:  # noqa: BLE001
                _remove(path)
                compiled = None
            else:
                _memory[key] = _by_name[name] = compiled
                loaded.append(f"jit({fun.__name__})")
                return finish(out)
        lowered = wrapper.lower(*args, **kwargs)
        compiled = _memory[key] = _compile_and_store(
            lowered.lowered if filtered else lowered, path)
        if compiled is not None:
            _by_name[name] = compiled
    if compiled is None:
        return wrapper(*args, **kwargs)
    return finish(compiled(*run_args, **run_kwargs))
