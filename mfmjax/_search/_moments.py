"""Sliding Legendre moments of the signals and their Gram (one per (h, delays) setting)."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .._gram import first_position
from .._quadrature import (
    delayed_samples,
    fft_size,
    gregory_weights,
    legendre_weights,
)
from .._signals import Signals
from ._grid import ChunkStatic


def _fft_modulate(x, W):
    """Sliding convolutions of every x[s] (S, T) with every row of W[s] (S, Q, L), by real FFT:
    (T, S * Q).

    The FFT is circular of size >= max(T, L): row t is exact wherever the kernel's support
    reaches no further back than sample 0, which holds for every sample the Gram weighs
    (`gregory_weights` is 0 before the support)."""
    T, L = x.shape[1], W.shape[2]
    nfft = fft_size(max(T, L))
    X = jnp.fft.rfft(x, nfft, axis=1)
    conv = jnp.fft.irfft(X[:, None, :] * jnp.fft.rfft(W, nfft, axis=2), nfft, axis=2)[:, :, :T]
    return conv.reshape(-1, T).T


def moment_gram(sig: Signals, static: ChunkStatic, h, delays, segments, levels=None):
    r"""Sliding Legendre moments of every source and their Gram $H$ (one per (h, delays)).

    Every column of $c(t)$ for every (N, M) is $\sum_q c_q\,\text{moment}_q$ of one source,
    so $G_{N,M} = C_{N,M} H C_{N,M}^T$ (module docstring). `levels` (`signal_levels`): the
    moments of the centred output and inputs (the bounds still of the signals themselves)."""
    dt, T = sig.dt, sig.n_samples
    signals, weights, shifts = [], [], []
    for kind, k, rule in static.sources:
        if kind == "y":
            x, tau, c = sig.y, jnp.asarray(0.0), 0
        elif kind == "u":
            x, tau, c = sig.u[:, k], delays[k], k + 1
        elif kind == "v":  # what D_k u_k(t - tau_k) puts into the output samples (m_k = n)
            x, tau, c = (delayed_samples(sig.u[:, k], delays[k], dt, sig.intersample[k]), 0.0,
                         k + 1)
        else:
            x, tau, c = jnp.ones(T), jnp.asarray(0.0), None
        weights.append(legendre_weights(static.degree, h, dt, rule, tau, static.length))
        signals.append(x)
        shifts.append(0.0 if levels is None or c is None else levels[c])
    x, W = jnp.stack(signals), jnp.stack(weights)
    Mom = _fft_modulate(x - jnp.stack(shifts)[:, None], W)  # (T, sources * Q)
    # the Gram integral sums the valid samples of each identification window [start, end)
    first = first_position(h, delays, dt)
    q = jnp.sum(jax.vmap(lambda ab: gregory_weights(T, ab[0] + first, dt, end=ab[1]))(segments),
                axis=0)
    Mq = jnp.sqrt(q)[:, None] * Mom  # q >= 0 (Gregory weights)
    H = Mq.T @ Mq
    scales = jnp.max(jnp.abs(x), axis=1)
    return H, W, scales * jnp.sqrt(jnp.sum(q))
