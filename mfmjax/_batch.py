"""Records of one layout as a batch (Monte Carlo realisations, repeated experiments): the
(record, model) pairs of one pytree structure and shape (a `Model`'s structure, or every
structure of one padded order: `mfmjax._padded`) are stacked and mapped through one compiled
program (`lax.map`: each record runs to its own convergence, memory of one record)."""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import equinox as eqx
import jax
import numpy as np

from ._jit import jit
from ._pytree import replace_fields
from ._quadrature import edge_padded, record_bucket
from ._signals import Signals


def stack(trees):
    """Concrete pytrees of one structure -> one pytree with a leading batch axis (stacked on
    the host and put back in one transfer, like `unstack`: no program per count and shape)."""
    return jax.device_put(jax.tree.map(lambda *xs: np.stack(xs), *jax.device_get(trees)))


def unstack(tree, device: bool = True) -> list:
    """The inverse of `stack` (sliced on the host and put back in one transfer: slicing each
    leaf on the device cost as much as the mapped computation itself); `device=False`: the
    NumPy slices, for a caller that reads them on the host."""
    host = jax.device_get(tree)
    count = jax.tree.leaves(host)[0].shape[0]
    out = [jax.tree.map(lambda x, i=i: x[i], host) for i in range(count)]
    return jax.device_put(out) if device else out


def as_records(fn: str, signals) -> tuple[list, bool]:
    """([records], single) for function `fn`: one `Signals`, or a non-empty list of them of one
    layout (a batch of records; ValueError naming the first record that differs)."""
    if isinstance(signals, Signals):
        return [signals], True
    if isinstance(signals, list | tuple) and not signals:
        raise ValueError(f"{fn}(): the list of records is empty; give at least one Signals")
    if not isinstance(signals, list | tuple):
        from ._boundary import swap_hint

        raise TypeError(f"{fn}(): signals must be a Signals or a list of Signals of one "
                        f"layout (a batch of records), got {type(signals).__name__}"
                        f"{swap_hint(fn, signals)}")
    bad = [i for i, r in enumerate(signals) if not isinstance(r, Signals)]
    if bad:
        raise TypeError(f"{fn}(): signals must be a Signals or a list of Signals of one "
                        f"layout (a batch of records); record {bad[0]} is a "
                        f"{type(signals[bad[0]]).__name__}")
    first = signals[0]
    layout = lambda r: (r.n_samples, r.n_inputs, r.dt, r.t0, r.intersample, r.smooth,  # noqa: E731
                        r.offset, r.output_rule)
    for i, r in enumerate(signals[1:], 1):
        if layout(r) != layout(first):
            raise ValueError(
                f"{fn}(): record {i} differs from record 0 in length, inputs, dt, t0, "
                "intersample, smoothing, offset or output rule; a batch needs records of one "
                "layout (give offset=True or False explicitly so the data do not decide it)")
    return list(signals), False


BATCH = 8  # pairs per mapped call: a batch runs in chunks of BATCH and single pairs
WORKERS = min(len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity")
              else os.cpu_count() or 1, 8)  # threads for the chunks (one per core)


def groups(trees) -> list[tuple[object, list[int]]]:
    """(group key, indices) of `trees` grouped by pytree structure (static fields included) and
    leaf shapes, each group cut
    into chunks of `BATCH` and single pairs: a batch's group sizes vary with the data (how
    many records chose a structure) and each size would be a new program; with two sizes a
    structure compiles at most two."""
    out: dict = {}
    for i, t in enumerate(trees):
        shapes = tuple(np.shape(x) for x in jax.tree.leaves(t))  # padded models: one treedef
        out.setdefault((jax.tree.structure(t), shapes), []).append(i)
    chunks = []
    for key, idx in out.items():
        full = len(idx) // BATCH * BATCH
        chunks += [(key, idx[c : c + BATCH]) for c in range(0, full, BATCH)]
        chunks += [(key, [i]) for i in idx[full:]]
    return chunks


@jit
def _mapped(fn, kw, sig, ys, us, lengths, models):
    def one(args):
        y, u, n_samples, model = args
        return fn(eqx.tree_at(lambda s: (s.y, s.u), sig, (y, u)), model, n_samples=n_samples,
                  **kw)

    return jax.lax.map(one, (ys, us, lengths, models))


def padded_record(signals: Signals, to: int | None = None) -> Signals:
    """`signals` padded to `to` samples (default its `record_bucket`) by repeating its last
    sample (NumPy: no program); a record already that long is returned as it is."""
    T = signals.n_samples
    pad = (record_bucket(T) if to is None else to) - T
    if pad == 0:
        return signals
    return replace_fields(signals, **{key: edge_padded(np.asarray(getattr(signals, key)), pad)
                                      for key in ("y", "u")})


def map_pairs(fn, records, models, *, device: bool = True, bucket: int | None = None,
              **kw) -> list:
    """`fn(records[i], models[i], **kw)` for every pair: each chunk of `BATCH` pairs of one
    pytree structure and shape in one compiled call, a single pair by `fn` itself (the program
    a direct call uses). `records`: `Signals` of one layout, each padded to its
    `record_bucket` (`padded_record`; `bucket`: to that length, e.g. a fit part's
    `window_bucket` in its record), `fn` told the record's own length as `n_samples=` (an
    int32 value), so records of every length in a bucket share the programs. `kw` are
    static (hashable) or values (NumPy scalars, e.g. a window start). The
    models' labels and modulating functions are dropped (`fn` does not use them); other
    pytrees (e.g. the search's padded candidates) pass as they are. An entry is None where
    `fn` raised ValueError (e.g. an overflowing simulation in eager mode).
    Chunks run on threads (`in_parallel`). `device=False`: the results as NumPy arrays (no
    transfer back to the device, for callers that read them on the host)."""
    models = [replace_fields(m.unlabelled(), mf=None) if hasattr(m, "unlabelled") else m
              for m in models]
    out = [None] * len(models)
    lengths = [np.int32(r.n_samples) for r in records]
    records = [padded_record(r, bucket) for r in records]

    def run(idx):
        try:
            if len(idx) == 1:
                i = idx[0]
                one = fn(records[i], models[i], n_samples=lengths[i], **kw)
                return [(i, one if device else jax.device_get(one))]
            sig = records[idx[0]].unlabelled()
            res = _mapped(fn, kw, sig, *stack([(records[i].y, records[i].u, lengths[i])
                                               for i in idx]),
                          stack([models[i] for i in idx]))
            return list(zip(idx, unstack(res, device)))
        except ValueError:
            return []

    for pairs in in_parallel(run, groups(models)):
        for i, r in pairs:
            out[i] = r
    return out


def in_parallel(run, chunks) -> list:
    """[run(idx) for (key, idx) in chunks] (`groups`' chunks): the first chunk of each program
    (group key and size) alone, so that it compiles once; the others on `WORKERS` threads, one
    per core (a compiled call releases the GIL; XLA:CPU runs a call's sequential loops on one
    core). One result per chunk, the first chunks of each program first."""
    first, rest, seen = [], [], set()
    for key, idx in chunks:
        (rest if (key, len(idx)) in seen else first).append(idx)
        seen.add((key, len(idx)))
    done = [run(idx) for idx in first]
    if rest:
        with ThreadPoolExecutor(max_workers=min(WORKERS, len(rest))) as pool:
            done += pool.map(run, rest)
    return done


def overlapped(run, meanwhile):
    """`run()` on a second thread while `meanwhile()` (None: nothing) runs on this one, e.g. a
    search while the stages after it compile; `run`'s result (or its exception)."""
    if meanwhile is None:
        return run()
    with ThreadPoolExecutor(max_workers=1) as pool:
        job = pool.submit(run)
        meanwhile()
        return job.result()
