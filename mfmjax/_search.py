r"""Batched structure search over (N, M, h, delays) x (n, m_1..m_K): one compiled computation.

Work sharing:

- for one (h, delays), every $\phi^{(i)}$ of every (N, M) is a polynomial of degree
  $\le N + M$ in $s/h$. Each signal (output, inputs, offset, and the feed-through sources of
  candidates with $m_k = n$) is convolved once with the exact weights of the shifted Legendre
  polynomials $P_q(2s/h - 1)$ (`legendre_weights`, real FFT): its sliding moments. Every
  column of $c(t)$ for every (N, M) is an exact combination $C_{N,M}$ of moments, so with the
  moment Gram $H$ (one per (h, delays)) every Gram is $G_{N,M} = C_{N,M} H C_{N,M}^T$: the
  convolutions and the O(T) Gram work are shared across N, M, orders and derivatives;
- every structure of order n is a masked sub-block of its order's largest Gram: candidates
  are grouped by n (`_Class`: the (N, M) with N, M >= n and the structures of order n, in a
  compact layout with only the columns order n can use), and `constrained_solve` with a column
  mask solves each class batched (masked columns get $\theta_j = 0$), exactly the problem
  `identify` solves for that structure. Its conditioning (flag `ill_conditioned`, `cond`)
  comes from Householder tridiagonalisation + Sturm bisection (`_linalg`);
- every candidate is then simulated from its initial-state-observer estimate on the validation
  window (eq. 14, 17) through a zero-padded realisation of order $n_{max}$ with a state mask,
  in vmapped batches of 64 (`lax.map`) so memory stays flat.

(h, delays) settings are processed in chunks of fixed size (one compilation for the whole
grid, memory flat in the candidate count; results go straight into preallocated columns).
Each chunk's setting axis is sharded over all `jax.devices()` with a 1-D mesh
(`NamedSharding`); within a device, the signal-sized work (moments, H) runs one setting at a
time (`lax.map`: cache-sized) and the small solves are batched over the whole chunk.
"""

from __future__ import annotations

import functools
import itertools
import json
import math
import time
from collections.abc import Callable, Sequence
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._identify import FEEDTHROUGH_STEPS
from ._linalg import hurwitz
from ._model import Model
from ._modulating import ModulatingFunction
from ._observers import _observe_forced, fit_percent, validation_window
from ._quadrature import (
    delayed_samples,
    gregory_weights,
    kernel_length,
    legendre_coefficients,
    legendre_weights,
    support_samples,
)
from ._signals import Signals
from ._simulate import forced_terms
from ._solve import DEAD_COLUMN_RTOL, constrained_solve, solve_status
from ._statespace import realisation
from ._status import Status, describe
from ._structure import Structure

SCORES = ("E", "J", "fit", "aic", "bic")
E_TIE_RTOL = 1e-12  # E values closer than this fraction of int y^2 rank by parameter count


# -- the grid ---------------------------------------------------------------------------------


def _values(x, name: str) -> list:
    vals = [x] if np.isscalar(x) else list(x)
    if not vals:
        raise ValueError(f"search(): the {name} grid is empty")
    return vals


def _structures(n_grid, m_grid, K: int) -> list[tuple[int, tuple[int, ...]]]:
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


class SearchResult(eqx.Module):
    """Ranked candidates of a `search` (numpy arrays, one row per feasible candidate).

    Columns: `n`, `m` (C, K), `N`, `M`, `h`, `delays` (C, K), `J` (scale-free J_rel), `E`,
    `fit`, `aic`, `bic`, `status`, `theta` (C, p_max; padded layout [a_0..a_nmax, b_1.., ..]),
    `a` (C, nmax+1), `b` (C, K, mmax+1), `offset`. `rank` orders them best first by `score`.
    """

    columns: dict
    rank: np.ndarray
    score: str = eqx.field(static=True)
    n_max: int = eqx.field(static=True)
    m_max: tuple[int, ...] = eqx.field(static=True)
    intersample: tuple[str, ...] = eqx.field(static=True)
    has_offset: bool = eqx.field(static=True)
    output_name: str = eqx.field(static=True)
    input_names: tuple[str, ...] = eqx.field(static=True)
    compile_s: float = eqx.field(static=True)
    run_s: float = eqx.field(static=True)

    def __len__(self) -> int:
        return int(self.rank.shape[0])

    def row(self, i: int) -> dict:
        """Candidate of rank `i` (0 = best) as a plain dict."""
        c, j = self.columns, int(self.rank[i])
        n = int(c["n"][j])
        m = [int(v) for v in c["m"][j]]
        return {
            "rank": i + 1,
            "n": n,
            "m": m,
            "N": _num(c["N"][j]),
            "M": _num(c["M"][j]),
            "h": float(c["h"][j]),
            "delays": [float(v) for v in c["delays"][j]],
            "J": _finite(c["J"][j]),
            "E": _finite(c["E"][j]),
            "fit": _finite(c["fit"][j]),
            "aic": _finite(c["aic"][j]),
            "bic": _finite(c["bic"][j]),
            "status": describe(int(c["status"][j])),
            "a": [float(v) for v in c["a"][j][: n + 1]],
            "b": [[float(v) for v in c["b"][j][k][: m[k] + 1]] for k in range(len(m))],
            "offset": float(c["offset"][j]) if self.has_offset else None,
        }

    def best(self, i: int = 0) -> Model:
        """The candidate of rank `i` as a `Model` (parameters exactly as searched)."""
        r = self.row(i)
        c, j = self.columns, int(self.rank[i])
        structure = Structure(r["n"], r["m"])
        return Model(
            a=jnp.asarray(r["a"]),
            b=tuple(jnp.asarray(bk) for bk in r["b"]),
            offset=jnp.asarray(r["offset"] or 0.0),
            delays=jnp.asarray(r["delays"]),
            theta=jnp.asarray(_compact_theta(c["theta"][j], r["n"], r["m"], self)),
            J=jnp.asarray(c["J_raw"][j]),
            J_rel=jnp.asarray(c["J"][j]),
            cond=jnp.asarray(c["cond"][j]),
            status=jnp.asarray(int(c["status"][j]), dtype=jnp.int32),
            mf=ModulatingFunction(r["N"], r["M"], r["h"]),
            structure=structure,
            intersample=self.intersample,
            has_offset=self.has_offset,
            output_name=self.output_name,
            input_names=self.input_names,
        )

    def table(self, top: int = 10) -> str:
        """Readable table of the best `top` candidates."""
        head = (f"{'rank':>4} {'n':>2} {'m':>8} {'N':>4} {'M':>4} {'h':>9} {'delays':>14} "
                f"{'J':>10} {'E':>11} {'fit%':>8} {'aic':>10} {'bic':>10}  status")
        lines = [head]
        for i in range(min(top, len(self))):
            r = self.row(i)
            lines.append(
                f"{r['rank']:>4} {r['n']:>2} {','.join(map(str, r['m'])):>8} {r['N']:>4} "
                f"{r['M']:>4} {r['h']:>9.4g} {','.join(f'{d:g}' for d in r['delays']):>14} "
                f"{_fmt(r['J'], '.3e'):>10} {_fmt(r['E'], '.4e'):>11} {_fmt(r['fit'], '.2f'):>8} "
                f"{_fmt(r['aic'], '.1f'):>10} {_fmt(r['bic'], '.1f'):>10}  {r['status']}"
            )
        return "\n".join(lines)

    def to_dict(self, top: int | None = None) -> dict:
        rows = [self.row(i) for i in range(len(self) if top is None else min(top, len(self)))]
        return {"score": self.score, "candidates": len(self), "compile_s": self.compile_s,
                "run_s": self.run_s, "ranked": rows}

    def to_json(self, path=None, top: int | None = None) -> str:
        text = json.dumps(self.to_dict(top))
        if path is not None:
            with open(path, "w") as fh:
                fh.write(text)
        return text

    def to_pandas(self):
        """All candidates, ranked, as a pandas DataFrame (pandas is optional)."""
        import pandas as pd

        return pd.DataFrame([self.row(i) for i in range(len(self))])


def _compact_theta(theta_pad, n, m, res: SearchResult):
    parts = [theta_pad[: n + 1]]
    pos = res.n_max + 1
    for k, mk in enumerate(res.m_max):
        parts.append(theta_pad[pos : pos + m[k] + 1])
        pos += mk + 1
    if res.has_offset:
        parts.append(theta_pad[pos : pos + 1])
    return np.concatenate(parts)


def _num(x):
    v = float(x)
    return int(v) if v == int(v) else v


def _finite(x):
    v = float(x)
    return v if math.isfinite(v) else None


def _fmt(v, spec):
    return "-" if v is None else format(v, spec)


# -- the batched computation ------------------------------------------------------------------


class _Static(eqx.Module):
    """Everything that fixes shapes and control flow of the compiled chunk."""

    n_max: int = eqx.field(static=True)
    m_max: tuple[int, ...] = eqx.field(static=True)
    ft_inputs: tuple[int, ...] = eqx.field(static=True)  # inputs that may have m_k = n
    length: int = eqx.field(static=True)  # kernel length
    degree: int = eqx.field(static=True)  # Legendre degree = max N + M
    sources: tuple = eqx.field(static=True)  # (kind, k, rule) of every moment source
    col_deriv: tuple[int, ...] = eqx.field(static=True)  # derivative order of every column
    col_source: tuple[int, ...] = eqx.field(static=True)  # source of each of the first p columns
    classes: tuple = eqx.field(static=True)  # `_Class` of every model order
    devices: int = eqx.field(static=True)  # devices the (h, delays) axis is sharded over
    v_start: int = eqx.field(static=True)
    v_length: int = eqx.field(static=True)
    ob_length: int = eqx.field(static=True)
    simulate: bool = eqx.field(static=True)
    batch: int = eqx.field(static=True)  # candidates per vmapped validation batch


def _fft_size(n: int) -> int:
    """Smallest 2^a 3^b 5^c >= n (sizes the FFT library handles fastest)."""
    best = 1 << (n - 1).bit_length()
    p5 = 1
    while p5 < best:
        p35 = p5
        while p35 < best:
            p235 = p35 * (1 << max(0, (-(-n // p35) - 1).bit_length()))
            best = min(best, p235)
            p35 *= 3
        p5 *= 5
    return best


def _fft_modulate(x, W):
    """Sliding convolutions of every x[s] (S, T) with every row of W[s] (S, Q, L), by real FFT:
    (T, S * Q).

    The FFT is circular of size >= max(T, L): row t is exact wherever the kernel's support
    reaches no further back than sample 0, which holds for every sample the Gram weighs
    (`gregory_weights` is 0 before the support)."""
    T, L = x.shape[1], W.shape[2]
    nfft = _fft_size(max(T, L))
    X = jnp.fft.rfft(x, nfft, axis=1)
    conv = jnp.fft.irfft(X[:, None, :] * jnp.fft.rfft(W, nfft, axis=2), nfft, axis=2)[:, :, :T]
    return conv.reshape(-1, T).T


def _moment_gram(sig: Signals, static: _Static, h, delays):
    r"""Sliding Legendre moments of every source and their Gram $H$ (one per (h, delays)).

    Every column of $c(t)$ for every (N, M) is $\sum_q c_q\,\text{moment}_q$ of one source,
    so $G_{N,M} = C_{N,M} H C_{N,M}^T$ (module docstring)."""
    dt, T = sig.dt, sig.n_samples
    signals, weights = [], []
    for kind, k, rule in static.sources:
        if kind == "y":
            x, tau = sig.y, jnp.asarray(0.0)
        elif kind == "u":
            x, tau = sig.u[:, k], delays[k]
        elif kind == "v":  # what D_k u_k(t - tau_k) puts into the output samples (m_k = n)
            x, tau = delayed_samples(sig.u[:, k], delays[k], dt, sig.intersample[k]), 0.0
        else:
            x, tau = jnp.ones(T), jnp.asarray(0.0)
        weights.append(legendre_weights(static.degree, h, dt, rule, tau, static.length))
        signals.append(x)
    x, W = jnp.stack(signals), jnp.stack(weights)
    Mom = _fft_modulate(x, W)  # (T, sources * Q)
    span = h + (jnp.max(delays) if delays.shape[0] else 0.0)
    q = gregory_weights(T, support_samples(span, dt), dt)
    Mq = jnp.sqrt(q)[:, None] * Mom  # q >= 0 (Gregory weights)
    H = Mq.T @ Mq
    scales = jnp.max(jnp.abs(x), axis=1)
    return H, W, scales * jnp.sqrt(jnp.sum(q))


class _Class(NamedTuple):
    """The candidates of one model order n: every (N, M) with N, M >= n x every structure of
    order n, solved in a compact layout (only the columns order n can use: a_0..a_n, b_k up to
    the class's largest m_k, offset) that `sel` picks from the padded one."""

    n: int
    sel: tuple[int, ...]  # compact column -> padded column
    sel_ext: tuple[int, ...]  # the same for the extended Gram (feed-through columns appended)
    m: tuple[int, ...]  # largest m_k of the class
    nm: tuple[int, ...]  # its (N, M) pairs (indices)
    structs: tuple[int, ...]  # its structures (indices)


def _chunk(sig: Signals, static: _Static, eta_full, groups, structs, nm):
    """All candidates of a chunk of (h, delays) groups: for every group, the classes' (N, M)
    x structure products, flattened in class order: outputs (G, C_group, ...)."""
    K = sig.n_inputs
    n_max, m_max = static.n_max, static.m_max
    p = n_max + 1 + sum(mk + 1 for mk in m_max) + int(sig.offset)
    n_src, Q = len(static.sources), static.degree + 1
    finite = jnp.isfinite(sig.y).all() & jnp.isfinite(sig.u).all()
    spread = jnp.max(sig.u, axis=0, initial=-jnp.inf) - jnp.min(sig.u, axis=0, initial=jnp.inf)
    excited = jnp.all(spread > 1e-12 * jnp.maximum(
        jnp.max(jnp.abs(sig.u), axis=0, initial=0.0), 1e-300))
    hpow_i = jnp.asarray(static.col_deriv, dtype=jnp.float64)
    src_of = np.asarray(static.col_source)
    pad = np.cumsum([n_max + 1] + [mk + 1 for mk in m_max])  # b blocks in the padded layout

    def one_nm(H, W, scale, h, coef):
        Cf = coef * (h ** (-hpow_i))[:, None, None]  # (p_ext, sources, Q)
        Cflat = Cf.reshape(Cf.shape[0], n_src * Q)
        Gx = Cflat @ H @ Cflat.T
        w = Cflat[:p] @ W.reshape(n_src * Q, -1)  # column kernels
        bounds = jnp.sum(jnp.abs(w), axis=1) * scale[src_of]
        alive = jnp.sqrt(jnp.maximum(jnp.diagonal(Gx)[:p], 0.0)) > DEAD_COLUMN_RTOL * bounds
        return Gx, alive

    def solve(Gx, alive, h, N, M, st, cls: _Class):
        """One candidate of class `cls` in its compact layout; results in the padded one."""
        n, sel = cls.n, np.asarray(cls.sel)
        pc = len(sel)
        off = np.cumsum([n + 1] + [mk + 1 for mk in cls.m])  # start of each b block
        mask, ft = st["mask"], st["ft"]
        active = mask & alive
        eta = jnp.where(mask, eta_full[sel], 0.0)
        G0 = Gx[:pc, :pc]
        G = G0
        if static.ft_inputs:
            theta, _, _ = constrained_solve(G0, eta, active, conditioning=False)
            for _ in range(FEEDTHROUGH_STEPS):
                an = jnp.where(theta[n] != 0, theta[n], 1.0)
                P = jnp.eye(Gx.shape[0], pc)
                for qi, k in enumerate(static.ft_inputs):
                    Dk = jnp.where(ft[k], theta[off[k] + n] / an, 0.0)
                    rows = pc + qi * (n + 1) + np.arange(n + 1)
                    P = P.at[rows, np.arange(n + 1)].set(-Dk)
                G = P.T @ Gx @ P
                theta, _, _ = constrained_solve(G, eta, active, conditioning=False)
        theta, cond, reduced = constrained_solve(G, eta, active)
        status = solve_status(theta, reduced, finite)
        dead = jnp.any(mask & ~alive)
        status = status | jnp.where(excited & ~dead, 0, Status.NO_EXCITATION)
        an = theta[n]
        an_ok = jnp.abs(an) > 1e-12 * jnp.max(jnp.abs(theta[: n + 1]))
        status = status | jnp.where(an_ok, 0, Status.A_N_ZERO)
        quad = jnp.maximum(theta @ G @ theta, 0.0)
        terms = jnp.sum(theta**2 * jnp.diagonal(G))
        theta = jnp.zeros(p).at[sel].set(theta)  # padded layout from here on
        norm = theta / jnp.where(an_ok, an, 1.0)
        b = [jnp.zeros(n_max + 1).at[: m_max[k] + 1].set(norm[pad[k] : pad[k] + m_max[k] + 1])
             for k in range(K)]
        return dict(
            theta=theta, a=norm[: n_max + 1], b=jnp.stack(b, 0) if K else jnp.zeros((0, n_max + 1)),
            offset=norm[p - 1] if sig.offset else jnp.asarray(0.0),
            J=jnp.sqrt(quad / jnp.where(terms > 0, terms, 1.0)),
            J_raw=h ** (N + M + 1) * jnp.sqrt(quad), cond=cond, status=status,
        )

    def grams(hd):  # one (h, delays) setting: the Gram of every (N, M)
        h, delays = hd
        H, W, scale = _moment_gram(sig, static, h, delays)
        return jax.vmap(lambda coef: one_nm(H, W, scale, h, coef))(nm["coef"])

    def solve_group(h, Gx, alive):
        outs = []
        for cls, st in zip(static.classes, structs):
            r, ext = np.asarray(cls.nm), np.asarray(cls.sel_ext)
            Gc, ac = Gx[r][:, ext[:, None], ext[None, :]], alive[r][:, np.asarray(cls.sel)]

            def per_nm(G, a, N, M, cls=cls, st=st):
                return jax.vmap(lambda s: solve(G, a, h, N, M, s, cls))(st)

            o = jax.vmap(per_nm)(Gc, ac, nm["N"][r], nm["M"][r])  # (NM_c, S_c, ...)
            outs.append(jax.tree_util.tree_map(lambda x: x.reshape((-1,) + x.shape[2:]), o))
        return {key: jnp.concatenate([o[key] for o in outs]) for key in outs[0]}

    # the signal-sized work one setting at a time (cache-sized; vmapped over the devices'
    # blocks of the sharded axis), the small solves batched over all of them
    per_dev = (static.devices, -1)
    Gx, alive = jax.vmap(lambda hd: jax.lax.map(grams, hd))(
        (groups["h"].reshape(per_dev), groups["delays"].reshape(per_dev + (K,))))
    Gx, alive = Gx.reshape((-1,) + Gx.shape[2:]), alive.reshape((-1,) + alive.shape[2:])
    out = jax.vmap(solve_group)(groups["h"], Gx, alive)  # (G, C_group, ...)
    shape = out["status"].shape
    if not static.simulate:  # equation error only (score J)
        nan = jnp.full(shape, jnp.nan)
        return dict(out, E=nan, fit=nan, aic=nan, bic=nan, status=out["status"].astype(jnp.int32))
    per_col = {key: jnp.concatenate([jnp.tile(st[key], len(cls.nm))
                                     for cls, st in zip(static.classes, structs)])
               for key in ("n", "k")}
    flat = {
        "a": out["a"].reshape(-1, n_max + 1),
        "b": out["b"].reshape(-1, K, n_max + 1),
        "offset": out["offset"].reshape(-1),
        "n": jnp.broadcast_to(per_col["n"], shape).reshape(-1),
        "k": jnp.broadcast_to(per_col["k"], shape).reshape(-1),
        "delays": jnp.broadcast_to(groups["delays"][:, None, :], shape + (K,)).reshape(-1, K),
    }
    val = jax.lax.map(lambda c: _validate(sig, static, c), flat, batch_size=static.batch)
    val = {key: v.reshape(shape) for key, v in val.items()}
    status = (out["status"] | val.pop("status")).astype(jnp.int32)
    return dict(out, status=status, **val)


def padded_forced(sig: Signals, c):
    """Zero-padded realisation (eq. 18) of candidate `c` (keys a, b, offset, n, delays) and its
    exact forced response to `sig`'s inputs: ((ss, drive, direct), live-state mask)."""
    K, n_max = sig.n_inputs, c["a"].shape[0] - 1
    bs, modes, dl, u_cols = [c["b"][k] for k in range(K)], list(sig.intersample), [
        c["delays"][k] for k in range(K)], [sig.u[:, k] for k in range(K)]
    if sig.offset:
        bs.append(jnp.zeros(n_max + 1).at[0].set(c["offset"]))
        modes.append("zoh")
        dl.append(jnp.asarray(0.0))
        u_cols.append(jnp.ones(sig.n_samples))
    ss, live = realisation(c["a"], bs, c["n"])
    drive, direct = forced_terms(ss, u_cols, modes, dl, sig.dt, sig.n_samples)
    return (ss, drive, direct), live


def _validate(sig: Signals, static: _Static, c):
    """E (eq. 17), fit and information criteria of one candidate on the validation window, the
    simulation started from the initial-state observer (eq. 14) of a zero-padded realisation."""
    forced, live = padded_forced(sig, c)
    obs = _observe_forced(forced, sig.y, sig.dt, static.v_start, static.v_length,
                          static.ob_length, live)
    status = obs.status | jnp.where(hurwitz(c["a"]), 0, Status.UNSTABLE)
    yv = jax.lax.dynamic_slice_in_dim(sig.y, static.v_start, static.v_length)
    Nv = static.v_length
    loglik = Nv * jnp.log(jnp.maximum(obs.E / (Nv * sig.dt), 1e-300))
    return dict(E=obs.E, fit=fit_percent(yv, obs.y_sim), aic=loglik + 2 * c["k"],
                bic=loglik + c["k"] * jnp.log(Nv), status=status)


_chunk_jit = eqx.filter_jit(_chunk)


def _place(x: np.ndarray, sharding):
    """A global array split over the mesh (works with one or several processes)."""
    return jax.make_array_from_callback(x.shape, sharding, lambda idx: x[idx])


def _mesh():
    devices = jax.devices()
    return jax.make_mesh((len(devices),), ("c",), axis_types=(jax.sharding.AxisType.Auto,))


def search(
    signals: Signals,
    *,
    n: Sequence[int] | int = (1, 2, 3),
    N: Sequence[float] | float = (3, 4, 5),
    M: Sequence[float] | float = (3, 4, 5),
    h: Sequence[float] | float,
    m: Sequence[Sequence[int]] | None = None,
    delays: Sequence[Sequence[float]] | None = None,
    score: str = "E",
    validate: tuple[float, float] | None = None,
    observer_window: float | None = None,
    eta=None,
    chunk_size: int = 8,
    simulate: bool = True,
    progress: Callable[[int, int], None] | None = None,
) -> SearchResult:
    r"""Identify and score every feasible candidate of a grid, batched (see module docstring).

    **Arguments:**

    - `signals`: the experiment. Its own `delays` are ignored when `delays` is given.
    - `n`: output orders; `m`: per input, the allowed numerator orders (default: 0..n-1 for
      each n; values above n are skipped); `N`, `M`, `h`: modulating function settings;
      `delays`: per input, the delays to try. Candidates with N < n or M < n are skipped.
    - `score`: ranking key, one of `"E"` (eq. 17 on the validation window), `"J"` (scale-free
      equation error J_rel), `"fit"` (NRMSE %), `"aic"`, `"bic"` ($N_v \ln(E/T_v) + 2k$ and
      $+ k \ln N_v$, k = number of free parameters). Flagged candidates rank after the others;
      ties (for E: differences below 1e-12 of $\int y^2$; for J: below $\sqrt{p\,\epsilon}$,
      the rounding noise of $\theta^T G \theta$; both matter on noise-free data) go to the
      candidate with fewer parameters.
    - `validate`: (t0, t1) window for E and fit (default: the whole record); the state at its
      start comes from the initial-state observer over `observer_window` (default: the window).
    - `simulate`: False skips the observer + simulation (E, fit, AIC, BIC are NaN; only the
      `"J"` score is available): the pure equation-error search.
    - `chunk_size`: (h, delays) settings per compiled chunk (at most the grid's; rounded up to
      a multiple of the device count), each with every (N, M) and structure: memory grows with
      it, not with the grid; `progress(done, total)` is
      called after each chunk with counts of (h, delays) settings.

    **Returns:** a `SearchResult`.
    """
    plan = _plan(signals, n=n, N=N, M=M, h=h, m=m, delays=delays, score=score,
                 validate=validate, observer_window=observer_window, eta=eta,
                 chunk_size=chunk_size, simulate=simulate)
    return _run(plan, signals, progress)


class _Plan(NamedTuple):
    """A checked grid, compiled once: everything but the data (`search` = `_run(_plan(..))`)."""

    static: _Static
    eta: jax.Array
    structs: list
    struct_arr: dict
    nm: dict
    hd: list
    combos: list
    columns: tuple[np.ndarray, np.ndarray]  # (N, M) pair and structure of each group column
    chunk: int
    sharding: jax.sharding.NamedSharding
    score: str
    n_samples: int
    n_inputs: int


def _plan(signals: Signals, *, n, N, M, h, m, delays, score, validate, observer_window, eta,
          chunk_size, simulate, span_bound: float = 0.0) -> _Plan:
    """Check the grid against the record's shape and build the static parts of `search`.

    `span_bound` (time units) pads the kernels to at least this h + delay, so that plans with
    different delays share one compilation (the on-line identifier)."""
    if not isinstance(signals, Signals):
        raise TypeError("search(): signals must be a Signals")
    if score not in SCORES:
        raise ValueError(f"search(): unknown score {score!r}; use one of {SCORES}")
    if not (isinstance(chunk_size, (int, np.integer)) and chunk_size >= 1):
        raise ValueError(f"search(): chunk_size must be an integer >= 1 (got {chunk_size!r})")
    if not simulate and score != "J":
        raise ValueError(f"search(): score {score!r} needs simulate=True (or use score='J')")
    K = signals.n_inputs
    n_grid = _values(n, "n")
    N_grid = [float(v) for v in _values(N, "N")]
    M_grid = [float(v) for v in _values(M, "M")]
    h_grid = [float(v) for v in _values(h, "h")]
    if m is not None:
        m = [_values(mk, f"m[{k}]") for k, mk in enumerate(m)]
        if len(m) != K:
            raise ValueError(f"search(): m needs one list of orders per input ({K}), got {len(m)}")
    if delays is not None:
        delays = [[float(d) for d in _values(dk, f"delays[{k}]")] for k, dk in enumerate(delays)]
        if len(delays) != K:
            raise ValueError(f"search(): delays needs one list per input ({K}), got {len(delays)}")
    else:
        delays = [[float(v)] for v in np.asarray(signals.delays)]
    for name, vals in (("N", N_grid), ("M", M_grid), ("h", h_grid)):
        if any(not math.isfinite(v) or v <= 0 for v in vals):
            raise ValueError(f"search(): {name} values must be finite and > 0 (got {vals})")
    if any(d < 0 or d >= signals.duration for dk in delays for d in dk):
        raise ValueError("search(): delays must be >= 0 and shorter than the record")
    structs = _structures(n_grid, m, K)
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
    if max(N_grid) + max(M_grid) > 20:
        raise ValueError("search(): N + M must be <= 20")
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
    first = int(support_samples(h_max + delay_max, dt))
    p_needed = n_max + 1 + sum(mk + 1 for mk in m_max) + int(signals.offset)
    if signals.n_samples - first < max(8, 2 * p_needed):
        raise ValueError(
            f"search(): h={h_max:g} (+ delays {delay_max:g}) leaves too few valid samples in "
            f"the record ({signals.duration:g} time units); use smaller h"
        )
    v0, v_len, ob = validation_window(signals, validate, observer_window, n_max, "search")
    p = p_needed
    eta = jnp.ones(p) if eta is None else jnp.asarray(eta, dtype=jnp.float64)
    if eta.shape != (p,):
        raise ValueError(f"search(): eta must have {p} entries (padded layout)")
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
    nm = {"N": jnp.asarray([a for a, _ in nm_pairs]), "M": jnp.asarray([b for _, b in nm_pairs]),
          "coef": jnp.asarray(coef)}
    classes, struct_arr = [], []
    pad_off = np.cumsum([n_max + 1] + [mk + 1 for mk in m_max])
    for n_c in sorted({st[0] for st in structs}):
        members = [j for j, st in enumerate(structs) if st[0] == n_c]
        pairs = [r for r, (a, b) in enumerate(nm_pairs) if min(a, b) >= n_c]
        if not pairs:
            continue
        m_c = tuple(max(structs[j][1][k] for j in members) for k in range(K))
        sel = list(range(n_c + 1))
        for k in range(K):
            sel += [int(pad_off[k]) + i for i in range(m_c[k] + 1)]
        sel += [p - 1] if signals.offset else []
        sel_ext = sel + [p + q * (n_max + 1) + i for q in range(len(ft_inputs)) for i in range(n_c + 1)]
        classes.append(_Class(n_c, tuple(sel), tuple(sel_ext), m_c, tuple(pairs), tuple(members)))
        struct_arr.append({
            "n": jnp.full(len(members), n_c, dtype=jnp.int32),
            "mask": jnp.asarray([_mask(structs[j], n_c, m_c, signals.offset) for j in members]),
            "ft": jnp.asarray([[structs[j][1][k] == n_c for k in range(K)]
                               for j in members]).reshape(len(members), K),
            "k": jnp.asarray([n_c + sum(mk + 1 for mk in structs[j][1]) + int(signals.offset)
                              for j in members], dtype=jnp.float64),
        })
    static = _Static(
        n_max, m_max, ft_inputs, kernel_length(max(h_max + delay_max, span_bound), dt), degree,
        tuple(sources), tuple(c[2] for c in cols), tuple(c[0] for c in cols[:p]), tuple(classes),
        len(jax.devices()), v0, v_len, ob, bool(simulate), 64,
    )
    mesh = _mesh()
    n_dev = mesh.devices.size
    chunk = n_dev * math.ceil(min(chunk_size, len(hd)) / n_dev)  # no padding beyond the grid
    sharding = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("c"))
    col_nm = np.concatenate([np.repeat(c.nm, len(c.structs)) for c in classes])
    col_struct = np.concatenate([np.tile(c.structs, len(c.nm)) for c in classes])
    return _Plan(static, eta, structs, tuple(struct_arr), nm, hd, combos, (col_nm, col_struct),
                 chunk, sharding, score, signals.n_samples, K)


def _run(plan: _Plan, signals: Signals, progress=None) -> SearchResult:
    """Evaluate a plan's grid on `signals` (same length and layout as the plan's record)."""
    static, hd, chunk, K = plan.static, plan.hd, plan.chunk, plan.n_inputs
    if (signals.n_samples, signals.n_inputs) != (plan.n_samples, K):
        raise ValueError("search: the signals do not match the plan's record length and inputs")
    col_nm, col_struct = plan.columns
    Cg = len(col_nm)  # candidates per (h, delays) setting
    cols, times = {}, []
    for c0 in range(0, len(hd), chunk):
        idx = list(range(c0, min(c0 + chunk, len(hd))))
        real = len(idx)
        idx = idx + [idx[-1]] * (chunk - real)  # pad the last chunk: same shapes
        g = {
            "h": np.asarray([hd[i][0] for i in idx]),
            "delays": np.asarray([hd[i][1] for i in idx], dtype=np.float64).reshape(chunk, K),
        }
        g = {k: _place(v, plan.sharding) for k, v in g.items()}
        t0 = time.perf_counter()
        res = jax.block_until_ready(
            _chunk_jit(signals, static, plan.eta, g, plan.struct_arr, plan.nm))
        if jax.process_count() > 1:  # multi-host: every process gets every candidate
            from jax.experimental import multihost_utils

            res = multihost_utils.process_allgather(res, tiled=True)
        for key, val in res.items():  # straight into the preallocated columns: memory flat
            val = np.asarray(val)[:real]
            if key not in cols:
                cols[key] = np.empty((len(hd) * Cg,) + val.shape[2:], val.dtype)
            cols[key][c0 * Cg : (c0 + real) * Cg] = val.reshape((-1,) + val.shape[2:])
        del res
        times.append(time.perf_counter() - t0)
        if progress is not None:
            progress(min(c0 + chunk, len(hd)), len(hd))
    # the first chunk compiles: its excess over a typical chunk is the compile time
    typical = float(np.median(times[1:])) if len(times) > 1 else 0.0
    t_compile, t_run = max(times[0] - typical, 0.0), sum(times) - max(times[0] - typical, 0.0)
    n_set = len(hd)
    cols["group"] = np.repeat(np.arange(n_set), Cg) * len(plan.nm["N"]) + np.tile(col_nm, n_set)
    cols["struct"] = np.tile(col_struct, n_set)
    return _collect(cols, plan.combos, plan.structs, signals, static, plan.score, t_compile, t_run)


@functools.lru_cache(maxsize=128)
def _coefficients(pair_N: tuple, pair_M: tuple, i: int, degree: int) -> np.ndarray:
    """`legendre_coefficients` of every (N, M) pair, memoised: constants of a grid."""
    out = legendre_coefficients(pair_N, pair_M, i, degree)
    out.setflags(write=False)
    return out


def _mask(s, n_max, m_max, offset):
    n, m = s
    mask = [i <= n for i in range(n_max + 1)]
    for k, mk in enumerate(m_max):
        mask += [j <= m[k] for j in range(mk + 1)]
    return mask + ([True] if offset else [])


def _collect(cols, combos, structs, signals, static, score, t_compile, t_run):
    g, st = cols.pop("group"), cols.pop("struct")
    grid = np.asarray([(c[0], c[1], c[2]) for c in combos])
    cols["n"] = np.asarray([s[0] for s in structs])[st]
    cols["m"] = np.asarray([s[1] for s in structs]).reshape(len(structs), -1)[st]
    cols["N"], cols["M"], cols["h"] = grid[g, 0], grid[g, 1], grid[g, 2]
    cols["delays"] = np.asarray([c[3] for c in combos]).reshape(len(combos), -1)[g]
    key = {"E": cols["E"], "J": cols["J"], "fit": -cols["fit"], "aic": cols["aic"],
           "bic": cols["bic"]}[score]
    key = np.where(np.isfinite(key), key, np.inf)
    if score == "E":  # E below rounding noise (1e-12 of the output energy) is a tie: fewer
        yv = np.asarray(signals.y)[static.v_start : static.v_start + static.v_length]
        q = E_TIE_RTOL * float(np.sum(yv**2)) * signals.dt + 1e-300
        key = np.where(np.isfinite(key), np.floor(key / q), np.inf)
    if score == "J":  # J^2 below p eps is the float64 noise of theta' G theta: a tie
        q = math.sqrt(cols["theta"].shape[1] * np.finfo(np.float64).eps)
        key = np.where(np.isfinite(key), np.floor(key / q), np.inf)
    n_par = np.asarray([s[0] + sum(mk + 1 for mk in s[1]) for s in structs])[st]
    bad = cols["status"] != 0
    rank = np.lexsort((n_par, key, bad))  # status, then score, then fewer parameters
    return SearchResult(
        columns=cols, rank=rank, score=score, n_max=static.n_max, m_max=static.m_max,
        intersample=signals.intersample, has_offset=signals.offset,
        output_name=signals.output_name, input_names=signals.input_names,
        compile_s=t_compile, run_s=t_run,
    )
