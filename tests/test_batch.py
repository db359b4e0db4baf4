"""Batches of records (`mfmjax._batch`): chunks of one program, run on one thread per core."""

import threading

import jax.numpy as jnp
import numpy as np

import mfmjax
from mfmjax import _batch


def _weighted(sig, model, n_samples):
    """`map_pairs` hands each record padded to its bucket (300 -> 320 samples here) with its
    own length: only those samples may count (the direct sums below check it)."""
    own = jnp.arange(sig.y.shape[0]) < n_samples
    return jnp.sum(jnp.where(own, sig.y * sig.u[:, 0], 0.0)) * model["g"] + model["c"]


def test_in_parallel_compiles_first_then_uses_threads(monkeypatch):
    """The first chunk of each program (group key, size) runs alone on the calling thread;
    the others run on the worker threads; every chunk runs exactly once."""
    monkeypatch.setattr(_batch, "WORKERS", 2)
    main = threading.get_ident()
    chunks = [("a", [0, 1]), ("a", [2, 3]), ("a", [4]), ("b", [5, 6]), ("a", [7, 8]),
              ("a", [9]), ("b", [10, 11])]
    seen = []
    barrier = threading.Barrier(2, timeout=30)  # two pool chunks must overlap in time

    def run(idx):
        seen.append((tuple(idx), threading.get_ident()))
        if idx in ([2, 3], [7, 8]):
            barrier.wait()
        return idx

    done = _batch.in_parallel(run, chunks)
    assert sorted(map(tuple, done)) == sorted(tuple(i) for _, i in chunks)
    ran = dict(seen)
    assert len(seen) == len(chunks)
    for first in ((0, 1), (4,), (5, 6)):
        assert ran[first] == main
    assert {ran[(2, 3)], ran[(7, 8)]} & {main} == set()
    assert ran[(2, 3)] != ran[(7, 8)]  # the barrier passed: both ran at once


def test_map_pairs_on_threads_equals_one_thread_and_the_direct_call(monkeypatch):
    rng = np.random.default_rng(3)
    count = 4 * _batch.BATCH + 3  # four mapped chunks and three single pairs
    records = [mfmjax.Signals(rng.standard_normal(300), rng.standard_normal(300), dt=0.1)
               for _ in range(count)]
    models = [{"g": np.float64(rng.standard_normal()), "c": np.float64(i)}
              for i in range(count)]
    out = {}
    for workers in (1, 2):
        monkeypatch.setattr(_batch, "WORKERS", workers)
        out[workers] = np.asarray(_batch.map_pairs(_weighted, records, models))
    np.testing.assert_array_equal(out[1], out[2])  # bitwise: the same programs, same data
    direct = [float(np.sum(r.y * r.u[:, 0]) * m["g"] + m["c"]) for r, m in zip(records, models)]
    np.testing.assert_allclose(out[2], direct, rtol=1e-12)  # summation order: rounding only


def test_map_pairs_on_the_host_equals_on_the_device():
    """`device=False`: every result a NumPy value (chunks and single pairs alike), bitwise
    those of the default call, which puts them back on the device."""
    import jax

    rng = np.random.default_rng(4)
    count = _batch.BATCH + 1  # one mapped chunk and one single pair
    records = [mfmjax.Signals(rng.standard_normal(300), rng.standard_normal(300), dt=0.1)
               for _ in range(count)]
    models = [{"g": np.float64(rng.standard_normal()), "c": np.float64(i)}
              for i in range(count)]
    on_device = _batch.map_pairs(_weighted, records, models)
    on_host = _batch.map_pairs(_weighted, records, models, device=False)
    assert all(isinstance(x, jax.Array) for x in on_device)
    assert all(isinstance(x, np.ndarray | np.generic) for x in on_host)  # 0-d: np.float64
    np.testing.assert_array_equal(np.asarray(on_host), np.asarray(on_device))
