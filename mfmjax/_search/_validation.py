"""E (eq. 17), fit and information criteria of one candidate through a zero-padded realisation."""

from __future__ import annotations

import jax.numpy as jnp

from .._linalg import hurwitz
from .._observers import masked_fit_percent
from .._padded import observe_padded
from .._quadrature import shift_samples
from .._signals import Signals
from .._status import Status


def validate_candidate(sig: Signals, v_length: int, c, where):
    """E (eq. 17), fit and information criteria of one candidate on the validation window
    (`where`: its start "v_start", its length "v_valid" <= `v_length` (the window's buffer) and
    the observer's "ob", all values), the simulation started from the initial-state observer
    (eq. 14) of a zero-padded realisation."""
    start, valid = where["v_start"], where["v_valid"]
    yv = shift_samples(sig.y, 0, start + jnp.arange(v_length))  # may run past the end
    obs = observe_padded(sig, c, start, v_length, where["ob"], valid)
    status = obs.status | jnp.where(hurwitz(c["a"]), 0, Status.UNSTABLE)
    Nv = valid.astype(jnp.float64)
    loglik = Nv * jnp.log(jnp.maximum(obs.E / (Nv * sig.dt), 1e-300))
    return dict(E=obs.E, fit=masked_fit_percent(yv, obs.y_sim, valid), aic=loglik + 2 * c["k"],
                bic=loglik + c["k"] * jnp.log(Nv), status=status)
