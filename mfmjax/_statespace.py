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

from ._boundary import require_x64
from ._model import Model


class StateSpace(eqx.Module):
    """Matrices A (n, n), B (n, K'), C (1, n), D (1, K'); K' = K (+1 with an offset term)."""

    A: jax.Array
    B: jax.Array
    C: jax.Array
    D: jax.Array


def state_space(model: Model) -> StateSpace:
    r"""Eq. (18): the observable canonical realisation of `model`."""
    require_x64("state_space")
    n = model.n
    a = model.a / model.a[n]
    bs = list(model.b) + ([jnp.reshape(model.offset, (1,))] if model.has_offset else [])
    padded = [jnp.zeros(n + 1).at[: bk.shape[0]].set(bk / model.a[n]) for bk in bs]
    return realisation(a, padded, n)[0]


def realisation(a, bs, n):
    r"""Eq. (18) from $a$ ($a_n = 1$) and numerators $b_k$, all zero-padded to length
    $n_{max}+1$, for an order $n \le n_{max}$ that may be traced (batched searches): the states
    beyond $n$ are zero rows/columns. **Returns:** (StateSpace, live-state mask)."""
    n_max = a.shape[0] - 1
    i = jnp.arange(n_max)
    live = i < n
    A = jnp.where((i[:, None] == i[None, :] + 1) & live[:, None], 1.0, 0.0)
    A = jnp.where((i[None, :] == n - 1) & live[:, None], -a[:n_max][:, None], A)
    cols, ds = [], []
    for bk in bs:
        d = bk[n]  # D_k = b_kn when m_k = n (else 0): the strictly proper remainder goes to B
        cols.append(jnp.where(live, bk[:n_max] - d * a[:n_max], 0.0))
        ds.append(d)
    B = jnp.stack(cols, axis=1) if cols else jnp.zeros((n_max, 0))
    D = jnp.stack(ds)[None, :] if ds else jnp.zeros((1, 0))
    C = jnp.where(i == n - 1, 1.0, 0.0)[None, :]
    return StateSpace(A, B, C, D), live


def to_scipy(model: Model):
    """`scipy.signal.StateSpace` of the model (delays are not representable there: ignored)."""
    require_x64("to_scipy")
    import numpy as np
    from scipy import signal

    ss = state_space(model)
    return signal.StateSpace(*(np.asarray(M) for M in (ss.A, ss.B, ss.C, ss.D)))


def to_control(model: Model):
    """python-control `StateSpace` (requires the optional `control` package; delays ignored)."""
    require_x64("to_control")
    try:
        import control
    except ImportError as err:  # pragma: no cover - depends on the environment
        raise ImportError("to_control() needs python-control: pip install control") from err
    import numpy as np

    ss = state_space(model)
    return control.ss(*(np.asarray(M) for M in (ss.A, ss.B, ss.C, ss.D)))
