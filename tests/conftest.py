import os
import sys

import jax

jax.config.update("jax_enable_x64", True)
sys.path.insert(0, os.path.dirname(__file__))

SHARED = os.environ.get("MFMJAX_DATA") or os.path.join(os.path.dirname(__file__), "..", "..",
                                                     "shared", "data")


import pytest  # noqa: E402


@pytest.fixture(autouse=True, scope="session")
def _session_compile_cache(tmp_path_factory):
    """One persistent compilation cache per test session, under the pytest tmp base: the run
    starts cold, and every module after the first reads the programs earlier modules compiled
    (the in-memory caches are still dropped per module, below). Exported through
    JAX_COMPILATION_CACHE_DIR so subprocesses (CLI, notebooks) share it and the CLI's own
    cache never writes to the user's folder during tests. Under pytest-xdist the workers share
    it (the session's base folder): a program one worker compiled, another loads."""
    from mfmjax import enable_compile_cache

    base = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        base = base.parent  # the session's folder, shared by the workers
    path = enable_compile_cache(base / "jax-compile-cache")
    if path is not None:
        os.environ["JAX_COMPILATION_CACHE_DIR"] = path
    yield path


@pytest.fixture(autouse=True, scope="module")
def _fresh_jax_caches():
    """Drop compiled executables between test modules: the suite compiles hundreds of
    programs, and one long-lived process holding all of them once crashed inside XLA's
    compiler (a segfault in backend_compile_and_load, not reproducible in isolation)."""
    yield
    jax.clear_caches()
    from mfmjax import _executables

    _executables.clear()


# The heaviest test files first (test time of the 2026-11-24 suite, in this order), the rest
# in their collection order after them: pytest-xdist's `loadfile` hands whole files to the
# workers in collection order, so a heavy file near the end (alphabetically,
# test_settings_values.py) left the other worker idle while it ran.
HEAVY_FIRST = ("test_search.py", "test_cache.py", "test_settings_values.py", "test_estimate.py",
               "test_selection.py", "test_notebooks.py", "test_refine.py", "test_fuzz.py",
               "test_online.py")


def pytest_collection_modifyitems(items):
    rank = {name: i for i, name in enumerate(HEAVY_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable within a file
