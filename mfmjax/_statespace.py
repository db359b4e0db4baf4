r"""Observable canonical state space of a model (paper eq. 18), including m_k = n (D != 0).

$A$ has ones on the sub-diagonal and last column $-a_0..-a_{n-1}$ ($a_n = 1$);
column k of $B$ holds $b_{kj} - D_k a_j$, $j = 0..n-1$, with $D_k = b_{kn}$ when $m_k = n$
(else 0); $C = [0 \dots 0\ 1]$. The offset term, when present, is one more input column
(a constant input 1).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from ._model import Model


class StateSpace(eqx.Module):
    """Matrices A (n, n), B (n, K'), C (1, n), D (1, K'); K' = K (+1 with an offset term)."""

    A: jax.Array
    B: jax.Array
    C: jax.Array
    D: jax.Array


def state_space(model: Model) -> StateSpace:
    r"""Eq. (18): the observable canonical realisation of `model`."""
    n = model.n
    a = model.a / model.a[n]
    A = jnp.zeros((n, n)).at[jnp.arange(1, n), jnp.arange(n - 1)].set(1.0)
    A = A.at[:, n - 1].set(-a[:n])
    cols, ds = [], []
    bs = list(model.b) + ([jnp.reshape(model.offset, (1,))] if model.has_offset else [])
    for bk in bs:
        full = jnp.zeros(n + 1).at[: bk.shape[0]].set(bk / model.a[n])
        d = full[n]
        cols.append(full[:n] - d * a[:n])
        ds.append(d)
    B = jnp.stack(cols, axis=1) if cols else jnp.zeros((n, 0))
    D = jnp.stack(ds)[None, :] if ds else jnp.zeros((1, 0))
    C = jnp.zeros((1, n)).at[0, n - 1].set(1.0)
    return StateSpace(A, B, C, D)


def to_scipy(model: Model):
    """`scipy.signal.StateSpace` of the model (delays are not representable there: ignored)."""
    import numpy as np
    from scipy import signal

    ss = state_space(model)
    return signal.StateSpace(*(np.asarray(M) for M in (ss.A, ss.B, ss.C, ss.D)))


def to_control(model: Model):
    """python-control `StateSpace` (requires the optional `control` package; delays ignored)."""
    try:
        import control
    except ImportError as err:  # pragma: no cover - depends on the environment
        raise ImportError("to_control() needs python-control: pip install control") from err
    import numpy as np

    ss = state_space(model)
    return control.ss(*(np.asarray(M) for M in (ss.A, ss.B, ss.C, ss.D)))
