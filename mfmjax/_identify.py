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
    feedthrough_corrections,
    gram_matrix,
    level_vector,
    modulated_columns,
    settings_valid,
    signal_levels,
    steady_input_columns,
)
from ._jit import jit
from ._linalg import hurwitz
from ._model import Model
from ._modulating import ModulatingFunction, as_values
from ._pytree import build, replace_fields
from ._quadrature import edge_padded, record_bucket
from ._signals import Signals, dependent_inputs
from ._solve import (
    DEAD_COLUMN_RTOL,
    centred_eta,
    constrained_solve,
    default_eta,
    finish_solve,
    uncentred,
)
from ._status import Status, describe
from ._structure import Structure

FEEDTHROUGH_STEPS = 4  # fixed-point steps of the m_k = n output correction (see _gram)


def _concrete(x) -> bool:
    return not isinstance(x, jax.core.Tracer)


def _check(signals: Signals, structure: Structure, mf: ModulatingFunction, eta,
           fn: str = "identify"):
    if not isinstance(signals, Signals):
        from ._boundary import swap_hint

        raise TypeError(f"{fn}(): signals must be a Signals, got {type(signals).__name__}"
                        f"{swap_hint('identify', signals)}")
    if not isinstance(structure, Structure):
        raise TypeError(
            f"{fn}(): structure must be a Structure, got {type(structure).__name__}"
        )
    if not isinstance(mf, ModulatingFunction):
        raise TypeError(f"{fn}(): mf must be a ModulatingFunction, got {type(mf).__name__}")
    structure = Structure.for_inputs(structure, signals.n_inputs, fn)  # (a bound method of an
    # equinox Module is built anew at every access: about 30 us on this hot path)
    n = structure.n
    for name, val in (("N", mf.N), ("M", mf.M)):
        if _concrete(val) and float(np.min(np.asarray(val))) < n:
            raise ValueError(
                f"{fn}(): {name} must be >= n (got {name}={_fmt(val)}, n={n}); "
                f"phi^(i) must vanish at both ends for i < n"
            )
    p = structure.n_params + int(signals.offset)
    check_record_length(signals, mf, p, fn)
    eta = default_eta(p, signals.offset) if eta is None else eta
    eta = jnp.asarray(eta, dtype=jnp.float64) if not _concrete(eta) else np.asarray(eta, np.float64)
    if eta.shape != (p,):
        raise ValueError(
            f"{fn}(): eta must have one entry per parameter ({p}), got shape {eta.shape}"
        )
    return structure, eta


def _fmt(v):
    v = np.asarray(v)
    return v.tolist()


def identify_model(signals, structure, mf, eta, length: int, end=None,
                   labels: tuple[str, tuple[str, ...]] = ("y", ()), *,
                   flag_unstable: bool = False) -> Model:
    """The MFM estimate as a `Model` labelled with `labels` (output name, input names; default
    names when empty): `signals` unlabelled, `mf` as values (`as_values`), `length` the static
    kernel length (`compiled_length`), `end` the record's own length when `signals` are padded
    (`bucketed`); `flag_unstable`: set `Status.UNSTABLE` (`identify`). The compiled part
    (`identify_core`) returns only what it computes; the model is assembled around it from the
    arguments (no copies of the settings through the program)."""
    a, b, offset, theta, J, J_rel, cond, status = identify_core(signals, structure, mf, eta,
                                                                length, end, flag_unstable)
    output_name, input_names = labels
    return build(Model, a=a, b=b, offset=offset, delays=signals.delays, theta=theta, J=J,
                 J_rel=J_rel, cond=cond, status=status, mf=mf, structure=structure,
                 intersample=signals.intersample, has_offset=signals.offset,
                 output_name=output_name,
                 input_names=tuple(input_names) or tuple(f"u{k + 1}" for k in range(
                     signals.n_inputs)))


@jit
def identify_core(signals, structure, mf, eta, length: int, end=None,
                  flag_unstable: bool = False):
    """The compiled core of `identify_model`: (a, b, offset, theta, J, J_rel, cond, status).
    One program per (structure, record bucket, kernel bucket). With `flag_unstable`, an A(s)
    with a root in the closed right half plane sets `Status.UNSTABLE` (the Routh test
    `hurwitz`, as the search's validation and SRIVC apply it), except where a_n vanished or
    values are non-finite: those bits already say the coefficients are no model."""
    K = signals.n_inputs
    n = structure.n
    means = levels = None  # with an offset term the columns are those of the centred signals
    if signals.offset:
        means = signal_levels(signals, None if end is None else
                              jnp.arange(signals.n_samples) < end)  # padding not counted
        starts = np.cumsum([n + 1] + [mk + 1 for mk in structure.m])[:K]
        levels = level_vector(means, starts, structure.n_params + 1)
        eta = centred_eta(eta, levels)
    ms = modulated_columns(signals, structure, mf, length, end, means)
    G = gram_matrix(ms)
    alive = jnp.sqrt(jnp.maximum(jnp.diagonal(G), 0.0)) > DEAD_COLUMN_RTOL * ms.bounds
    alive = alive & ~steady_input_columns(ms.excited, n + 1, [mk + 1 for mk in structure.m],
                                          signals.offset)
    theta, cond, reduced = constrained_solve(G, eta, alive)
    corrections = feedthrough_corrections(signals, structure, mf, length=length)
    if corrections:  # m_k = n: remove D_k * Delta_k from the output columns, re-solve
        starts = np.cumsum([n + 1] + [mk + 1 for mk in structure.m])
        y_cols = ms.columns[:, : n + 1]

        def step(_, carry):  # one program for every step (as the search's)
            theta, ms, _ = carry
            an = jnp.where(theta[n] != 0, theta[n], 1.0)
            fix = sum(theta[starts[k] + n] / an * delta for k, delta in corrections)
            ms = eqx.tree_at(lambda m: m.columns, ms, ms.columns.at[:, : n + 1].set(y_cols - fix))
            G = gram_matrix(ms)
            return constrained_solve(G, eta, alive, conditioning=False)[0], ms, G

        theta, ms, G = jax.lax.fori_loop(0, FEEDTHROUGH_STEPS, step, (theta, ms, G))
        theta, cond, reduced = constrained_solve(G, eta, alive)
    if levels is not None:
        theta = uncentred(theta, levels)
    finite = jnp.isfinite(signals.y).all() & jnp.isfinite(signals.u).all()
    status, div, quad, J_rel = finish_solve(theta, G, reduced, n, finite,
                                            jnp.all(ms.excited) & jnp.all(alive), levels=levels)
    # a traced setting outside its valid range, or whose kernels (h + delays over dt) do not
    # fit the compiled length (the truncated kernels gave plausible numbers): no model (NaN),
    # flagged as out of bounds
    valid = settings_valid(signals, n, mf, ms.first, end, theta.shape[0]) & ms.fits
    status = jnp.where(valid, status, Status.OUT_OF_BOUNDS | (status & Status.NONFINITE))
    theta, quad, J_rel = (jnp.where(valid, x, jnp.nan) for x in (theta, quad, J_rel))
    bs, pos = [], n + 1
    for k in range(K):
        bs.append(theta[pos : pos + structure.m[k] + 1] / div)
        pos += structure.m[k] + 1
    offset = theta[pos] / div if signals.offset else jnp.zeros((), jnp.float64)  # not weak-typed
    J = mf.h ** (mf.N + mf.M + 1) * jnp.sqrt(quad)  # undo the common factor (see _gram)
    a = theta[: n + 1] / div
    status = status.astype(jnp.int32)
    if flag_unstable:
        void = ((status & int(Status.NONFINITE | Status.A_N_ZERO)) != 0) | ~valid
        status = status | jnp.where(void | hurwitz(a), 0, int(Status.UNSTABLE)).astype(jnp.int32)
    return a, tuple(bs), offset, theta, J, J_rel, cond, status


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
    - `eta`: constraint vector, default ones on a and b (the paper's choice) and 0 on the
      offset term (`default_eta`: the estimate then does not depend on the signals' levels).
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
