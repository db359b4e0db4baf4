"""`identify`: modulating functions -> modulated signals -> Gram -> constrained solve -> Model."""

from __future__ import annotations

import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._gram import (
    check_record_length,
    compiled_length,
    feedthrough_columns,
    gram_matrix,
    modulated_columns,
    steady_input_columns,
)
from ._jit import jit
from ._linalg import hurwitz
from ._model import Model
from ._modulating import ModulatingFunction, as_values
from ._pytree import build, replace_fields
from ._quadrature import edge_padded, record_bucket
from ._signals import Signals, dependent_inputs
from ._solve import DEAD_COLUMN_RTOL, constrained_solve, finish_solve
from ._status import Status, describe
from ._structure import Structure

FEEDTHROUGH_STEPS = 4  # fixed-point steps of the m_k = n output correction (see _gram)


def _concrete(x) -> bool:
    return not isinstance(x, jax.core.Tracer)


def _check(signals: Signals, structure: Structure, mf: ModulatingFunction, eta):
    if not isinstance(signals, Signals):
        raise TypeError(f"identify(): signals must be a Signals, got {type(signals).__name__}")
    if not isinstance(structure, Structure):
        raise TypeError(
            f"identify(): structure must be a Structure, got {type(structure).__name__}"
        )
    if not isinstance(mf, ModulatingFunction):
        raise TypeError(f"identify(): mf must be a ModulatingFunction, got {type(mf).__name__}")
    structure = Structure.for_inputs(structure, signals.n_inputs)  # (a bound method of an
    # equinox Module is built anew at every access: about 30 us on this hot path)
    n = structure.n
    for name, val in (("N", mf.N), ("M", mf.M)):
        if _concrete(val) and float(np.min(np.asarray(val))) < n:
            raise ValueError(
                f"identify(): {name} must be >= n (got {name}={_fmt(val)}, n={n}); "
                f"phi^(i) must vanish at both ends for i < n"
            )
    p = structure.n_params + int(signals.offset)
    check_record_length(signals, mf, p)
    eta = np.ones(p) if eta is None else eta
    eta = jnp.asarray(eta, dtype=jnp.float64) if not _concrete(eta) else np.asarray(eta, np.float64)
    if eta.shape != (p,):
        raise ValueError(
            f"identify(): eta must have one entry per parameter ({p}), got shape {eta.shape}"
        )
    return structure, eta


def _fmt(v):
    v = np.asarray(v)
    return v.tolist()


ORDER_BUCKETS = (2, 4, 8)  # identify's programs pad the orders up to one of these


def order_bucket(n: int) -> int:
    """The padded order of `identify`'s program for output order n (n itself beyond 8)."""
    return next((b for b in ORDER_BUCKETS if b >= n), n)


def padded_layout(structure: Structure, K: int, offset: bool):
    """`structure` in the padded column layout of `identify_core`: every signal's derivative
    orders 0..n_b (n_b = `order_bucket(n)`), [y; u_1; ..; u_K; offset]. Returns (n_b, the
    positions of the compact theta [a; b_1; ..; b_K; offset] in it (NumPy ints))."""
    n_b, w = order_bucket(structure.n), order_bucket(structure.n) + 1
    idx = list(range(structure.n + 1)) + [w * (k + 1) + j for k, mk in enumerate(structure.m)
                                          for j in range(mk + 1)]
    if offset:
        idx.append(w * (K + 1))
    return n_b, np.asarray(idx)


def feedthrough_inputs(signals: Signals, structure: Structure) -> tuple[int, ...]:
    """Inputs whose output columns `identify` corrects (`feedthrough_corrections`)."""
    return tuple(k for k in range(signals.n_inputs)
                 if structure.m[k] == structure.n and not signals.smooth[k]
                 and signals.output_rule == "cubic")


def identify_model(signals, structure, mf, eta, length: int, end=None,
                   labels: tuple[str, tuple[str, ...]] = ("y", ()), *,
                   flag_unstable: bool = False) -> Model:
    """The MFM estimate as a `Model` labelled with `labels` (output name, input names; default
    names when empty): `signals` unlabelled, `mf` as values (`as_values`), `length` the static
    kernel length (`compiled_length`), `end` the record's own length when `signals` are padded
    (`bucketed`); `flag_unstable`: set `Status.UNSTABLE` (`identify`). The compiled part
    (`identify_core`) sees the structure only through its order bucket and feed-through inputs:
    the orders n, m_k enter as values (the column mask), so every structure of one bucket
    shares its program. The model is assembled around it from the arguments (no copies of the
    settings through the program)."""
    K = signals.n_inputs
    n_b, idx = padded_layout(structure, K, signals.offset)
    p_b = (n_b + 1) * (K + 1) + int(signals.offset)
    mask = np.zeros(p_b, bool)
    mask[idx] = True
    if isinstance(eta, jax.core.Tracer):
        eta_b = jnp.zeros(p_b).at[idx].set(eta)
    else:
        eta_b = np.zeros(p_b)
        eta_b[idx] = np.asarray(eta)
    out = identify_core(signals, n_b, feedthrough_inputs(signals, structure),
                        np.int32(structure.n), mask, mf, eta_b, length, end, flag_unstable)
    traced = any(isinstance(x, jax.core.Tracer) for x in out)
    if not traced:  # cut to the structure on the host (slicing device arrays would compile)
        out = jax.device_get(out)
    a, b, offset, theta, J, J_rel, cond, status = out
    fields = dict(a=a[: structure.n + 1], b=tuple(b[k, : mk + 1] for k, mk in enumerate(
        structure.m)), offset=offset, theta=theta[idx], J=J, J_rel=J_rel, cond=cond,
        status=status)
    if not traced:
        fields = jax.device_put(fields)
    output_name, input_names = labels
    return build(Model, **fields, delays=signals.delays, mf=mf, structure=structure,
                 intersample=signals.intersample, has_offset=signals.offset,
                 output_name=output_name,
                 input_names=tuple(input_names) or tuple(f"u{k + 1}" for k in range(K)))


@jit
def identify_core(signals, n_b: int, ft: tuple, n, mask, mf, eta, length: int, end=None,
                  flag_unstable: bool = False):
    """The compiled core of `identify_model` in the padded layout (`padded_layout`: orders
    0..`n_b` for every signal, the columns beyond the structure's orders outside `mask`,
    zeroed and left out of the solve, eq. 11): (a (n_b+1,), b (K, n_b+1), offset, theta,
    J, J_rel, cond, status). `n` (the output order) and `mask` are values: one program per
    (order bucket, feed-through inputs `ft`, record bucket, kernel bucket). With
    `flag_unstable`, an A(s) with a root in the closed right half plane sets
    `Status.UNSTABLE` (the Routh test `hurwitz`, as the search's validation and SRIVC apply
    it), except where a_n vanished or values are non-finite: those bits already say the
    coefficients are no model."""
    K = signals.n_inputs
    w = n_b + 1
    ms = modulated_columns(signals, Structure(n_b, [n_b] * K), mf, length, end)
    ms = eqx.tree_at(lambda m: m.columns, ms, jnp.where(mask, ms.columns, 0.0))
    G = gram_matrix(ms)
    alive = jnp.sqrt(jnp.maximum(jnp.diagonal(G), 0.0)) > DEAD_COLUMN_RTOL * ms.bounds
    alive = alive & ~steady_input_columns(ms.excited, w, [w] * K, signals.offset)
    active = alive & mask
    theta, cond, reduced = constrained_solve(G, eta, active)
    if ft:  # m_k = n: remove D_k * Delta_k from the output columns, re-solve
        deltas = [(k, feedthrough_columns(signals, k, n_b, mf, length)) for k in ft]
        y_cols = ms.columns[:, :w]
        for _ in range(FEEDTHROUGH_STEPS):
            an = jnp.where(theta[n] != 0, theta[n], 1.0)
            fix = sum(theta[w * (k + 1) + n] / an * delta for k, delta in deltas)
            fixed = jnp.where(mask[:w], y_cols - fix, 0.0)
            ms = eqx.tree_at(lambda m: m.columns, ms, ms.columns.at[:, :w].set(fixed))
            G = gram_matrix(ms)
            theta, _, _ = constrained_solve(G, eta, active, conditioning=False)
        theta, cond, reduced = constrained_solve(G, eta, active)
    finite = jnp.isfinite(signals.y).all() & jnp.isfinite(signals.u).all()
    status, div, quad, J_rel = finish_solve(theta, G, reduced, n, finite,
                                            jnp.all(ms.excited) & jnp.all(alive | ~mask),
                                            n_max=n_b)
    status = status | jnp.where(ms.fits, 0, Status.OUT_OF_BOUNDS)
    b = theta[w : w * (K + 1)].reshape(K, w) / div
    offset = theta[w * (K + 1)] / div if signals.offset else jnp.zeros((), jnp.float64)
    J = mf.h ** (mf.N + mf.M + 1) * jnp.sqrt(quad)  # undo the common factor (see _gram)
    a = theta[:w] / div
    status = status.astype(jnp.int32)
    if flag_unstable:
        void = (status & int(Status.NONFINITE | Status.A_N_ZERO)) != 0
        status = status | jnp.where(void | hurwitz(a), 0, int(Status.UNSTABLE)).astype(jnp.int32)
    return a, b, offset, theta, J, J_rel, cond, status


def bucketed(signals: Signals):
    """(`signals` unlabelled (`Signals.unlabelled`) and padded to their `record_bucket` by
    repeating the last sample, their length as a value): records of every length in a bucket
    share one compiled `identify_core`. Traced signals (inside a user's jit or vmap) are only
    unlabelled, with `end` None."""
    if not _concrete(signals.y) or not _concrete(signals.u):
        return Signals.unlabelled(signals), None
    T = signals.n_samples
    pad = record_bucket(T) - T
    y, u = (edge_padded(np.asarray(x), pad) if pad else x for x in (signals.y, signals.u))
    return Signals.unlabelled(signals, y=y, u=u), np.int32(T)  # one copy, no program


def identify(
    signals: Signals,
    structure: Structure,
    mf: ModulatingFunction,
    *,
    eta=None,
    delay_max: float | None = None,
) -> Model:
    r"""Identify the continuous-time MISO model of eq. (1) with the Modulating Function Method.

    Builds the modulated signals of eq. (3)-(4) with exact quadrature weights, the Gram matrix
    of eq. (9)-(10), and minimises $\theta^T G \theta$ subject to $\eta^T\theta = 1$ (eq. 11)
    with the equilibrated KKT solve (`constrained_solve`), which equals the closed form (12)
    wherever G is invertible and stays defined when G is singular (noise-free data).

    **Arguments:**

    - `signals`: the experiment (`Signals`).
    - `structure`: orders (`Structure(n, m)`), m_k <= n.
    - `mf`: the modulating function (`ModulatingFunction(N, M, h)`), N, M >= n.
    - `eta`: constraint vector, default all ones (the paper's choice).
    - `delay_max`: static bound on the delays, needed only when delays are traced.

    **Returns:** a `Model` with a_n = 1. Problems found in the data (constant input, singular
    reduced Gram, a_n = 0, non-finite values) are reported in `model.status`, never as silent
    NaN, and so is an A(s) with a root in the closed right half plane (`Status.UNSTABLE`: an
    unstable plant, or noise); in eager mode they also warn. Jit-able and vmap-able over
    `mf.h` (give `h_max`) and over datasets of equal shape.

    Settings are values: N, M, h and the delays enter the compiled program as arrays, and the
    kernel length is bucketed (`kernel_bucket`), so a new setting whose h + delays fit the
    current bucket reuses the program; the record is padded to its `record_bucket` and the
    padding masked exactly, so a new record length inside a bucket reuses it too; t0 and the
    signal names never enter it. A traced h (or delay) beyond its static bound sets
    `Status.OUT_OF_BOUNDS` instead of truncating.
    """
    from ._boundary import check_identify

    check_identify(signals, structure, mf, eta, delay_max)
    structure, eta = _check(signals, structure, mf, eta)
    length = compiled_length(signals, mf, delay_max)
    padded, end = bucketed(signals)
    model = identify_model(padded, structure, as_values(mf), eta, length, end,
                           (signals.output_name, signals.input_names), flag_unstable=True)
    dependent = dependent_inputs(signals)
    if dependent and _concrete(model.status) and model.status.ndim == 0:
        model = replace_fields(model, status=np.int32(int(model.status)
                                                      | Status.ILL_CONDITIONED))
        warnings.warn(f"identify(): the inputs {list(dependent)} are linearly dependent (one "
                      "is a multiple of the others): their gains cannot be told apart; drop "
                      "all but one of them", stacklevel=2)
    if _concrete(model.status) and model.status.ndim == 0 and int(model.status) != 0:
        warnings.warn(
            f"identify(): status {describe(int(model.status))} (n={structure.n}, "
            f"m={list(structure.m)}); see Model.status",
            stacklevel=2,
        )
    return model
