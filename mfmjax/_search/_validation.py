"""E (eq. 17), fit and information criteria of one candidate through a zero-padded realisation."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .._linalg import hurwitz
from .._observers import fit_percent
from .._padded import observe_padded
from .._signals import Signals
from .._status import Status
from ._grid import ChunkStatic


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
