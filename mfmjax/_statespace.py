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
import numpy as np

from . import _boundary as _b
from ._boundary import require_x64
from ._model import Model


class StateSpace(eqx.Module):
    """Matrices A (n, n), B (n, K'), C (1, n), D (1, K'); K' = K (+1 with an offset term)."""

    A: jax.Array
    B: jax.Array
    C: jax.Array
    D: jax.Array


def state_space(model: Model) -> StateSpace:
    r"""Eq. (18): the observable canonical realisation of `model` (a concrete model's on the
    host in NumPy, so an eager call compiles nothing; a traced one's in JAX). The input delays
    are not part of it (`model.delays`; `to_control` can add them as Pade approximants)."""
    require_x64("state_space")
    _model_only("state_space", model)
    traced = any(_b.is_traced(x) for x in jax.tree.leaves((model.a, model.b, model.offset)))
    ss = _realised(model, jnp if traced else np)
    return ss if traced else jax.device_put(ss)


def _realised(model: Model, xp=np) -> StateSpace:
    """Eq. (18) of `model` computed with `xp` (NumPy: a concrete model's, on the host)."""
    n = model.n
    a, b, offset = (model.a, model.b, model.offset) if xp is jnp else \
        jax.device_get((model.a, model.b, model.offset))
    bs = list(b) + ([xp.reshape(offset, (1,))] if model.has_offset else [])
    padded = [xp.concatenate([bk / a[n], xp.zeros(n + 1 - bk.shape[0])]) for bk in bs]
    return realisation(a / a[n], padded, n, xp)[0]


def realisation(a, bs, n, xp=jnp):
    r"""Eq. (18) from $a$ ($a_n = 1$) and numerators $b_k$, all zero-padded to length
    $n_{max}+1$, for an order $n \le n_{max}$ that may be traced (batched searches): the states
    beyond $n$ are zero rows/columns. `xp`: `jax.numpy`, or `numpy` for concrete arrays.
    **Returns:** (StateSpace, live-state mask)."""
    n_max = a.shape[0] - 1
    i = xp.arange(n_max)
    live = i < n
    A = xp.where((i[:, None] == i[None, :] + 1) & live[:, None], 1.0, 0.0)
    A = xp.where((i[None, :] == n - 1) & live[:, None], -a[:n_max][:, None], A)
    cols, ds = [], []
    for bk in bs:
        d = bk[n]  # D_k = b_kn when m_k = n (else 0): the strictly proper remainder goes to B
        cols.append(xp.where(live, bk[:n_max] - d * a[:n_max], 0.0))
        ds.append(d)
    B = xp.stack(cols, axis=1) if cols else xp.zeros((n_max, 0))
    D = xp.stack(ds)[None, :] if ds else xp.zeros((1, 0))
    C = xp.where(i == n - 1, 1.0, 0.0)[None, :]
    return StateSpace(A, B, C, D), live


def _model_only(fn: str, model) -> None:
    if not isinstance(model, Model):
        raise TypeError(f"{fn}(): model must be a Model (from identify, search, estimate or "
                        f"Model.from_coefficients), got {type(model).__name__}")


def _delays(model: Model):
    return np.asarray(model.delays, dtype=np.float64).reshape(-1)


def to_scipy(model: Model, *, ignore_delays: bool = False):
    """`scipy.signal.StateSpace` of the model (inputs: the K inputs, then the offset's constant
    input when the model has one).

    SciPy's LTI systems cannot carry a transport delay: a model with a nonzero delay raises a
    ValueError that says what to do, unless `ignore_delays=True` (the delay-free part
    $B_k(s)/A(s)$, what earlier versions returned silently). For the delays use
    `to_control(model, pade_order=...)` (a Pade approximation) or shift the inputs yourself.
    """
    require_x64("to_scipy")
    _model_only("to_scipy", model)
    from ._boundary import eager_only

    eager_only("to_scipy", model)
    import numpy as np
    from scipy import signal

    if not isinstance(ignore_delays, bool):
        raise TypeError(f"to_scipy(): ignore_delays must be True or False (got {ignore_delays!r})")
    tau = _delays(model)
    if np.any(tau != 0) and not ignore_delays:
        raise ValueError(
            f"to_scipy(): scipy.signal systems cannot carry the model's delays {tau.tolist()}; "
            "use to_control(model, pade_order=5) for a Pade approximation, or "
            "to_scipy(model, ignore_delays=True) for the delay-free part"
        )
    ss = _realised(model)  # NumPy: also inside a user's jit, where a device_put would trace
    return signal.StateSpace(*(np.asarray(M) for M in (ss.A, ss.B, ss.C, ss.D)))


def to_control(model: Model, *, pade_order: int = 5):
    r"""python-control `StateSpace` of the model, delays included as Pade approximations.

    Input k's delay $e^{-s\tau_k}$ becomes python-control's `pade(tau_k, pade_order)` in series
    before the plant (python-control 0.10 has no exact delay element). A Pade approximation is
    all-pass (exact magnitude); its phase error, measured here, is below 0.001 deg for
    $\omega\tau \le 2$ and 0.15 deg at $\omega\tau = 5$ with the default order 5 (37 deg at
    $\omega\tau = 10$; order 7: 2 deg, order 10: 0.002 deg there). Each delayed input adds
    `pade_order` states. `pade_order=0` drops the delays (the delay-free
    part). Inputs are named after the model's (plus "offset" for the offset's constant input);
    requires the optional `control` package.
    """
    require_x64("to_control")
    _model_only("to_control", model)
    from ._boundary import eager_only

    eager_only("to_control", model)
    try:
        import control
    except ImportError as err:  # pragma: no cover - depends on the environment
        raise ImportError("to_control() needs python-control: pip install control") from err
    import numpy as np

    from ._boundary import integer

    pade_order = integer("to_control", "pade_order", pade_order, lo=0, hi=20,
                         fix="use 3..10 (higher orders are ill-conditioned)")
    ss = _realised(model)  # NumPy, as to_scipy
    names = list(model.input_names) + (["offset"] if model.has_offset else [])
    if len(set(names)) < len(names):  # python-control keeps one label per name: sys[0, name]
        # then picked another column than the name said
        raise ValueError(f"to_control(): the system's input labels {names} (the model's inputs"
                         f"{' and offset for its offset term' if model.has_offset else ''}) "
                         "must differ: rename the inputs (model.labelled(output_name, "
                         "input_names))")
    plant = control.ss(*(np.asarray(M) for M in (ss.A, ss.B, ss.C, ss.D)))
    tau = _delays(model)
    if pade_order == 0 or not np.any(tau != 0):
        return control.ss(plant, inputs=names, outputs=[model.output_name])
    blocks = []
    for k in range(len(names)):
        if k < tau.size and tau[k] != 0:
            num, den = control.pade(float(tau[k]), pade_order)
            blocks.append(control.tf2ss(num, den))
        else:
            blocks.append(control.ss([], [], [], [[1.0]]))
    delayed = control.series(control.append(*blocks), plant)
    return control.ss(delayed, inputs=names, outputs=[model.output_name])
