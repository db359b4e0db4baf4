"""The grid plan of a search: candidate structures, (N, M) pairs, order classes and every
static that fixes the compiled chunk's shapes (`ChunkStatic`), built once per grid."""

from __future__ import annotations

import functools
import itertools
import math
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import _batch
from .._boundary import window_list
from .._gram import MIN_VALID
from .._modulating import MAX_DEGREE
from .._observers import validation_window
from .._quadrature import (
    kernel_bucket,
    kernel_length,
    legendre_coefficients,
    record_bucket,
)
from .._signals import Signals
from .._solve import default_eta

SCORES = ("E", "J", "fit", "aic", "bic")


def delay_edge_notes(delays, input_names, grid: list, fitted=None) -> tuple:
    """A note per input whose delay is the largest (or the smallest, above 0) value of a
    delay grid of two or more (`grid`: per input, the values tried): the best delay may lie
    beyond the grid (a 5 s dead time searched on (0, 1) s returned 1 s, a DC gain 11 standard
    errors off, status ok). `fitted` (per input, the delay fitted from there, or None): a
    fitted delay back inside the grid needs no note, one beyond it says so."""
    out = []
    for k, values in enumerate(grid):
        d, lo, hi = float(np.asarray(delays)[k]), min(values), max(values)
        side = "largest" if d == hi else "smallest" if d == lo and lo > 0 else None
        f = None if fitted is None else fitted[k]
        if hi > lo and side and (f is None or not lo <= f <= hi):
            name = input_names[k] if input_names else f"u{k + 1}"
            out.append(f"the delay of {name!r} ({d:g}) is the {side} of its grid "
                       f"({lo:g}..{hi:g}): the best delay may lie beyond it, and the model "
                       "(and any standard errors) are then wrong; widen delays= to check"
                       if f is None else
                       f"the delay of {name!r} was the {side} of its grid ({lo:g}..{hi:g}), "
                       f"{d:g}, and output error moved it beyond, to {f:g}: the structure and "
                       "the MF settings were chosen at the grid's edge; widen delays= to "
                       "check them")
    return tuple(out)


# candidates per vmapped batch of the validation simulations (lax.map): each holds its
# candidates' (window, states) drive; 32 against 64: warm 0.63-0.64 s against 0.90-0.92 s on
# 1728 E-scored candidates (T = 6000), 0.25-0.26 s against 0.31-0.33 s on the on-line grid's
# 39 x 32 (T = 3000; its chunks of 96 fill 3 blocks of 32, not 2 of 64), results bitwise equal
VALIDATION_BATCH = 32


CHUNK_SETTINGS = 8  # (h, delays) settings per compiled chunk by default (cache-sized)


def grid_values(x, name: str) -> list:
    vals = [x] if np.ndim(x) == 0 else list(x)  # a model's mf.N is a 0-d array
    if not vals:
        raise ValueError(f"search(): the {name} grid is empty")
    return vals


def distinct(vals: list) -> list:
    """The grid's values once each, in their first order (h=(2, 2) listed every candidate
    twice, each computed again: n and m were merged already)."""
    return list(dict.fromkeys(vals))


def delay_grids(delays) -> list[list[float]]:
    """The per-input delay grids of a `delays=` argument as lists of floats."""
    return [distinct([float(d) for d in grid_values(dk, f"delays[{k}]")])
            for k, dk in enumerate(delays)]


def structures(n_grid, m_grid, K: int) -> list[tuple[int, tuple[int, ...]]]:
    out = []
    for n in sorted(set(int(v) for v in n_grid)):
        if n < 1:
            raise ValueError(f"search(): orders n must be >= 1 (got {n})")
        per_input = []
        for k in range(K):
            allowed = sorted(set(int(v) for v in m_grid[k])) if m_grid is not None else range(n)
            per_input.append([mk for mk in allowed if 0 <= mk <= n])
        for m in itertools.product(*per_input):
            out.append((n, tuple(m)))
    return out


class ChunkStatic(eqx.Module):
    """Everything that fixes shapes and control flow of the compiled chunk."""

    n_max: int = eqx.field(static=True)
    m_max: tuple[int, ...] = eqx.field(static=True)
    ft_inputs: tuple[int, ...] = eqx.field(static=True)  # inputs that may have m_k = n
    length: int = eqx.field(static=True)  # kernel length
    degree: int = eqx.field(static=True)  # Legendre degree = max N + M
    sources: tuple = eqx.field(static=True)  # (kind, k, rule) of every moment source
    col_deriv: tuple[int, ...] = eqx.field(static=True)  # derivative order of every column
    col_source: tuple[int, ...] = eqx.field(static=True)  # source of each of the first p columns
    devices: int = eqx.field(static=True)  # devices the (h, delays) axis is sharded over
    v_length: int = eqx.field(static=True)  # validation buffer: the window's length or a bound
    simulate: bool = eqx.field(static=True)
    batch: int = eqx.field(static=True)  # candidates per vmapped validation batch
    apart: bool = eqx.field(static=True)  # the validation simulations in a program of their own


def device_mesh():
    devices = jax.devices()
    return jax.make_mesh((len(devices),), ("c",), axis_types=(jax.sharding.AxisType.Auto,))


class Plan(NamedTuple):
    """A checked grid, compiled once: everything but the data (`search` = `run_plan(plan_search(..))`)."""

    static: ChunkStatic
    eta: jax.Array
    structs: list
    cand: dict  # per candidate of a setting: its (N, M) pair "nm", order "n", padded "mask",
    # feed-through inputs "ft" and parameter count "k"
    nm: dict
    hd: list
    combos: list
    columns: tuple[np.ndarray, np.ndarray]  # (N, M) pair and structure of each group column
    chunk: int
    sharding: jax.sharding.NamedSharding
    score: str
    n_samples: int
    n_padded: int  # the record padded to this length (`record_bucket`) before the chunk sees it
    n_inputs: int
    where: dict  # values, not shapes: "segments" (S, 2) identification windows [start, end),
    # the validation window's "v_start" and length "v_valid" and the observer's length "ob", in
    # samples (a new fold, or a shorter window under `v_bound`, reuses the compiled chunk)
    small: bool = False  # the grid fits in one chunk (split over the cores: one round)


def identification_segments(signals: Signals, identify, fn: str = "search") -> tuple:
    """(start, end) sample ranges (end exclusive) of the identification window(s): one (t0, t1)
    window or a list of them (e.g. the experiments of `Signals.concatenate`); default the record."""
    if identify is None:
        return ((0, signals.n_samples),)
    windows = window_list(identify)
    T, dt, t0 = signals.n_samples, signals.dt, signals.t0
    out = []
    for w in windows:
        if len(w) != 2:
            raise ValueError(f"{fn}(): identify must be a window (t0, t1) or a list of them "
                             f"(got {w!r})")
        a, b = round((float(w[0]) - t0) / dt), round((float(w[1]) - t0) / dt)
        if not (0 <= a < b <= T - 1):
            raise ValueError(f"{fn}(): identify window ({float(w[0]):g}, {float(w[1]):g}) must "
                             f"lie inside the record [{t0:g}, {t0 + (T - 1) * dt:g}] with "
                             "start < end")
        out.append((a, b + 1))
    return tuple(out)


def plan_search(signals: Signals, *, n, N, M, h, m, delays, score, validate, observer_window, eta,
          chunk_size, simulate, span_bound: float = 0.0, identify=None,
          n_padded: int | None = None, v_bound: int | None = None,
          split: bool = False, apart: bool = False) -> Plan:
    """Check the grid against the record's shape and build the static parts of `search`.

    The record is padded to `n_padded` samples (default `record_bucket`) and the validation
    window to `v_bound` (default its `record_bucket`: windows of one length share it; a
    share of the record gives its `window_bucket`, `holdout_search`), which may run past the
    padded record's end (the last sample is held there); neither
    padding counts (the Gram integral and E end with the data), so records and windows of
    every length in a bucket share one compilation. `span_bound` (time units) pads the
    kernels to at least this h + delay, so that plans with different delays share one (the
    on-line identifier). `split`: a grid that fits in one chunk is cut into one chunk per
    core (`search`; a caller that plans grids of many sizes keeps one chunk each, so that
    sizes do not multiply the compiled chunk shapes). `apart`: with one device, the validation
    simulations of an E-scored grid run as a program of their own (`validate_blocks`), which
    every grid on the record's layout with the same largest order and window shares, so a new
    grid compiles its solves only (`search`: a user trying grid after grid). The on-line
    identifier and `estimate` plan one grid per record layout and keep them in the chunk: apart,
    a warm on-line re-identification ran 6.2-6.5 -> 7.6-8.6 ms and its cold run 5.6-5.75 ->
    6.2-6.3 s (`benchmarks/online_latency.py --quick`), `estimate`'s hold-out search of 100
    records 676-683 -> 701-709 ms."""
    if not isinstance(signals, Signals):
        raise TypeError("search(): signals must be a Signals")
    if score not in SCORES:
        raise ValueError(f"search(): unknown score {score!r}; use one of {SCORES}")
    if not (isinstance(chunk_size, (int, np.integer)) and chunk_size >= 1):
        raise ValueError(f"search(): chunk_size must be an integer >= 1 (got {chunk_size!r})")
    if not simulate and score != "J":
        raise ValueError(f"search(): score {score!r} needs simulate=True (or use score='J')")
    if not simulate and (validate is not None or observer_window is not None):
        raise ValueError("search(): validate= and observer_window= set where E and fit are "
                         "scored, which simulate=False skips (they did nothing); drop them, "
                         "or use simulate=True")
    K = signals.n_inputs
    n_grid = grid_values(n, "n")
    N_grid = distinct([float(v) for v in grid_values(N, "N")])
    M_grid = distinct([float(v) for v in grid_values(M, "M")])
    h_grid = distinct([float(v) for v in grid_values(h, "h")])
    if m is not None:
        m = [grid_values(mk, f"m[{k}]") for k, mk in enumerate(m)]
        if len(m) != K:
            raise ValueError(f"search(): m needs one list of orders per input ({K}), got {len(m)}")
    if delays is not None:
        delays = delay_grids(delays)
        if len(delays) != K:
            raise ValueError(f"search(): delays needs one list per input ({K}), got {len(delays)}")
    else:
        delays = [[float(v)] for v in np.asarray(signals.delays)]
    for name, vals in (("N", N_grid), ("M", M_grid), ("h", h_grid)):
        if any(not math.isfinite(v) or v <= 0 for v in vals):
            raise ValueError(f"search(): {name} values must be finite and > 0 (got {vals})")
    for k, dk in enumerate(delays):
        for j, d in enumerate(dk):
            if d < 0 or d >= signals.duration:
                raise ValueError(f"search(): delays[{k}][{j}] must be >= 0 and shorter than "
                                 f"the record ({signals.duration:g} time units; got "
                                 f"delays[{k}][{j}]={d:g})")
    structs = structures(n_grid, m, K)
    if not structs:
        raise ValueError("search(): no structure in the grid (check n and m)")
    n_max = max(s[0] for s in structs)
    m_max = tuple(max(s[1][k] for s in structs) for k in range(K))
    ft_inputs = tuple(
        k for k in range(K)
        if any(s[1][k] == s[0] for s in structs) and not signals.smooth[k]
        and signals.output_rule == "cubic"
    )
    if any(v != int(v) for v in N_grid + M_grid):
        raise ValueError("search(): N and M must be integers (the moment basis is polynomial)")
    if max(N_grid) + max(M_grid) > MAX_DEGREE:
        raise ValueError(f"search(): N + M must be <= {MAX_DEGREE}")
    if min(N_grid) < 1 or min(M_grid) < 1:
        raise ValueError("search(): N and M must be >= 1")
    n_of = np.asarray([st[0] for st in structs])
    nm_pairs = [(a, b) for a in N_grid for b in M_grid if min(a, b) >= n_of.min()]
    if not nm_pairs:
        raise ValueError("search(): every candidate has N < n or M < n; widen N, M or lower n")
    hd = list(itertools.product(h_grid, itertools.product(*delays)))
    combos = [(a, b, hv, dv) for hv, dv in hd for a, b in nm_pairs]  # index g * NM + nm
    h_max = max(h_grid)
    delay_max = max((max(dk) for dk in delays), default=0.0)
    dt = signals.dt
    first = kernel_length(h_max + delay_max, dt) - 1  # support_samples, on the host
    p_needed = n_max + 1 + sum(mk + 1 for mk in m_max) + int(signals.offset)
    segments = identification_segments(signals, identify)
    valid = sum(max(b - a - first, 0) for a, b in segments)  # samples the Gram integral sums
    if valid < max(MIN_VALID, 2 * p_needed):
        raise ValueError(
            f"search(): h={h_max:g} (+ delays {delay_max:g}) leaves too few valid samples in "
            f"the {'record' if identify is None else 'identify windows'} ({valid} samples); "
            "use smaller h"
        )
    v0, v_len, ob = validation_window(signals, validate, observer_window, n_max, "search")
    T_pad = record_bucket(signals.n_samples) if n_padded is None else n_padded
    if v_bound is None:  # may run past the padded record's end (held last sample)
        v_bound = record_bucket(v_len)
    if not (signals.n_samples <= T_pad and v_len <= v_bound):
        raise ValueError(f"search(): the validation window ({v_len} samples) must fit "
                         f"v_bound={v_bound} and the record the padded one ({T_pad} samples)")
    p = p_needed
    eta = jax.device_put(default_eta(p, signals.offset)) if eta is None else jnp.asarray(
        eta, dtype=jnp.float64)
    if eta.shape != (p,):
        raise ValueError(f"search(): eta must have {p} entries (padded layout: a_0..a_{n_max}, "
                         f"each input's b_k0..b_km with m = {list(m_max)}"
                         + (", the offset" if signals.offset else "") + f"), got {eta.size}")
    check_eta_reaches("search", np.asarray(eta), structs, signals.offset)
    # moment sources and the Legendre coefficients of every column for every (N, M)
    sources = [("y", -1, signals.output_rule)]
    sources += [("u", k, "cubic" if signals.smooth[k] else signals.intersample[k])
                for k in range(K)]
    if signals.offset:
        sources.append(("one", -1, "zoh"))
    sources += [("v", k, "cubic") for k in ft_inputs]
    cols = [(0, None, i, 1.0) for i in range(n_max + 1)]  # (source, minus source, i, sign)
    cols += [(1 + k, None, j, -1.0) for k in range(K) for j in range(m_max[k] + 1)]
    if signals.offset:
        cols.append((1 + K, None, 0, -1.0))
    n_fixed = 1 + K + int(signals.offset)
    cols += [(n_fixed + q, 1 + k, i, 1.0) for q, k in enumerate(ft_inputs)
             for i in range(n_max + 1)]
    degree = int(max(a + b for a, b in nm_pairs))
    coef = np.zeros((len(nm_pairs), len(cols), len(sources), degree + 1))
    pair_N, pair_M = [a for a, _ in nm_pairs], [b for _, b in nm_pairs]
    by_deriv = {i: _coefficients(tuple(pair_N), tuple(pair_M), i, degree) for i in {c[2] for c in cols}}
    for j, (src, minus, i, sign) in enumerate(cols):
        coef[:, j, src] += sign * by_deriv[i]
        if minus is not None:
            coef[:, j, minus] -= sign * by_deriv[i]
    nm = jax.device_put({"N": np.asarray([a for a, _ in nm_pairs]),  # device_put: no program
                         "M": np.asarray([b for _, b in nm_pairs]), "coef": coef})
    # the candidates of one (h, delays) setting, order class by order class: every (N, M) with
    # N, M >= n x every structure of order n; each solved in the padded layout with its mask
    col_nm, col_struct = [], []
    for n_c in sorted({st[0] for st in structs}):
        members = [j for j, st in enumerate(structs) if st[0] == n_c]
        pairs = [r for r, (a, b) in enumerate(nm_pairs) if min(a, b) >= n_c]
        col_nm += [r for r in pairs for _ in members]
        col_struct += [j for _ in pairs for j in members]
    col_nm, col_struct = np.asarray(col_nm), np.asarray(col_struct)
    per_struct = {
        "n": np.asarray([st[0] for st in structs], dtype=np.int32),
        "mask": np.asarray([_mask(st, n_max, m_max, signals.offset) for st in structs]),
        "ft": np.asarray([[st[1][k] == st[0] for k in range(K)] for st in structs],
                         dtype=bool).reshape(len(structs), K),
        "k": np.asarray([st[0] + sum(mk + 1 for mk in st[1]) + int(signals.offset)
                         for st in structs], dtype=np.float64),
    }
    cand = jax.device_put({**{key: v[col_struct] for key, v in per_struct.items()},
                           "nm": col_nm.astype(np.int32)})
    static = ChunkStatic(
        n_max, m_max, ft_inputs,
        kernel_bucket(kernel_length(max(h_max + delay_max, span_bound), dt)), degree,
        tuple(sources), tuple(c[2] for c in cols), tuple(c[0] for c in cols[:p]),
        len(jax.devices()), v_bound, bool(simulate),
        VALIDATION_BATCH, bool(apart),
    )
    mesh = device_mesh()
    n_dev = mesh.devices.size
    small = len(hd) <= chunk_size
    if split and n_dev == 1 and small:  # a grid of one chunk: split over the cores, whose
        # threads run the chunks at once once the program is compiled (`run_plan`)
        chunk = math.ceil(len(hd) / min(_batch.WORKERS, len(hd)))
    else:
        chunk = n_dev * math.ceil(min(chunk_size, len(hd)) / n_dev)  # no padding beyond the grid
    sharding = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("c"))
    where = jax.device_put({"segments": np.asarray(segments, dtype=np.int32),
                            "v_start": np.int32(v0), "v_valid": np.int32(v_len),
                            "ob": np.int32(ob)})
    return Plan(static, eta, structs, cand, nm, hd, combos, (col_nm, col_struct),
                chunk, sharding, score, signals.n_samples, T_pad, K, where, small)


@functools.lru_cache(maxsize=128)
def _coefficients(pair_N: tuple, pair_M: tuple, i: int, degree: int) -> np.ndarray:
    """`legendre_coefficients` of every (N, M) pair, memoised: constants of a grid."""
    out = legendre_coefficients(pair_N, pair_M, i, degree)
    out.setflags(write=False)
    return out


def check_eta_reaches(fn: str, eta: np.ndarray, structs, offset: bool) -> None:
    """Refuse an eta (padded layout) that is zero on every column of a structure: eta^T theta
    = 1 (eq. 11) has no solution there, and its candidates came back flagged (nonfinite,
    a_n_zero, unstable), unsaid; the on-line identifier then never chose that order (eta = 1
    on a_3 alone with n = (2, 3): every model third order)."""
    if not structs:  # (the caller refuses an empty grid in its own words)
        return
    n_max = max(s[0] for s in structs)
    m_max = tuple(max(s[1][k] for s in structs) for k in range(len(structs[0][1])))
    if eta.shape != (len(_mask(structs[0], n_max, m_max, offset)),):
        return  # the caller refuses a wrong length in its own words
    dead = [s for s in structs if not np.any(eta[np.asarray(_mask(s, n_max, m_max, offset))])]
    if dead:
        n, m = dead[0]
        raise ValueError(
            f"{fn}(): eta is zero on every column of {len(dead)} of the {len(structs)} "
            f"structures (the first: n={n}, m={list(m)}), so eta^T theta = 1 (eq. 11) has no "
            "solution for them and each would come back flagged; give eta a nonzero entry on "
            f"their columns (padded layout: a_0..a_{n_max}, each input's b_k0..b_km with "
            f"m = {list(m_max)}, the offset), or leave them out of the grid")


def _mask(s, n_max, m_max, offset):
    n, m = s
    mask = [i <= n for i in range(n_max + 1)]
    for k, mk in enumerate(m_max):
        mask += [j <= m[k] for j in range(mk + 1)]
    return mask + ([True] if offset else [])
