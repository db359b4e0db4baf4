"""Counting JAX compilations in tests, from JAX's own log (`jax_log_compiles`)."""

import contextlib
import logging

import jax


@contextlib.contextmanager
def compiles():
    """Names of the programs JAX compiles inside the block (jitted cores and eager primitives),
    and of those loaded as stored executables (`mfmjax._executables`): a new program either way."""
    from mfmjax import _executables

    names, first_new = [], len(_executables.loaded)

    class Handler(logging.Handler):
        def emit(self, record):
            msg = record.getMessage()
            if msg.startswith("Compiling "):
                names.append(msg.split()[1])

    handler, logger = Handler(), logging.getLogger("jax")
    before = jax.config.jax_log_compiles
    jax.config.update("jax_log_compiles", True)
    logger.addHandler(handler)
    try:
        yield names
    finally:
        names.extend(_executables.loaded[first_new:])
        logger.removeHandler(handler)
        jax.config.update("jax_log_compiles", before)


def eager(names):
    """The entries of `names` (from `compiles`) that are single JAX primitives or `jax.numpy`
    functions compiled on their own: an operation on device arrays outside `jit` (tens of ms
    each on a first call), which the library's public paths avoid (host work in NumPy)."""
    import jax.numpy as jnp

    ops = set(dir(jax.lax)) | set(dir(jnp))
    return [n for n in names if n.startswith("jit(") and n[4:-1] in ops]
