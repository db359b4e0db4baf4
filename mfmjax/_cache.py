"""Persistent compilation cache: compiled programs survive the process (one call to turn on)."""

from __future__ import annotations

import hashlib
import os
import platform
import re

import jax

from . import _executables

DEFAULT_MAX_SIZE_BYTES = 1 << 30  # 1 GiB; a full test run writes about 0.2 GiB
_OPT_OUT = "MFMJAX_NO_COMPILE_CACHE"
_ENV_DIR = "JAX_COMPILATION_CACHE_DIR"


def _cpu_id() -> str:
    """Short hash of the CPU model string (compiled CPU code is specific to the CPU)."""
    model = ""
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.lower().startswith("model name"):
                    model = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    model = model or platform.processor() or platform.machine() or "unknown"
    return hashlib.sha256(model.encode()).hexdigest()[:10]


def default_cache_dir() -> str:
    """`$XDG_CACHE_HOME` (or `~/.cache`)`/mfmjax/jax-<jax>-<jaxlib>-<cpu id>`."""
    import jaxlib

    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    name = f"jax-{jax.__version__}-{jaxlib.__version__}-{_cpu_id()}"
    return os.path.join(base, "mfmjax", name)


def cache_dir(path: str | os.PathLike | None = None) -> str:
    """The directory `enable_compile_cache(path)` uses: `$JAX_COMPILATION_CACHE_DIR`, else
    `path`, else `default_cache_dir()`."""
    directory = os.environ.get(_ENV_DIR) or (os.fspath(path) if path is not None else None)
    return os.path.abspath(os.path.expanduser(directory or default_cache_dir()))


ENTRY = re.compile(r"-[0-9a-f]{64}-cache$")  # JAX's entries and `mfmjax-exe-<key>-cache`
# `atomic_write`'s temporary file of a stored executable whose writer was killed
LEFTOVER = re.compile(r"^\.mfmjax-exe-[0-9a-f]{64}-cache\..*\.tmp$")
LEFTOVER_AGE_S = 3600.0  # older than this: no writer is still writing it


def _prune(path: str, max_size_bytes: int) -> None:
    """Delete the oldest cache entries (`ENTRY`: other files in the folder are the user's)
    until the directory holds at most `max_size_bytes`. Another process may prune the same
    folder at the same time: a file gone meanwhile is skipped (it raised before)."""
    entries = []
    import time

    for entry in os.scandir(path):
        if LEFTOVER.match(entry.name):  # (never counted nor removed: 0.5 MB each)
            try:
                if time.time() - entry.stat().st_mtime > LEFTOVER_AGE_S:
                    os.remove(entry.path)
            except OSError:
                pass
            continue
        if not ENTRY.search(entry.name):
            continue
        atime = os.path.join(path, entry.name[: -len("-cache")] + "-atime")
        try:
            if not entry.is_file():
                continue
            st = entry.stat()
            used = max(st.st_mtime, os.path.getmtime(atime) if os.path.exists(atime) else 0.0)
        except OSError:
            continue
        entries.append((used, st.st_size, entry.path, atime))
    total = sum(e[1] for e in entries)
    for _, size, file, atime in sorted(entries):
        if total <= max_size_bytes:
            break
        for f in (file, atime):
            try:
                os.remove(f)
            except OSError:
                pass
        total -= size


def enable_compile_cache(
    path: str | os.PathLike | None = None, *, max_size_bytes: int = DEFAULT_MAX_SIZE_BYTES,
    executables: bool = True,
) -> str | None:
    r"""Turn on JAX's persistent compilation cache, so a new process skips compilation.

    The cache stores the compiled XLA executables of the jitted programs (mfmjax's and any
    other JAX code run in this process), one file per program, keyed by the program text,
    argument shapes and dtypes, the jax/jaxlib versions and the CPU; a program is read back
    instead of compiled when all of these match. It holds no data values. Every program is
    written (minimum compile time 0). The CLI calls this at start; library users call it once,
    before the first computation (importing mfmjax does not).

    **Arguments:**

    - `path`: the cache directory. `$JAX_COMPILATION_CACHE_DIR`, when set, takes precedence;
      default `$XDG_CACHE_HOME` (or `~/.cache`)`/mfmjax/jax-<jax>-<jaxlib>-<cpu id>`.
    - `max_size_bytes`: size cap (default 1 GiB). The oldest entries beyond it are deleted
      now (each call, so each CLI start); a long process may exceed it until the next call.
    - `executables`: also store mfmjax's own programs as whole executables in the same folder
      (`mfmjax-exe-*-cache`, see `mfmjax/_executables.py`), so a new process loads them without
      tracing or lowering them (default True; False: JAX's cache alone).

    **Returns:** the directory used, or None when `MFMJAX_NO_COMPILE_CACHE=1` is set (then
    the cache is off, JAX's own too: `disable_compile_cache`).
    """
    if os.environ.get(_OPT_OUT, "").strip().lower() in ("1", "true", "yes", "on"):
        disable_compile_cache()
        return None
    if isinstance(max_size_bytes, bool) or not (isinstance(max_size_bytes, int)
                                                and max_size_bytes > 0):
        raise ValueError(
            f"enable_compile_cache(): max_size_bytes must be a positive int (got "
            f"{max_size_bytes!r})"
        )
    directory = cache_dir(path)
    where = (f"set by ${_ENV_DIR}: set it to another folder or unset it"
             if os.environ.get(_ENV_DIR) else "pass another path")
    try:
        os.makedirs(directory, exist_ok=True)
    except OSError as err:
        raise ValueError(
            f"enable_compile_cache(): cannot create the cache directory {directory!r} "
            f"({err.strerror}); {where}, or set {_OPT_OUT}=1"
        ) from None
    if not os.access(directory, os.W_OK):  # (every program then compiled from cold, unsaid,
        # and JAX warned once per program)
        import warnings

        warnings.warn(f"enable_compile_cache(): the cache directory {directory!r} is not "
                      f"writable: programs stored there load, new ones are compiled and not "
                      f"stored; {where} to store them", stacklevel=2)
        warnings.filterwarnings("ignore", message="Error writing persistent compilation cache")
    else:
        _prune(directory, max_size_bytes)
    from jax.experimental.compilation_cache import compilation_cache as cc

    previous = jax.config.jax_compilation_cache_dir
    jax.config.update("jax_enable_compilation_cache", True)
    jax.config.update("jax_compilation_cache_dir", directory)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    # JAX's own size cap (with `filelock` installed) reads an "-atime" file for every entry on
    # each write, and plain-JAX processes sharing the directory (a notebook with
    # JAX_COMPILATION_CACHE_DIR set) write entries without one: every later write here then
    # failed with a warning. The cap is therefore mfmjax's `_prune`, at every enable.
    jax.config.update("jax_compilation_cache_max_size", -1)
    if previous and os.path.abspath(previous) != directory:
        cc.reset_cache()  # JAX opens the directory once per process; reopen at the new one
    _executables.enable(directory if executables else None)
    return directory


def disable_compile_cache() -> None:
    """No persistent compilation cache in this process: JAX's off (it turned itself on from
    `$JAX_COMPILATION_CACHE_DIR`, so `--no-compile-cache` still wrote entries there) and no
    stored executables. `MFMJAX_NO_COMPILE_CACHE=1` and the CLI's `--no-compile-cache`."""
    jax.config.update("jax_enable_compilation_cache", False)
    _executables.enable(None)
