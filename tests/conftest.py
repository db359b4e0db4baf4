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


# The test files in decreasing order of their time in the suite (seconds on one worker,
# summed from a run's junit report, 2026-11-27 on the 2-core machine), the rest after them in
# collection order. With `--no-loadscope-reorder`
# (pyproject addopts) pytest-xdist's `loadfile` hands whole files to the workers in this order,
# each worker taking the next file when it is almost done: longest first, so the two workers
# end together (without it, xdist orders files by their number of tests, and one worker sat
# idle for 19 s at the end while the other ran test_notebooks.py).
FILE_SECONDS = {"test_settings_values.py": 177, "test_search.py": 142, "test_estimate.py": 140,
                "test_cache.py": 99, "test_selection.py": 81, "test_cli.py": 79,
                "test_notebooks.py": 70, "test_refine.py": 65, "test_identify.py": 60,
                "test_fuzz.py": 52, "test_online.py": 51, "test_observers.py": 42,
                "test_output_error.py": 31, "test_srivc.py": 30, "test_quadrature.py": 29,
                "test_demo_modes.py": 28, "test_linalg.py": 20, "test_gram_solve.py": 19,
                "test_properties.py": 17, "test_report_cli.py": 15, "test_boundary_cli.py": 13,
                "test_boundary_api.py": 12, "test_prepare.py": 11, "test_analysis.py": 10,
                "test_modulating.py": 7, "test_datasets.py": 5}


def pytest_collection_modifyitems(items):
    items.sort(key=lambda item: -FILE_SECONDS.get(item.path.name, 0))  # stable within a file
