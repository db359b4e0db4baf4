import os
import sys

import jax

jax.config.update("jax_enable_x64", True)
sys.path.insert(0, os.path.dirname(__file__))

SHARED = os.environ.get("MFMJAX_DATA") or os.path.join(os.path.dirname(__file__), "..", "..",
                                                     "shared", "data")


import pytest  # noqa: E402


@pytest.fixture(autouse=True, scope="module")
def _fresh_jax_caches():
    """Drop compiled executables between test modules: the suite compiles hundreds of
    programs, and one long-lived process holding all of them once crashed inside XLA's
    compiler (a segfault in backend_compile_and_load, not reproducible in isolation)."""
    yield
    jax.clear_caches()
