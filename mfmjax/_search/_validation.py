"""E (eq. 17), fit and information criteria of one candidate through a zero-padded realisation."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .._jit import jit
from .._linalg import hurwitz
from .._observers import fit_percent, observe_forced
from .._signals import Signals
from .._simulate import forced_terms
from .._statespace import realisation
from .._status import Status
from ._grid import ChunkStatic


def padded_forced(sig: Signals, c, rows=None):
    """Zero-padded realisation (eq. 18) of candidate `c` (keys a, b, offset, n, delays) and its
    exact forced response to `sig`'s inputs (at the samples `rows`, default all):
    ((ss, drive, direct), live-state mask)."""
    K, n_max = sig.n_inputs, c["a"].shape[0] - 1
    bs, modes, dl, u_cols = [c["b"][k] for k in range(K)], list(sig.intersample), [
        c["delays"][k] for k in range(K)], [sig.u[:, k] for k in range(K)]
    if sig.offset:
        bs.append(jnp.zeros(n_max + 1).at[0].set(c["offset"]))
        modes.append("zoh")
        dl.append(jnp.asarray(0.0))
        u_cols.append(jnp.ones(sig.n_samples))
    ss, live = realisation(c["a"], bs, c["n"])
    drive, direct = forced_terms(ss, u_cols, modes, dl, sig.dt, sig.n_samples, rows)
    return (ss, drive, direct), live


def validate_candidate(sig: Signals, static: ChunkStatic, c, v_start=0):
    """E (eq. 17), fit and information criteria of one candidate on the validation window, the
    simulation started from the initial-state observer (eq. 14) of a zero-padded realisation."""
    yv = jax.lax.dynamic_slice_in_dim(sig.y, v_start, static.v_length)
    obs = observe_padded(sig, c, v_start, static.v_length, static.ob_length)
    status = obs.status | jnp.where(hurwitz(c["a"]), 0, Status.UNSTABLE)
    Nv = static.v_length
    loglik = Nv * jnp.log(jnp.maximum(obs.E / (Nv * sig.dt), 1e-300))
    return dict(E=obs.E, fit=fit_percent(yv, obs.y_sim), aic=loglik + 2 * c["k"],
                bic=loglik + c["k"] * jnp.log(Nv), status=status)


def padded_candidate(model, n_max: int) -> dict:
    """A concrete `Model` of order n <= `n_max` as a zero-padded candidate (`padded_forced`):
    every order shares one pytree structure, hence one compiled observer."""
    K = model.n_inputs
    a, b = np.zeros(n_max + 1), np.zeros((K, n_max + 1))
    a[: model.n + 1] = np.asarray(model.a)
    for k in range(K):
        b[k, : model.m[k] + 1] = np.asarray(model.b[k])
    return {"a": a, "b": b, "offset": np.asarray(model.offset, dtype=np.float64),
            "n": np.asarray(model.n, dtype=np.int32),
            "delays": np.asarray(model.delays, dtype=np.float64).reshape(K)}


def observe_padded(sig: Signals, c, start, length: int, ob_length: int):
    """The observers (eq. 14-15) and E (eq. 17) of a zero-padded candidate on samples
    `start .. start + length - 1` (`start` traced): `observe_window` for any order at once,
    the drive computed for the window's samples only (the record can be much longer)."""
    yw = jax.lax.dynamic_slice_in_dim(sig.y, start, length)
    forced, live = padded_forced(sig, c, start + jnp.arange(length))
    return observe_forced(forced, yw, sig.dt, 0, length, ob_length, live)


@jit
def observe_candidate(sig: Signals, c, start, length: int, ob_length: int):
    """`observe_padded` compiled: `estimate`'s hold-out observer, one program for every order."""
    return observe_padded(sig, c, start, length, ob_length)
