r"""Modulated signals $c(t)$ (eq. 3-6) and the Gram matrix $G$ (eq. 9-10).

Columns, in order: $y_0..y_n$, $-u_{10}..-u_{1m_1}$, ..., $-u_{K0}..-u_{Km_K}$ and, when the
signals carry an offset term, $-u_{\text{off},0}$ for the constant input 1. Each column is the
paper's column divided by $h^{N+M+1}$ (a common factor, so $\theta$ of eq. 12 is unchanged and
$J$ is rescaled by it in `identify`); the remaining factor $h^{-i}$ keeps the raw meaning of
$\theta$. The Gram integral runs over the valid samples $t_k \ge t_0 + \max_k(\tau_k) + h$
(rounded up to the grid) with the Gregory rule (O(dt^4)).
"""

from __future__ import annotations

import operator

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._boundary import require_x64
from ._jit import jit
from ._modulating import ModulatingFunction, as_values, phi_scaled
from ._quadrature import (
    EDGE,
    delayed_samples,
    gregory_weights,
    kernel_bucket,
    kernel_length,
    kernel_weights,
    modulate,
    profile_weights,
    support_samples,
)
from ._signals import Signals
from ._structure import Structure

MIN_VALID = 8  # fewest valid samples accepted for the Gram integral


class ModulatedSignals(eqx.Module):
    """Columns of c(t) on the whole record, with the Gram quadrature weights (0 where invalid)."""

    columns: jax.Array  # (T, p)
    weights: jax.Array  # (T,)
    bounds: jax.Array  # (p,) upper bound of each column's L2 norm (dead-column test)
    first: jax.Array  # index of the first valid sample
    excited: jax.Array  # (K,) bool: input k varies on the record
    fits: jax.Array  # bool: every kernel's support (tau + h) fits the compiled kernel length


def column_sources(signals: Signals, structure: Structure):
    """Static list of (signal index, derivative order, rule, sign) per column; -1 is y, K offset."""
    K = signals.n_inputs
    srcs = [(-1, i, signals.output_rule, 1.0) for i in range(structure.n + 1)]
    for k in range(K):
        rule = "cubic" if signals.smooth[k] else signals.intersample[k]
        srcs += [(k, j, rule, -1.0) for j in range(structure.m[k] + 1)]
    if signals.offset:
        srcs.append((K, 0, "zoh", -1.0))
    return srcs


def source_groups(signals: Signals, structure: Structure):
    """`column_sources` grouped by signal: [((signal, rule, sign), [derivative orders]), ...] in
    column order (consecutive columns of one signal share its rule and sign)."""
    groups = []
    for src, i, rule, sign in column_sources(signals, structure):
        if groups and groups[-1][0] == (src, rule, sign):
            groups[-1][1].append(i)
        else:
            groups.append(((src, rule, sign), [i]))
    return groups


TRACED_DELAYS = ("pass delay_max=... (records stacked for jax.vmap carry their delays as "
                 "traced values: delay_max=0.0 when they have none)")


def static_span(signals: Signals, mf: ModulatingFunction, delay_max: float | None) -> float:
    """Largest tau + h, fixing the static kernel length."""
    h_max = mf.h_max
    if h_max is None:  # a model's own mf (`as_values`) carries no bound: its concrete h is one
        if isinstance(mf.h, jax.core.Tracer):
            raise ValueError(
                "identify(): h is traced (jit/vmap/grad) but no static bound is known; "
                "pass ModulatingFunction(..., h_max=...)"
            )
        h_max = float(np.max(np.asarray(mf.h)))
    if delay_max is None:
        if isinstance(signals.delays, jax.core.Tracer):
            raise ValueError(
                f"identify(): delays are traced but no static bound is known; {TRACED_DELAYS}"
            )
        delay_max = float(np.max(np.asarray(signals.delays), initial=0.0))
    return h_max + delay_max


def compiled_length(signals: Signals, mf: ModulatingFunction, delay_max: float | None = None) -> int:
    """Static kernel length of a program for these settings: the bucket (`kernel_bucket`) of the
    length that h (or h_max when h is traced) plus the delays (or delay_max) needs."""
    return kernel_bucket(kernel_length(static_span(signals, mf, delay_max), signals.host_dt))


def modulated_signals(
    signals: Signals, structure: Structure, mf: ModulatingFunction, delay_max: float | None = None,
    *, length: int | None = None, end=None,
) -> ModulatedSignals:
    r"""All columns of $c(t)$ (eq. 6), scaled as described in the module docstring.

    `length` is the static kernel length (default: the `kernel_bucket` of what h_max and
    delay_max need, as `identify` compiles it); a support
    longer than it is reported in `fits`, never truncated silently. `end` (may be traced): the
    Gram integral ends before sample `end` (default: the record's end), e.g. on a record padded
    to its `record_bucket`; the columns are causal, so those before `end` do not see the
    padding. Called outside jit/vmap/grad it runs one compiled program per structure, record
    length, sampling interval, rules, offset term and kernel length: a new h, N, M, delay,
    t0 or name reuses it."""
    from . import _boundary as _b
    from ._identify import _check

    fn = "modulated_signals"
    _b.check_identify(signals, structure, mf, None, delay_max, fn)
    structure, _ = _check(signals, structure, mf, None, fn)  # inputs, N, M >= n, h in the record
    length = compiled_length(signals, mf, delay_max) if length is None else operator.index(length)
    if end is not None and not isinstance(end, jax.core.Tracer):
        end = np.int32(_b.integer(fn, "end", end, lo=1, hi=signals.n_samples,
                                  fix="the sample index the Gram integral ends before"))
    return _modulated_program(Signals.unlabelled(signals), structure, as_values(mf), length, end)


def signal_levels(signals: Signals, inside=None):
    r"""(K + 1,) the constants removed from the output and from each input before they are
    modulated when the model has an offset term (their means, with their gradient: any
    constant is exact in value up to the quadrature of non-integer N, M): with the offset
    column in the model, $y = y' + c_y$, $u_k = u_k' + c_k$ only move
    the offset ($\theta_{off}' = \theta_{off} - c_y a_0 + \sum_k c_k b_{k0}$, `level_vector`),
    and the Gram of the centred columns keeps the signals' variation: with a level of 1e4
    its $y_0$, $u_{k0}$ and offset columns were collinear to 1e-8 and the solve returned
    coefficients 1e-4 off (8e-3 at n = 3; a level of 1e6: 100 % off), status ok. `inside`
    (T,) bool: the means over the identification windows' samples only (the search took the
    whole record's, validation data included, so its J_rel differed from `identify`'s on the
    window's own record)."""
    if inside is None:
        means = jnp.concatenate([jnp.mean(signals.y)[None], jnp.mean(signals.u, axis=0)])
    else:
        w = inside.astype(jnp.float64) / jnp.maximum(jnp.sum(inside), 1)
        means = jnp.concatenate([(w @ signals.y)[None], w @ signals.u])
    return means  # (its gradient counts: a stop_gradient here was off by 3.4e-4 where the
    # value is level-free to 1.3e-8, at non-integer N, M, whose quadrature of phi^(i) does not
    # sum to exactly zero; an audit of 2026-11-28)


def first_position(h, delays, dt):
    """The first sample (from a window's start) the modulated columns are integrated from:
    every kernel, delays included, inside the window (`support_samples` of h + max tau)."""
    return support_samples(h + (jnp.max(delays) if delays.shape[0] else 0.0), dt)


def read_samples(n_samples: int, segments, first, h, delays, dt, rules, feedthrough):
    """(T, K) bool: the samples of each input that the modulated columns read. Positions
    run from start + `first` to end - 1 of each identification segment [start, end) (S, 2);
    input k's kernel at position t covers u_k from t - tau_k - h to t - tau_k, and its rule
    (`rules[k]`: "zoh", "foh", "cubic") reads the samples at lags d + 1 (zoh: held from the
    sample before), d (foh) or max(d - 1, 0) (cubic: one node beyond the cell) back to
    ceil((h + tau_k)/dt), d = floor(tau_k/dt); a feed-through input (`feedthrough[k]`: m_k =
    n, its delayed samples enter the output columns) also lag d. The excitation test runs on
    these: an input constant over them is no excitation, whatever it does in the window's last
    tau_k (a step there passed the test on the window's samples, and the constant delayed
    input and the offset, collinear, came out at +-1e12, status ok)."""
    d = jnp.floor(delays / dt + EDGE).astype(jnp.int32)
    step = np.array([0 if ft else {"zoh": 1, "cubic": -1}.get(rule, 0)
                     for rule, ft in zip(rules, feedthrough)], np.int32)
    idx = jnp.arange(n_samples)[:, None, None]
    lo = segments[None, :, :1] + first - support_samples(h + delays, dt)[None, None, :]
    hi = segments[None, :, 1:] - 1 - jnp.maximum(d + step, 0)[None, None]
    return jnp.any((idx >= lo) & (idx <= hi), axis=1)


def input_rules(signals: Signals) -> tuple:
    """Each input's quadrature rule: cubic where `smooth`, else its intersample rule."""
    return tuple("cubic" if s else r for r, s in zip(signals.intersample, signals.smooth))


def level_vector(levels, b_starts, p: int):
    r"""(p,) $l$ with $\theta_{off}' = \theta_{off} + l^T\theta$ for the centred columns
    (`signal_levels`): $-c_y$ at $a_0$, $+c_k$ at $b_{k0}$ (`b_starts`, static), 0 elsewhere
    (the offset last)."""
    return jnp.zeros(p).at[0].set(-levels[0]).at[np.asarray(b_starts, int)].set(levels[1:])


def modulated_columns(signals: Signals, structure: Structure, mf: ModulatingFunction,
                      length: int, end=None, levels=None) -> ModulatedSignals:
    """`modulated_signals` inside a program, at the static kernel `length`; `levels`
    (`signal_levels`): the columns of the centred signals (the dead-column bounds and the
    excitation test still of the signals themselves)."""
    dt = signals.dt
    T = signals.n_samples
    K = signals.n_inputs
    data = [signals.u[:, k] for k in range(K)] + [jnp.ones(T, dtype=jnp.float64)]
    delays = [signals.delays[k] for k in range(K)] + [jnp.asarray(0.0)]
    shift = [0.0] * (K + 2) if levels is None else [levels[k + 1] for k in range(K)] + [
        0.0, levels[0]]  # indexed by src: inputs, the constant (K), the output (-1)
    cols, bounds, first = [], [], jnp.asarray(0, dtype=jnp.int32)
    for (src, rule, sign), orders in source_groups(signals, structure):
        x = signals.y if src == -1 else data[src]
        tau = jnp.asarray(0.0) if src == -1 else delays[src]
        # every derivative order of one signal in one batch: one weights program, one convolution
        W = profile_weights(lambda r: jnp.stack([phi_scaled(r, mf.N, mf.M, i) for i in orders]),
                            mf.h, dt, rule, tau, length)
        W = W * (sign * mf.h ** (-jnp.asarray(orders, dtype=jnp.float64)))[:, None]
        cols.append(modulate(x - shift[src], W).T)
        bounds.append(jnp.sum(jnp.abs(W), axis=1) * jnp.max(jnp.abs(x)))
        first = jnp.maximum(first, support_samples(tau + mf.h, dt))
    q = gregory_weights(T, first, dt, end)
    bounds = jnp.concatenate(bounds) * jnp.sqrt(jnp.sum(q))
    fits = first <= length - 1
    reads = read_samples(T, jnp.asarray([[0, T if end is None else end]]), first, mf.h,
                         signals.delays, dt, input_rules(signals),
                         [mk == structure.n for mk in structure.m])
    return ModulatedSignals(jnp.concatenate(cols, axis=1), q, bounds, first,
                            input_varies(signals.u, reads), fits)


def input_varies(u, inside=None):
    """(K,) bool: input k varies (its spread above 1e-12 of its largest |u|) over the samples
    that `inside` (T,) or, per input, (T, K) marks (default: all of them)."""
    mask = None if inside is None else inside if inside.ndim == 2 else inside[:, None]
    keep = (lambda x, fill: x) if inside is None else (  # noqa: E731
        lambda x, fill: jnp.where(mask, x, fill))
    spread = (jnp.max(keep(u, -jnp.inf), axis=0, initial=-jnp.inf)
              - jnp.min(keep(u, jnp.inf), axis=0, initial=jnp.inf))
    return spread > 1e-12 * jnp.maximum(jnp.max(keep(jnp.abs(u), 0.0), axis=0, initial=0.0),
                                        1e-300)


def steady_input_columns(varies, a_len: int, b_lens, offset: bool):
    """(p,) bool: the columns of the inputs that do not vary that must be masked, in the
    layout [a (a_len); b_1 (b_lens[0]); ..; b_K; offset]. A steady input's lag-0 column is
    its level times the offset column (its derivative columns vanish and are masked as dead
    anyway): with an offset term, or another steady input before it, the two span one
    direction and the solve split them at random (b_k0 and the offset at +-1e12 on a DaISy
    record), so the input is masked and the offset (or the first steady input's b_k0) takes
    the level; without one, its b_k0 carries its steady contribution and stays."""
    K = len(b_lens)
    owner = np.repeat(np.arange(-1, K + 1), [a_len, *b_lens, int(offset)])
    if K == 0:
        return jnp.zeros(owner.shape, bool)
    steady = ~varies
    first = steady & (jnp.cumsum(steady) == 1)
    masked = steady & (~first if not offset else True)
    return (owner >= 0) & (owner < K) & masked[np.clip(owner, 0, K - 1)]


def feedthrough_corrections(
    signals: Signals, structure: Structure, mf: ModulatingFunction, delay_max: float | None = None,
    *, length: int | None = None,
):
    r"""Corrections of the output columns for inputs with $m_k = n$ (direct feed-through).

    Then $y = D_k u_k(t-\tau_k) + z$ inherits the breaks of $u_k$'s interpolant, which the
    cubic rule does not see. Applying the cubic rule to $y$ errs by $D_k \Delta_k$ with
    $\Delta_{k,i}$ = the cubic rule on the samples of $u_k(t_j - \tau_k)$ minus $u_k$'s own
    exact (zoh/foh, delayed) rule; `identify` subtracts
    $\hat D_k \Delta_k$ from the $y$ columns and re-solves (a few fixed-point steps).

    **Returns:** list of (k, Delta_k (T, n+1)) for those inputs (empty if none).
    """
    if length is None:
        length = kernel_length(static_span(signals, mf, delay_max), signals.host_dt)
    return [
        (k, feedthrough_columns(signals, k, structure.n, mf, length))
        for k in range(signals.n_inputs)
        if structure.m[k] == structure.n and not signals.smooth[k]
        and signals.output_rule == "cubic"
    ]


def feedthrough_columns(signals: Signals, k: int, n: int, mf: ModulatingFunction, length: int):
    r"""$\Delta_{k,i}$, $i = 0..n$ (T, n+1): cubic rule on the samples of $u_k(t_j-\tau_k)$ minus
    $u_k$'s own exact (zoh/foh, delayed) rule, in the scaling of the output columns."""
    dt = signals.dt
    x, tau, mode = signals.u[:, k], signals.delays[k], signals.intersample[k]
    on_grid = delayed_samples(x, tau, dt, mode)  # what D_k u_k(t - tau_k) puts into y's samples
    cols = []
    for i in range(n + 1):
        scale = mf.h ** (-i)
        seen = modulate(on_grid, kernel_weights(mf, i, dt, "cubic", 0.0, length) * scale)
        true = modulate(x, kernel_weights(mf, i, dt, mode, tau, length) * scale)
        cols.append(seen - true)
    return jnp.stack(cols, axis=1)


def gram_matrix(ms: ModulatedSignals) -> jax.Array:
    r"""$G = \int c(t) c(t)^T dt$ (eq. 9-10), Gregory rule on the valid samples."""
    return ms.columns.T @ (ms.weights[:, None] * ms.columns)


def gram(ms: ModulatedSignals) -> jax.Array:
    r"""$G = \int c(t) c(t)^T dt$ (eq. 9-10), Gregory rule on the valid samples (one compiled
    program per shape outside jit/vmap/grad)."""
    require_x64("gram")
    if not isinstance(ms, ModulatedSignals):
        raise TypeError(f"gram(): give the ModulatedSignals of modulated_signals(signals, "
                        f"structure, mf), got {type(ms).__name__}")
    return _gram_program(ms)


_modulated_program = jit(modulated_columns)
_gram_program = jit(gram_matrix)


def settings_valid(signals: Signals, n: int, mf: ModulatingFunction, first, end, n_params: int):
    """Inside a program: the traced settings are in the range the eager checks enforce (N, M
    >= n and N + M <= `MAX_DEGREE`, h at least 2 samples, delays >= 0, dt > 0, all finite, and at
    least max(`MIN_VALID`, 2 p) valid samples after the kernels' support `first`). Concrete
    settings outside it are refused at the boundary; traced ones gave a wrong model with
    status ok (N = 2 < n = 3: a = [12.4, 12.5, 4.8, 1])."""
    from ._modulating import MAX_DEGREE

    N, M, h = (jnp.asarray(v, jnp.float64) for v in (mf.N, mf.M, mf.h))
    d = jnp.asarray(signals.delays, jnp.float64)
    dt = jnp.asarray(signals.dt, jnp.float64)
    T = signals.n_samples if end is None else end
    return (jnp.isfinite(N) & jnp.isfinite(M) & jnp.isfinite(h) & jnp.all(jnp.isfinite(d))
            & jnp.isfinite(dt) & (dt > 0)
            & (N >= n) & (M >= n) & (N + M <= MAX_DEGREE) & (h >= 2 * signals.dt * (1 - 1e-12))
            & jnp.all(d >= 0) & (T - first >= max(MIN_VALID, 2 * n_params)))


def check_record_length(signals: Signals, mf: ModulatingFunction, n_params: int,
                        fn: str = "identify"):
    """Boundary check: the record must hold h (+ delays) plus enough valid samples."""
    if isinstance(mf.h, jax.core.Tracer) or isinstance(signals.delays, jax.core.Tracer):
        return
    span = float(np.max(np.asarray(mf.h))) + float(np.max(np.asarray(signals.delays), initial=0.0))
    first = kernel_length(span, signals.host_dt) - 1  # support_samples, on the host (as plan_search)
    need = max(MIN_VALID, 2 * n_params)
    if signals.n_samples - first < need:
        raise ValueError(
            f"{fn}(): the record ({signals.duration:g} time units, {signals.n_samples} "
            f"samples) is too short for h={float(np.max(np.asarray(mf.h))):g} plus delays: it leaves "
            f"{max(signals.n_samples - first, 0)} valid samples, need {need}; "
            "use a smaller h or a longer record"
        )
