"""The compiled chunk: Grams of every (N, M) from the moments, every candidate's masked solve
in the padded layout, the validation simulations; and the driver that runs a plan chunk by
chunk."""

from __future__ import annotations

import threading
import time
from concurrent.futures import ThreadPoolExecutor

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import _batch
from .._gram import (
    first_position,
    input_rules,
    input_varies,
    level_vector,
    read_samples,
    signal_levels,
    steady_input_columns,
)
from .._identify import FEEDTHROUGH_STEPS
from .._jit import RUN_ONCE_OPTIONS, jit
from .._linalg import hurwitz
from .._quadrature import edge_padded
from .._signals import Signals
from .._solve import DEAD_COLUMN_RTOL, centred_eta, constrained_solve, finish_solve, uncentred
from .._status import Status
from ._grid import VALIDATION_BATCH, ChunkStatic, Plan
from ._moments import moment_gram
from ._result import collect
from ._validation import validate_candidate

# candidates per vmapped block of the small solves: the padded KKT solve and conditioning of
# a whole chunk at once ran from memory; in blocks of 128 they stay in cache (14,464-candidate
# grid, T = 8000: warm search 0.22 -> 0.17 s; blocks of 64: 0.18 s, 256: 0.20 s)
SOLVE_BLOCK = 128


def in_blocks(fn, xs, block: int):
    """`fn` vmapped over the leading axis of `xs` in blocks of `block` (`lax.map`), the axis
    padded with its last element to whole blocks (`lax.map`'s remainder would compile the
    body a second time); the outputs cut back to the axis' length."""
    total = jax.tree.leaves(xs)[0].shape[0]
    block = min(block, total)
    padded = -(-total // block) * block
    xs = jax.tree.map(lambda x: jnp.concatenate([x, jnp.repeat(x[-1:], padded - total, 0)]), xs)
    leaves, tree = jax.tree.flatten(xs)
    full = [x.size > 0 for x in leaves]
    if all(full):
        return jax.tree.map(lambda v: v[:total], jax.lax.map(fn, xs, batch_size=block))
    # leaves with no elements (the inputs' axis of a record without input, K = 0) stay out of
    # `lax.map`, whose batching reshape cannot infer their sizes; empty outputs likewise

    def body(kept):
        it = iter(kept)
        return fn(jax.tree.unflatten(tree, [next(it) if f else jnp.zeros(x.shape[1:], x.dtype)
                                            for x, f in zip(leaves, full)]))

    shapes = jax.eval_shape(body, [x[0] for x, f in zip(leaves, full) if f])
    outs, out_tree = jax.tree.flatten(shapes)
    mapped = jax.lax.map(lambda kept: [o for o, s in zip(jax.tree.leaves(body(kept)), outs)
                                       if s.size > 0],
                         [x for x, f in zip(leaves, full) if f], batch_size=block)
    it = iter(mapped)
    return jax.tree.unflatten(out_tree, [next(it)[:total] if s.size > 0 else
                                         jnp.zeros((total,) + s.shape, s.dtype) for s in outs])


def evaluate_chunk(sig: Signals, static: ChunkStatic, eta_full, groups, cand, nm, where):
    """All candidates of a chunk of (h, delays) groups: for every group, the plan's candidates
    `cand` ((N, M) pair x structure, order class by order class): outputs (G, C_group, ...)."""
    K = sig.n_inputs
    n_max, m_max = static.n_max, static.m_max
    p = n_max + 1 + sum(mk + 1 for mk in m_max) + int(sig.offset)
    n_src, Q = len(static.sources), static.degree + 1
    finite = jnp.isfinite(sig.y).all() & jnp.isfinite(sig.u).all()
    # over the identification windows only, as `identify` on the window's own record
    idx = jnp.arange(sig.u.shape[0])
    segs = where["segments"]
    inside = jnp.any((idx[:, None] >= segs[None, :, 0]) & (idx[:, None] < segs[None, :, 1]),
                     axis=1)
    hpow_i = jnp.asarray(static.col_deriv, dtype=jnp.float64)
    src_of = np.asarray(static.col_source)
    pad = np.cumsum([n_max + 1] + [mk + 1 for mk in m_max])  # b blocks in the padded layout

    # with an offset term the Grams are those of the centred signals (`signal_levels`: the
    # means over the identification windows, as `identify` on the window's own record)
    levels = signal_levels(sig, inside) if sig.offset else None
    lv = None if levels is None else level_vector(levels, pad[:K], p)

    def one_nm(H, W, scale, h, coef, steady):
        Cf = coef * (h ** (-hpow_i))[:, None, None]  # (p_ext, sources, Q)
        Cflat = Cf.reshape(Cf.shape[0], n_src * Q)
        Gx = Cflat @ H @ Cflat.T
        w = Cflat[:p] @ W.reshape(n_src * Q, -1)  # column kernels
        bounds = jnp.sum(jnp.abs(w), axis=1) * scale[src_of]
        alive = jnp.sqrt(jnp.maximum(jnp.diagonal(Gx)[:p], 0.0)) > DEAD_COLUMN_RTOL * bounds
        return Gx, alive & ~steady

    a_idx = np.arange(n_max + 1)

    def solve(Gx, alive, excited, h, N, M, c):
        """One candidate in the padded layout, the columns beyond its orders masked: one
        program for every order class (the order `c["n"]` is traced)."""
        n, mask, ft = c["n"], c["mask"], c["ft"]
        active = mask & alive
        eta = jnp.where(mask, eta_full, 0.0)
        eta = eta if lv is None else centred_eta(eta, lv)
        G = Gx[:p, :p]
        if static.ft_inputs:  # m_k = n: the output columns corrected by D_k (see _gram)
            def step(_, carry):  # one program for every step (unrolled: 25 % more compile)
                theta, _ = carry
                an = jnp.where(theta[n] != 0, theta[n], 1.0)
                P = jnp.eye(Gx.shape[0], p)
                for qi, k in enumerate(static.ft_inputs):
                    Dk = jnp.where(ft[k] & (a_idx <= n), theta[pad[k] + n] / an, 0.0)
                    P = P.at[p + qi * (n_max + 1) + a_idx, a_idx].set(-Dk)
                G = P.T @ Gx @ P
                return constrained_solve(G, eta, active, conditioning=False)[0], G

            theta = constrained_solve(G, eta, active, conditioning=False)[0]
            theta, G = jax.lax.fori_loop(0, FEEDTHROUGH_STEPS, step, (theta, G))
        theta, cond, reduced = constrained_solve(G, eta, active)
        theta = theta if lv is None else uncentred(theta, lv)
        dead = jnp.any(mask & ~alive)
        status, div, quad, J_rel = finish_solve(theta, G, reduced, n, finite, excited & ~dead,
                                                n_max=n_max, levels=lv)
        norm = theta / div
        b = [jnp.zeros(n_max + 1).at[: m_max[k] + 1].set(norm[pad[k] : pad[k] + m_max[k] + 1])
             for k in range(K)]
        return dict(
            theta=theta, a=norm[: n_max + 1], b=jnp.stack(b, 0) if K else jnp.zeros((0, n_max + 1)),
            offset=norm[p - 1] if sig.offset else jnp.zeros((), jnp.float64),
            J=J_rel,
            J_raw=h ** (N + M + 1) * jnp.sqrt(quad), cond=cond, status=status,
        )

    def grams(hd):  # one (h, delays) setting: the Gram of every (N, M)
        h, delays = hd
        H, W, scale = moment_gram(sig, static, h, delays, segs, levels)
        # the excitation test on the samples each (delayed) input's columns read
        varies = input_varies(sig.u, read_samples(
            sig.n_samples, segs, first_position(h, delays, sig.dt), h, delays, sig.dt,
            input_rules(sig), [k in static.ft_inputs for k in range(K)]))
        steady = steady_input_columns(varies, n_max + 1, [mk + 1 for mk in m_max], sig.offset)
        Gx, alive = jax.vmap(lambda coef: one_nm(H, W, scale, h, coef, steady))(nm["coef"])
        return Gx, alive, jnp.all(varies)

    def solve_pair(g, c):  # candidate `c` at setting `g`
        return solve(Gx[g, c["nm"]], alive[g, c["nm"]], excited[g], groups["h"][g],
                     nm["N"][c["nm"]], nm["M"][c["nm"]], c)

    # the signal-sized work one setting at a time (cache-sized; vmapped over the devices'
    # blocks of the sharded axis), the small solves batched over all of them
    # (explicit sizes in every reshape: with no input, K = 0, the arrays of the inputs' axis
    # are empty and a -1 could not be inferred)
    G, C = groups["h"].shape[0], cand["n"].shape[0]

    def per_dev(x):  # the leading axis split into the devices' blocks
        return x.reshape((static.devices, x.shape[0] // static.devices) + x.shape[1:])

    Gx, alive, excited = jax.vmap(lambda hd: jax.lax.map(grams, hd))(
        (per_dev(groups["h"]), per_dev(groups["delays"])))
    Gx, alive, excited = (x.reshape((G,) + x.shape[2:]) for x in (Gx, alive, excited))
    # every (setting, candidate) pair in one flat axis (a smaller program than two nested
    # vmaps), solved in cache-sized blocks on each device's share of the settings
    pairs = (jnp.repeat(jnp.arange(G), C),
             jax.tree.map(lambda x: jnp.tile(x, (G,) + (1,) * (x.ndim - 1)), cand))

    def solve_all(xs):
        return in_blocks(lambda gc: solve_pair(*gc), xs, SOLVE_BLOCK)

    lead = 1
    if static.devices > 1:  # a vmap over the devices' shares keeps the axis sharded (with
        # one device it cost 0.1-0.2 s more compile time, so not there)
        pairs = jax.tree.map(per_dev, pairs)
        solve_all, lead = jax.vmap(solve_all), 2
    out = jax.tree.map(lambda x: x.reshape((G, C) + x.shape[lead:]), solve_all(pairs))
    shape = out["status"].shape
    if not static.simulate:  # equation error only (score J): the Routh test all the same
        # (the status said ok for unstable A(s)), not where a_n vanished or values are not
        # finite (those bits say the coefficients are no model), as `identify`
        nan = jnp.full(shape, jnp.nan)
        stable = jax.vmap(hurwitz)(out["a"].reshape(G * C, n_max + 1)).reshape(shape)
        void = (out["status"] & int(Status.NONFINITE | Status.A_N_ZERO)) != 0
        status = out["status"] | jnp.where(void | stable, 0, int(Status.UNSTABLE))
        return dict(out, E=nan, fit=nan, aic=nan, bic=nan, status=status.astype(jnp.int32))
    flat = {  # the padded models of the (G, C) solves as one axis (`validate_candidate`'s c)
        "a": out["a"].reshape(G * C, n_max + 1),
        "b": out["b"].reshape(G * C, K, n_max + 1),
        "offset": out["offset"].reshape(G * C),
        "n": jnp.broadcast_to(cand["n"], shape).reshape(G * C),
        "k": jnp.broadcast_to(cand["k"], shape).reshape(G * C),
        "delays": jnp.broadcast_to(groups["delays"][:, None, :], shape + (K,)).reshape(G * C, K),
    }
    if validated_apart(static):  # the validation simulations: `validate_blocks`, after it,
        # on the candidates padded to whole slabs (the last repeated)
        idx = jnp.minimum(jnp.arange(slab_size(G * C)), G * C - 1)
        return dict(out, status=out["status"].astype(jnp.int32),
                    slab=jax.tree.map(lambda x: x[idx], flat))
    val = in_blocks(lambda c: validate_candidate(sig, static.v_length, c, where), flat,
                    static.batch)
    val = {key: v.reshape(shape) for key, v in val.items()}
    status = (out["status"] | val.pop("status")).astype(jnp.int32)
    return dict(out, status=status, **val)


def validated_apart(static: ChunkStatic) -> bool:
    """The chunk's candidates are validated by a program of their own (`validate_blocks`),
    whose shapes depend on the record, the largest order and the window only, so grids that
    differ in anything else share it (`plan_search(apart=True)`, one device; several devices:
    inside the chunk, sharded with it)."""
    return static.simulate and static.apart and static.devices == 1


# a chunk's candidates go to the validation program padded to a multiple of this (32 blocks):
# the programs of all chunks up to this size are one; the blocks beyond the chunk's own
# candidates are skipped
VALIDATION_SLAB = 32 * VALIDATION_BATCH


def slab_size(count: int) -> int:
    """The validation program's candidate count for a chunk of `count` candidates."""
    return -(-count // VALIDATION_SLAB) * VALIDATION_SLAB


@jit
def validate_blocks(sig: Signals, c, count, where, v_length: int):
    """`validate_candidate` of the first `count` (a value) of the padded candidates `c`
    (leaves (blocks x B, ...), B = `VALIDATION_BATCH`), B at a time (vmapped) in a loop of
    ceil(count / B) trips; the blocks beyond return zeros. (A `lax.map` with the unused blocks
    skipped by `lax.cond` ran 2-4 % slower.)"""
    B = VALIDATION_BATCH
    blocks = jax.tree.map(lambda x: x.reshape((x.shape[0] // B, B) + x.shape[1:]), c)

    def block(cb):
        return jax.vmap(lambda ci: validate_candidate(sig, v_length, ci, where))(cb)

    n_blocks = c["n"].shape[0] // B
    shapes = jax.eval_shape(block, jax.tree.map(lambda x: x[0], blocks))
    init = jax.tree.map(lambda s: jnp.zeros((n_blocks,) + s.shape, s.dtype), shapes)

    def one(i, out):
        res = block(jax.tree.map(lambda x: jax.lax.dynamic_index_in_dim(x, i, keepdims=False),
                                 blocks))
        return jax.tree.map(lambda o, r: jax.lax.dynamic_update_index_in_dim(o, r, i, 0), out,
                            res)

    out = jax.lax.fori_loop(0, (count + B - 1) // B, one, init)
    return jax.tree.map(lambda v: v.reshape((v.shape[0] * v.shape[1],) + v.shape[2:]), out)


def _compile_validation(sig, plan: Plan, where) -> None:
    """`validate_blocks` run on no candidate (count 0: no block simulated) with the slab's
    shapes, so that it compiles while the first chunk does (two cores: two compilers). The
    slab goes in as host arrays here and from the chunk: a chunk's outputs carry the plan's
    mesh, whose sharding would key another program."""
    static, K = plan.static, plan.n_inputs
    size = slab_size(plan.chunk * len(plan.columns[0]))
    slab = {"a": np.zeros((size, static.n_max + 1)), "b": np.zeros((size, K, static.n_max + 1)),
            "offset": np.zeros(size), "n": np.ones(size, np.int32), "k": np.zeros(size),
            "delays": np.zeros((size, K))}
    jax.block_until_ready(validate_blocks(sig, slab, np.int32(0), where, static.v_length))


chunk_jit = jit(evaluate_chunk)
chunk_jit_once = jit(evaluate_chunk, options=RUN_ONCE_OPTIONS)  # a one-chunk search


@jit
def chunk_records_jit(sig: Signals, ys, us, *args):
    """`evaluate_chunk` for records of equal layout (outputs ys (R, T), inputs us (R, T, K)),
    one after another inside one compiled call (`lax.map`: memory of one record)."""
    return jax.lax.map(
        lambda yu: evaluate_chunk(eqx.tree_at(lambda s: (s.y, s.u), sig, yu), *args), (ys, us))


def place(x: np.ndarray, sharding):
    """A global array split over the mesh (works with one or several processes)."""
    return jax.make_array_from_callback(x.shape, sharding, lambda idx: x[idx])


# per program that ran in this process (function, static part, argument shapes): the shape
# and dtype of every output column beyond the candidate axis, so a later run allocates them
# before its chunks start (on threads)
_COLUMNS: dict = {}


def run_plan(plan: Plan, signals: Signals, progress=None, records=None, once=False):
    """Evaluate a plan's grid on `signals` (same length and layout as the plan's record).
    With `records` (a list of `Signals` of that layout, e.g. Monte Carlo realisations) every
    chunk evaluates all of them in one compiled call; returns one `SearchResult` per record.
    `once`: the caller runs this plan once (`search`), so a grid of one chunk scored by J
    alone (no validation simulations), whose program runs once and briefly, is compiled for
    compile time (`RUN_ONCE_OPTIONS`). 760 candidates, T = 8000: first call 1.3-1.8 s against
    2.4-2.8 s, a second call in the process 0.07-0.12 s against 0.025 s. Scored by E, the
    simulations ran 2-3x slower at that level (a second call 2.9-3.2 s against 0.9-1.5 s),
    more than the compile time saved on a later call, so those keep the default options."""
    static, hd, chunk, K = plan.static, plan.hd, plan.chunk, plan.n_inputs
    batch = records if records is not None else [signals]
    if any((r.n_samples, r.n_inputs) != (plan.n_samples, K) for r in batch):
        raise ValueError("search: the signals do not match the plan's record length and inputs")
    col_nm, col_struct = plan.columns
    Cg = len(col_nm)  # candidates per (h, delays) setting
    pad = plan.n_padded - plan.n_samples
    ys, us = (np.stack([edge_padded(np.asarray(x), pad) for x in xs])  # NumPy: no program
              for xs in ([r.y for r in batch], [r.u for r in batch]))
    sig = eqx.tree_at(lambda s: (s.y, s.u), signals.unlabelled(), (ys[0], us[0]))
    starts = list(range(0, len(hd), chunk))
    threaded = plan.sharding.num_devices == 1 and jax.process_count() == 1
    if len(batch) == 1:  # one record: the program `search` uses
        # a grid that fits in one chunk (`plan_search` splits it over the cores)
        quick = once and plan.small and not static.simulate
        fn = chunk_jit_once if quick else chunk_jit
    else:
        fn = chunk_records_jit
    apart = validated_apart(static)
    if apart and records is not None:
        raise ValueError("run_plan: a plan with apart=True validates one record at a time")
    v_where = {k: plan.where[k] for k in ("v_start", "v_valid", "ob")}
    if plan.sharding.num_devices == 1:  # the record on the device once, not at every call
        sig, ys, us = jax.device_put((sig, ys, us))
    program = (fn, static, chunk, tuple(np.shape(x) for x in jax.tree.leaves(
        (sig, ys, us, plan.eta, plan.cand, plan.nm, plan.where))))
    cols, times, early = [{} for _ in batch], {}, []
    done, lock = [0], threading.Lock()

    def run_chunk(c0):
        idx = list(range(c0, min(c0 + chunk, len(hd))))
        real = len(idx)
        idx = idx + [idx[-1]] * (chunk - real)  # pad the last chunk: same shapes
        g = {
            "h": np.asarray([hd[i][0] for i in idx]),
            "delays": np.asarray([hd[i][1] for i in idx], dtype=np.float64).reshape(chunk, K),
        }
        g = {k: place(v, plan.sharding) for k, v in g.items()}
        t0 = time.perf_counter()
        args = (static, plan.eta, g, plan.cand, plan.nm, plan.where)
        one = len(batch) == 1  # one record: the program `search` uses
        out = fn(sig, *args) if one else jax.device_get(fn(sig, ys, us, *args))
        if apart:  # the settings repeated to fill the last chunk are not simulated
            count = np.int32(real * Cg)
            for f in early:  # its compile on another thread (first chunk of a new program)
                f.result()
            val = validate_blocks(sig, jax.device_get(out.pop("slab")), count, v_where,
                                  static.v_length)
            out, val = jax.device_get((out, val))
            out = {k: v[:real] for k, v in out.items()}
            out["status"] = out["status"] | val.pop("status")[:count].reshape(real, Cg)
            out.update({k: v[:count].reshape(real, Cg) for k, v in val.items()})
        res = ([jax.block_until_ready(out)] if one else
               [jax.tree.map(lambda x, r=r: x[r], out) for r in range(len(batch))])
        if jax.process_count() > 1:  # multi-host: every process gets every candidate
            from jax.experimental import multihost_utils

            res = [multihost_utils.process_allgather(x, tiled=True) for x in res]
        for col, rec in zip(cols, res):  # straight into the preallocated columns: memory flat
            for key, val in rec.items():
                val = np.asarray(val)[:real]
                if key not in col:
                    col[key] = np.empty((len(hd) * Cg,) + val.shape[2:], val.dtype)
                col[key][c0 * Cg : (c0 + real) * Cg] = val.reshape((real * Cg,) + val.shape[2:])
        del res
        times[c0] = time.perf_counter() - t0
        if progress is not None:
            with lock:  # in order of completion: `done` only grows
                done[0] += real
                progress(done[0], len(hd))

    t_start = time.perf_counter()
    layout = _COLUMNS.get(program)
    if layout is None:  # a new program: its first chunk alone (it compiles; columns allocated)
        if apart:  # the validation program compiles on another thread meanwhile
            with ThreadPoolExecutor(max_workers=1) as pool:
                early.append(pool.submit(_compile_validation, sig, plan, v_where))
                run_chunk(starts[0])
            early.clear()
        else:
            run_chunk(starts[0])
        rest = starts[1:]
        _COLUMNS[program] = [{k: (v.shape[1:], v.dtype) for k, v in col.items()} for col in cols]
    else:  # it ran before: every chunk may run at once
        for col, lay in zip(cols, layout):
            col.update({k: np.empty((len(hd) * Cg,) + shp, dt) for k, (shp, dt) in lay.items()})
        rest = starts
    if len(rest) > 1 and threaded:
        # the other chunks on a thread per core: a compiled chunk runs its loops on one core
        # and releases the GIL (several devices: the chunk is sharded over them instead)
        with ThreadPoolExecutor(max_workers=min(_batch.WORKERS, len(rest))) as pool:
            list(pool.map(run_chunk, rest))
    else:
        for c0 in rest:
            run_chunk(c0)
    wall = time.perf_counter() - t_start
    times = [times[c0] for c0 in starts]
    # the first chunk compiles: its excess over a typical chunk is the compile time
    typical = float(np.median(times[1:])) if len(times) > 1 else 0.0
    t_compile = max(times[0] - typical, 0.0)
    t_run = wall - t_compile
    n_set = len(hd)
    out = []
    for col, rec in zip(cols, batch):
        col["group"] = np.repeat(np.arange(n_set), Cg) * len(plan.nm["N"]) + np.tile(col_nm, n_set)
        col["struct"] = np.tile(col_struct, n_set)
        out.append(collect(col, plan.combos, plan.structs, rec, static, plan.score, t_compile,
                           t_run, plan.where))
    return out if records is not None else out[0]
