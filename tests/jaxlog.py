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
