r"""A model zero-padded to static orders (eq. 1): the orders n and $m_k$ as values.

A padded model is a dict: `a` (n_max+1,) with $a_n$ at index n and zeros beyond, `b` (K, w)
with $b_{kj}$ at column j ($j \le m_k$, w - 1 >= every $m_k$), `offset`, `delays` (K,), `n` and
`m` (K,) as int32 values. Every structure of one padded shape is one pytree structure, hence
one compiled program (SRIVC, output error, the hold-out observer).

Its free parameters as one vector, the padded $\theta$, are
[a_0..a_{n_max-1}; b_10..b_1(w-1); ..; b_K0..b_K(w-1); offset], those outside `free` zero.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from . import _boundary as _b
from ._jit import jit
from ._model import Model
from ._observers import observe_forced
from ._quadrature import shift_samples
from ._signals import Signals
from ._simulate import forced_terms
from ._statespace import realisation


def padded_model(model: Model, n_max: int, m_max: int | None = None) -> dict:
    """`model` (order n <= `n_max`, m_k <= `m_max`, default `n_max`) zero-padded: NumPy for a
    concrete model, JAX for a traced one (a user's `jax.vmap`)."""
    K, w = model.n_inputs, (n_max if m_max is None else m_max) + 1
    traced = any(_b.is_traced(x) for x in (model.a, *model.b, model.offset, model.delays))
    xp = jnp if traced else np
    pad = lambda x, to: xp.concatenate([xp.asarray(x, dtype=np.float64),  # noqa: E731
                                        xp.zeros(to - x.shape[0])])
    b = xp.stack([pad(bk, w) for bk in model.b]) if K else xp.zeros((0, w))
    return {"a": pad(model.a, n_max + 1), "b": b,
            "offset": xp.asarray(model.offset, dtype=np.float64),
            "delays": xp.reshape(xp.asarray(model.delays, dtype=np.float64), (K,)),
            "n": np.int32(model.n), "m": np.asarray(model.m, dtype=np.int32).reshape(K)}


def free(c, has_offset: bool):
    """Mask of the padded theta's free entries: a_i (i < n), b_kj (j <= m_k), the offset
    (NumPy for a concrete `c` from `padded_model`, JAX inside a program)."""
    xp = jnp if _b.is_traced(c["n"]) or _b.is_traced(c["m"]) else np
    n_max, w = c["a"].shape[0] - 1, c["b"].shape[1]
    return xp.concatenate([xp.arange(n_max) < c["n"],
                           (xp.arange(w)[None, :] <= c["m"][:, None]).reshape(-1)]
                          + ([xp.ones(1, bool)] if has_offset else []))


def theta(c, has_offset: bool):
    """The padded theta of `c`, normalised to a_n = 1 (zero outside `free`)."""
    an = c["a"][c["n"]]
    out = jnp.concatenate([c["a"][:-1] / an, (c["b"] / an).reshape(-1)]
                          + ([jnp.reshape(c["offset"] / an, (1,))] if has_offset else []))
    return jnp.where(free(c, has_offset), out, 0.0)


def split(theta, c, has_offset: bool):
    """Padded theta -> (a (n_max+1,) with a_n = 1, b (K, w), offset) in `c`'s shapes."""
    n_max, (K, w) = c["a"].shape[0] - 1, c["b"].shape
    a = jnp.concatenate([theta[:n_max], jnp.zeros(1)]).at[c["n"]].set(1.0)
    b = theta[n_max : n_max + K * w].reshape(K, w)
    return a, b, (theta[-1] if has_offset else jnp.zeros(()))


def with_theta(c, theta, has_offset: bool) -> dict:
    """`c` with its coefficients from the padded theta."""
    a, b, offset = split(theta, c, has_offset)
    return dict(c, a=a, b=b, offset=offset)


def indices(model: Model, n_max: int, w: int) -> np.ndarray:
    """Positions in the padded theta of `model`'s free parameters, in the order of
    `free_parameters` (a_0..a_{n-1}, b_kj, offset)."""
    idx = list(range(model.n)) + [n_max + k * w + j for k, mk in enumerate(model.m)
                                  for j in range(mk + 1)]
    if model.has_offset:
        idx.append(n_max + model.n_inputs * w)
    return np.asarray(idx)


def realised(c, has_offset: bool):
    """(a, numerators zero-padded to n_max + 1 with the offset's as one more, n) for
    `realisation` (eq. 18)."""
    n_max = c["a"].shape[0] - 1
    K, w = c["b"].shape
    bs = [jnp.zeros(n_max + 1).at[:w].set(c["b"][k]) for k in range(K)]
    if has_offset:
        bs.append(jnp.zeros(n_max + 1).at[0].set(c["offset"]))
    return c["a"], bs, c["n"]


def padded_forced(sig: Signals, c, rows=None):
    """Zero-padded realisation (eq. 18) of the padded model `c` (a search candidate too: keys a,
    b, offset, n, delays) and its exact forced response to `sig`'s inputs (at the samples
    `rows`, default all, exactly as in the whole record): ((ss, drive, direct), live mask)."""
    K = sig.n_inputs
    modes, dl, u_cols = list(sig.intersample), [c["delays"][k] for k in range(K)], [
        sig.u[:, k] for k in range(K)]
    if sig.offset:
        modes.append("zoh")
        dl.append(jnp.asarray(0.0))
        u_cols.append(jnp.ones(sig.n_samples))
    ss, live = realisation(*realised(c, sig.offset))
    Phi, drive, direct = forced_terms(ss, u_cols, modes, dl, sig.dt, sig.n_samples, rows)
    return (ss, Phi, drive, direct), live


def observe_padded(sig: Signals, c, start, length: int, ob_length, valid=None):
    """The observers (eq. 14-15) and E (eq. 17) of a zero-padded candidate on samples
    `start .. start + length - 1` (`start` traced; of them the first `valid`, see
    `observe_forced`): `observe_window` for any order at once, the drive computed for the
    window's samples only (the record can be much longer)."""
    rows = start + jnp.arange(length)  # may run past the record's end (held last sample)
    yw = shift_samples(sig.y, 0, rows)
    forced, live = padded_forced(sig, c, rows)
    return observe_forced(forced, yw, sig.dt, 0, length, ob_length, live, valid)


@jit
def observe_candidate(sig: Signals, c, start, length: int, ob_length: int, valid=None):
    """`observe_padded` compiled: `estimate`'s hold-out observer and output error's start, one
    program for every order."""
    return observe_padded(sig, c, start, length, ob_length, valid)
