"""How mfmjax compiles: `jit` is `eqx.filter_jit` with the library's XLA options."""

from __future__ import annotations

import functools
import os

import equinox as eqx
import jax
import numpy as np

from . import _executables

# XLA:CPU's new fusion emitters (on by default in jaxlib 0.10) took 1.3-2.1x the compile time
# on this library's programs (many small fusions); with them off, warm calls ran 0.68-0.96x,
# except `simulate` at 1.24x (0.3 ms) (`python benchmarks/compile_options.py`).
# `MFMJAX_XLA_DEFAULTS=1` compiles with XLA's own defaults instead. Options are per program:
# other JAX code in the process is unaffected.
COMPILER_OPTIONS = (
    {} if os.environ.get("MFMJAX_XLA_DEFAULTS", "").strip().lower() in ("1", "true", "yes", "on")
    else {"xla_cpu_use_fusion_emitters": False}
)

# for a program that runs once (a one-chunk `search`): XLA's backend at optimisation level 0
# compiled the 760-candidate chunk in 0.66-0.73 s against 1.2-1.6 s, and ran it in 70-80 ms
# against 17-47 ms (`python benchmarks/cold_start.py`)
RUN_ONCE_OPTIONS = {**COMPILER_OPTIONS, "xla_backend_optimization_level": 0}


try:  # private, resolved once: jax is pinned to 0.10.x; without it, XLA's defaults are used
    from jax._src.core import trace_ctx as _trace_ctx

    _trace_ctx.is_top_level  # noqa: B018
except (ImportError, AttributeError):
    _trace_ctx = None


def _top_level() -> bool:
    """True outside every JAX transformation (JAX takes compiler options only there)."""
    return _trace_ctx is not None and _trace_ctx.is_top_level()


def _on_cpu() -> bool:
    """True when programs compile for XLA:CPU, the backend `COMPILER_OPTIONS` and stored
    executables are for: on a GPU, XLA refused the CPU option ("No such compile option:
    'xla_cpu_use_fusion_emitters'") and every program failed; there XLA's defaults apply."""
    return jax.default_backend() == "cpu"


def jit(fun=None, *, options=None, **jitkwargs):
    """`eqx.filter_jit(fun, **jitkwargs)`, compiled with `options` (default `COMPILER_OPTIONS`)
    when called at the top level on the CPU backend; inside a user's `jax.jit`/`vmap`/`grad` it is inlined into
    the caller's program (whose options apply), as a plain `filter_jit` is."""
    if fun is None:
        return functools.partial(jit, options=options, **jitkwargs)
    return _tuned(eqx.filter_jit, fun, jitkwargs, options)


def array_jit(fun, **jitkwargs):
    """`jit` over `jax.jit` (every argument traced, Python numbers included)."""
    return _tuned(jax.jit, fun, jitkwargs)


def _tuned(make, fun, jitkwargs, options=None):
    options = COMPILER_OPTIONS if options is None else options
    plain = make(fun, **jitkwargs)
    if not options:
        return plain
    tuned = make(fun, compiler_options=dict(options), **jitkwargs)

    filtered = make is eqx.filter_jit

    @functools.wraps(fun)
    def call(*args, **kwargs):
        if not _top_level() or not _on_cpu():
            return plain(*args, **kwargs)
        if _executables.active():  # stored executables (`_executables`)
            return _executables.call(tuned, fun, options, args, kwargs, filtered=filtered)
        return tuned(*args, **kwargs)

    call.lower = lambda *a, **k: (tuned if _on_cpu() else plain).lower(*a, **k)  # the top
    # level's program (on a GPU, lowering with the CPU options failed at compile)
    if hasattr(tuned, "_cached"):
        call._cached = tuned._cached
    return call


def device(x, dtype=None):
    """One host array (NumPy array, number or nested list) on the device without compiling
    anything: in jax 0.10 `jnp.asarray` of a NumPy array or a number runs a compiled `stage`
    program per shape and dtype (and `jnp.stack` one per count and shape), each tens of ms on
    a first call; `device_put` runs none (it also takes pytrees of NumPy arrays)."""
    return jax.device_put(np.asarray(x, dtype=dtype))
