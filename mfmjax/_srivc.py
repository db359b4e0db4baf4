r"""Simplified refined instrumental variables for continuous-time models (SRIVC).

Young & Jakeman (1980); Garnier & Wang, *Identification of continuous-time models from sampled
data* (2008), ch. 4. The MISO model of eq. (1) with its common denominator,
$A(s)\,y = \sum_k B_k(s)\,u_k(t-\tau_k) + b_{\text{off}}$, $a_n = 1$, orders from the
`Structure` of the starting model, delays fixed. From the MFM estimate, iterate:

1. auxiliary model: $\hat x = \sum_k (B_k/A)\,u_k + b_{\text{off}}/A$, the exact noise-free
   response from rest (the same as `simulate(model, u, dt=dt)`);
2. prefilter every signal with $s^i/A(s)$, $i = 0..n$: one controllable-canonical filter
   $1/A$ per signal, whose state holds the filtered derivatives $0..n-1$ and whose
   $n$-th derivative is the input minus $a_{0..n-1}$ times the state;
3. solve the IV normal equations $\sum \hat\varphi \varphi^T \theta = \sum \hat\varphi\,
   y_f^{(n)}$, $\varphi = [-y_f^{(0..n-1)}, u_{kf}^{(0..m_k)}, 1_f]$, with the instruments
   $\hat\varphi$ built from $\hat x_f$ in place of $y_f$;

until the largest relative parameter change is below `tol`.

Exact discretisation: the filters are discretised exactly (augmented matrix exponential,
the step map of `simulate`) for the interpolant of each signal. Inputs follow their own
rule (zoh / foh) and delay, so $u_f$ and $\hat x$ are exact. The output $y$ and the auxiliary
output $\hat x$ are point samples of a continuous response (that is how `simulate` and any
sampler return them): they are filtered as piecewise linear (foh), so that their filtered
derivatives are those of the continuous response to $O(dt^2)$; holding them (zoh) would add
an $O(dt)$ half-sample lag. Both get the same rule, so regressors and instruments are built
alike. Consistency does not hinge on it: at $\hat A = A$,
$\sum_i a_i (s^i/A)\,y_{int} = y_{int}$ for any interpolant, which equals $y$ at every sample,
so on noise-free data the true parameters are an exact fixed point whatever dt (the tests
check recovery to rounding), and under noise the equation error at the samples is the noise.
Filters start from rest at the first sample; inputs before the first sample are held at its
value (as in `simulate`).

The sample recursion is a `lax.scan` with the small matrix product written elementwise:
measured on 7000 samples, n = 4, 5 signals, 0.6 ms per pass, against 0.9-3 ms for a chunked
scan (64-sample chunks, chunk starts by a short scan) and 14 ms for `lax.associative_scan`.
Two passes per iteration (the signals, then $\hat x$): one cascaded scan forming $\hat x$
inside the loop was 4-6x slower (its reductions do not fuse). benchmarks/noise_montecarlo.py
times whole fits against the NumPy/SciPy peer.
"""

from __future__ import annotations

import enum
import functools
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.custom_batching import custom_vmap

from . import _boundary as _b
from ._jit import array_jit
from ._linalg import expm, hurwitz, solve
from ._model import Model
from ._quadrature import delayed_samples, shift_samples, split_delay
from ._signals import Signals
from ._status import Status

DIVERGENCE_FACTOR = 100.0  # simulation error this many times the best iterate's: diverged
MAX_ITER_LIMIT = 10**6  # max_iter above this is a typo, not a request
ROUNDING_FLOOR = 1e-20  # E below this fraction of sum(y^2) is rounding: never 'diverged'


class SrivcStatus(enum.IntFlag):
    """Why the SRIVC iteration stopped (bit flags; 0: converged)."""

    CONVERGED = 0
    MAX_ITER = 1  # max_iter reached before the relative change fell below tol
    DIVERGED = 2  # simulation error grew DIVERGENCE_FACTOR times over the best iterate
    UNSTABLE_FILTER = 4  # an iterate's A(s) is not Hurwitz: the prefilter 1/A would blow up
    NONFINITE = 8  # non-finite data, or a singular IV system


def describe_srivc(status: int) -> str:
    status = int(status)
    if status == 0:
        return "converged"
    return ",".join(f.name.lower() for f in SrivcStatus if f.value and status & f.value)


class SrivcFit(eqx.Module):
    """Result of `srivc` (parameters ordered as `names`: a_0..a_{n-1}, b_kj, offset).

    `model` is the returned iterate (the converged one, else the best by simulation error);
    `status` holds `SrivcStatus` bits, `converged` is `status == 0`; `covariance` is the IV
    estimate $\\hat\\sigma^2 (\\hat\\Phi^T \\hat\\Phi)^{-1}$, `std_errors` its diagonal's root,
    `sigma2` the simulation-residual variance (sum / (T - p)), `E` the simulation error
    $dt \\sum (y - \\hat x)^2$ (eq. 17), `iterations` the IV solves done. E, sigma2 and the
    covariance belong to the last evaluated iterate: `model` itself, or when converged the
    iterate before it (within `tol`). The filters and $\\hat x$ start from rest.
    """

    model: Model
    start: Model
    theta: jax.Array
    std_errors: jax.Array
    covariance: jax.Array
    sigma2: jax.Array
    E: jax.Array
    iterations: jax.Array
    converged: jax.Array
    status: jax.Array
    names: tuple[str, ...] = eqx.field(static=True)

    def describe(self) -> str:
        """The status in words (concrete results only)."""
        return describe_srivc(int(self.status))


def _names(n, m, has_offset):
    names = [f"a_{i}" for i in range(n)]
    for k, mk in enumerate(m):
        names += [f"b_{k + 1}{j}" for j in range(mk + 1)]
    return tuple(names + (["offset"] if has_offset else []))


def _mm(Phi, z):
    """Phi (n, n) @ z (n, S) written elementwise (fuses inside the scan; see module)."""
    return sum(Phi[:, j, None] * z[j][None, :] for j in range(Phi.shape[0]))


def _filter(Phi, drive):
    """States z_j (T, n, S) of z_{j+1} = Phi z_j + drive_j from z_0 = 0."""
    def step(z, d):
        return _mm(Phi, z) + d, z

    return jax.lax.scan(step, jnp.zeros(drive.shape[1:]), drive)[1]


def _companion(a):
    """Controllable canonical A_c of 1/A(s) (a_n = 1): state = (w, w', .., w^(n-1))."""
    n = a.shape[0] - 1
    A = jnp.zeros((n, n)).at[jnp.arange(n - 1), jnp.arange(1, n)].set(1.0)
    return A.at[n - 1].set(-a[:n])


def _gammas(Ac, deltas):
    """e^{A d}, Gamma_0(d) e_n, Gamma_1(d) e_n for every d in `deltas` (one batched expm of
    the augmented matrix [[A, e_n, 0], [0, 0, 1], [0, 0, 0]] d, as in `simulate`)."""
    n = Ac.shape[0]
    aug = jnp.zeros((n + 2, n + 2)).at[:n, :n].set(Ac).at[n - 1, n].set(1.0).at[n, n + 1].set(1.0)
    E = jax.vmap(lambda d: expm(aug * d))(deltas)
    return E[:, :n, :n], E[:, :n, n], E[:, :n, n + 1]


def _terms(Ac, modes, taus, dt):
    r"""Phi (n, n) and per column the step terms (S, 3, n) of
    $z_{j+1} = \Phi z_j + P x_{j-d-1} + Q x_{j-d} + R x_{j-d+1}$ (delay (d + f) dt)."""
    S = len(modes)
    d, f = split_delay(taus, dt)
    E, g0, g1 = _gammas(Ac, jnp.concatenate([f * dt, (1.0 - f) * dt, jnp.full(1, dt)]))
    out = []
    for s, mode in enumerate(modes):
        E2, g0a, g1a, g0b, g1b, fs = E[S + s], g0[s], g1[s], g0[S + s], g1[S + s], f[s]
        if mode == "zoh":
            out.append(jnp.stack([E2 @ g0a, g0b, jnp.zeros_like(g0b)]))
        else:
            out.append(jnp.stack([E2 @ (fs * g0a - g1a / dt),
                                  E2 @ ((1.0 - fs) * g0a + g1a / dt) + g0b - g1b / dt,
                                  g1b / dt]))
    return E[-1], d, jnp.stack(out)


def _apply(X, d, PQR, a, taus, dt, modes, Phi):
    """Filtered derivatives (T, n+1, S) of the columns X (T, S) from their step terms."""
    n = a.shape[0] - 1
    cols = range(X.shape[1])
    shifted = [jnp.stack([shift_samples(X[:, s], d[s] + 1 - i) for i in range(3)], 1)
               for s in cols]  # (T, 3): x_{j-d-1}, x_{j-d}, x_{j-d+1}
    drive = jnp.stack([shifted[s] @ PQR[s] for s in cols], axis=-1)  # (T, n, S)
    z = _filter(Phi, drive)
    vals = jnp.stack([delayed_samples(X[:, s], taus[s], dt, modes[s]) for s in cols], axis=-1)
    top = vals - jnp.einsum("i,tis->ts", a[:n], z)
    return jnp.concatenate([z, top[:, None, :]], axis=1)


def _split(theta, n, m, has_offset):
    a = jnp.concatenate([theta[:n], jnp.ones(1)])
    pos, bs = n, []
    for mk in m:
        bs.append(theta[pos : pos + mk + 1])
        pos += mk + 1
    off = theta[pos] if has_offset else jnp.zeros(())
    return a, bs, off


def _step(theta, y, u, delays, *, n, m, modes, has_offset, dt):
    """One SRIVC pass at theta: (simulation error sum, next theta, Phi_hat^T Phi_hat)."""
    a, bs, off = _split(theta, n, m, has_offset)
    T, K = y.shape[0], len(m)
    Ac = _companion(a)
    # y first (foh, no delay; module docstring), then the inputs, then the constant
    X = [y] + [u[:, k] for k in range(K)] + ([jnp.ones(T)] if has_offset else [])
    cmodes = ("foh",) + tuple(modes) + (("zoh",) if has_offset else ())
    taus = jnp.concatenate([jnp.zeros(1), delays] + ([jnp.zeros(1)] if has_offset else []))
    Phi_d, d, PQR = _terms(Ac, cmodes, taus, dt)
    F = _apply(jnp.stack(X, 1), d, PQR, a, taus, dt, cmodes, Phi_d)  # (T, n+1, S)
    uf = [F[:, : mk + 1, 1 + k] for k, mk in enumerate(m)]
    of = [F[:, :1, -1]] if has_offset else []
    xhat = sum(uf[k] @ bs[k] for k in range(K)) + (of[0][:, 0] * off if has_offset else 0.0)
    xf = _apply(xhat[:, None], d[:1], PQR[:1], a, taus[:1], dt, ("foh",), Phi_d)[:, :, 0]
    Phi = jnp.concatenate([-F[:, :n, 0]] + uf + of, axis=1)
    Phih = jnp.concatenate([-xf[:, :n]] + uf + of, axis=1)
    target = F[:, n, 0]
    c = jnp.sqrt(jnp.sum(Phi**2, axis=0))
    ch = jnp.sqrt(jnp.sum(Phih**2, axis=0))
    c, ch = jnp.where(c > 0, c, 1.0), jnp.where(ch > 0, ch, 1.0)
    R = (Phih / ch).T @ (Phi / c)
    new = solve(R, (Phih / ch).T @ target) / c
    E = jnp.sum((y - xhat) ** 2)
    return E, new, Phih.T @ Phih


def _core(theta0, y, u, delays, max_iter, tol, *, n, m, modes, has_offset, dt):
    """The jitted iteration (see `srivc`); one traced SRIVC pass inside a while loop.

    E, sigma2 and the covariance belong to the last evaluated iterate: the returned one, or,
    when converged, the one before it (within `tol`)."""
    step = jax.tree_util.Partial(_step, n=n, m=m, modes=modes, has_offset=has_offset, dt=dt)
    guess = _stable_guess(n)
    floor = ROUNDING_FLOOR * jnp.sum(y**2)  # noise-free fits: E at rounding level

    def cond(c):
        return ~c["done"] & (c["it"] < max_iter)

    def body(c):
        theta = c["theta"]
        stable = hurwitz(jnp.concatenate([theta[:n], jnp.ones(1)])) & jnp.all(jnp.isfinite(theta))
        # an unstable A is never filtered (it would overflow): a stable stand-in, discarded
        E, new, G = step(jnp.where(stable, theta, theta.at[:n].set(guess)), y, u, delays)
        E = jnp.where(stable, E, jnp.inf)
        better = stable & (E < c["E_best"])
        pick = lambda now, old: jnp.where(better, now, old)  # noqa: E731
        best, E_best, G_best = pick(theta, c["best"]), pick(E, c["E_best"]), pick(G, c["G"])
        scale = jnp.maximum(jnp.abs(new), 1e-12 * jnp.max(jnp.abs(new)))
        change = jnp.max(jnp.abs(new - theta) / scale)
        finite = jnp.all(jnp.isfinite(new)) & ~jnp.isnan(E)
        status = c["status"]
        status = status | jnp.where(~stable, int(SrivcStatus.UNSTABLE_FILTER), 0)
        status = status | jnp.where(stable & ~finite, int(SrivcStatus.NONFINITE), 0)
        diverged = stable & finite & (E > DIVERGENCE_FACTOR * jnp.maximum(E_best, floor))
        status = status | jnp.where(diverged, int(SrivcStatus.DIVERGED), 0)
        failed = status != 0
        conv = ~failed & (change < tol)
        return dict(theta=jnp.where(failed, theta, new), best=best, E_best=E_best,
                    G=G_best, E_last=E, G_last=G, it=c["it"] + 1, status=status,
                    done=failed | conv, conv=conv)

    T, p = y.shape[0], theta0.shape[0]
    init = dict(theta=theta0, best=theta0, E_best=jnp.asarray(jnp.inf), G=jnp.zeros((p, p)),
                E_last=jnp.asarray(jnp.inf), G_last=jnp.zeros((p, p)), it=jnp.asarray(0),
                status=jnp.asarray(0), done=jnp.asarray(False), conv=jnp.asarray(False))
    c = jax.lax.while_loop(cond, body, init)
    status = c["status"] | jnp.where(~c["done"], int(SrivcStatus.MAX_ITER), 0)
    status = status | jnp.where(jnp.all(jnp.isfinite(y)) & jnp.all(jnp.isfinite(u)), 0,
                                int(SrivcStatus.NONFINITE))
    conv = c["conv"] & (status == 0)
    theta = jnp.where(conv, c["theta"], c["best"])
    E = jnp.where(conv, c["E_last"], c["E_best"])
    G = jnp.where(conv, c["G_last"], c["G"])  # Phi_hat^T Phi_hat
    sigma2 = E / max(T - p, 1)
    ch = jnp.sqrt(jnp.diagonal(G))
    ch = jnp.where(ch > 0, ch, 1.0)
    Rn = G / ch[:, None] / ch[None, :]
    inv = jax.vmap(lambda e: solve(Rn, e))(jnp.eye(p)) / ch[:, None] / ch[None, :]
    cov = jnp.where(jnp.isfinite(E), sigma2 * 0.5 * (inv + inv.T), jnp.nan)
    return theta, E * dt, sigma2, cov, c["it"], status


def _stable_guess(n):
    """a_0..a_{n-1} of (s + 1)^n: a stable stand-in so an unstable iterate is never filtered."""
    coeffs = np.polynomial.polynomial.polypow([1.0, 1.0], n)
    return jnp.asarray(coeffs[:n])


def _run(a0, b0, off0, y, u, delays, max_iter, tol, dt, n, m, modes, has_offset):
    """Start vector from the model, the iteration, and the outputs of `srivc` (one program)."""
    an = a0[n]
    theta0 = jnp.concatenate([a0[:n] / an] + [bk / an for bk in b0]
                             + ([jnp.reshape(off0 / an, (1,))] if has_offset else []))
    theta, E, sigma2, cov, it, status = _core(theta0, y, u, delays, max_iter, tol, n=n, m=m,
                                              modes=modes, has_offset=has_offset, dt=dt)
    a, bs, off = _split(theta, n, m, has_offset)
    model_status = jnp.where(hurwitz(a), 0, int(Status.UNSTABLE)).astype(jnp.int32)
    std = jnp.sqrt(jnp.diagonal(cov))
    nan = jnp.full((), jnp.nan)
    return (theta, a, tuple(bs), off, model_status, nan, std, cov, sigma2, E, it, status,
            status == 0)


@functools.cache
def _program(n, m, modes, has_offset):
    """The jitted SRIVC program of one structure. Under `jax.vmap` its rule maps the records one
    after another (`lax.map`) inside the one compiled call: each record stops at its own
    convergence and its filter scans stay in cache, where the batched while loop ran every
    record to the slowest one's iteration count with a 4x slower batched scan per record
    (measured: 50 records of 7500 samples, n = 4: 1.8 s batched, 0.43 s mapped)."""
    def run(*args):
        return _run(*args, n, m, modes, has_offset)

    fn = custom_vmap(run)

    @fn.def_vmap
    def _rule(axis_size, in_batched, *args):
        def full(x, batched):
            return x if batched else jnp.broadcast_to(x, (axis_size,) + jnp.shape(x))

        args = jax.tree.map(full, args, tuple(in_batched))
        out = jax.lax.map(lambda xs: fn(*xs), args)
        return out, jax.tree.map(lambda _: True, out)

    return array_jit(fn)


def srivc(signals: Signals, model: Model, *, max_iter: int = 30, tol: float = 1e-8) -> SrivcFit:
    r"""SRIVC estimate (module docstring) started from `model` (e.g. the MFM estimate).

    Orders, offset term and delays come from `model`; intersample rules and data from
    `signals`. Stops when the largest relative parameter change is below `tol`, or after
    `max_iter` IV solves, or when an iterate's $A(s)$ is unstable (the filter $1/A$ would blow
    up), the simulation error diverges (`DIVERGENCE_FACTOR` times the best), or values turn
    non-finite: then the best iterate by simulation error is returned (the start when there is
    none) with the reason in `status`, and a warning in eager mode. One jitted program per
    structure and record length: new data, starts, dt, `max_iter` and `tol` are values.
    Works under `jax.jit` and `jax.vmap` (over stacked `Signals` and `Model`s of equal shape).

    **Arguments:** `signals` (y (T,), u (T, K)), `model` (the start), `max_iter`, `tol`.

    **Returns:** `SrivcFit`; its `model` is a `Model` (a, b, offset, delays) whose `status`
    has `Status.UNSTABLE` when the returned A is not Hurwitz.
    """
    _b.require_x64("srivc")
    if not isinstance(signals, Signals):
        raise TypeError(f"srivc(): signals must be a Signals, got {type(signals).__name__}")
    if not isinstance(model, Model):
        raise TypeError(f"srivc(): model must be a Model (e.g. from identify), got "
                        f"{type(model).__name__}")
    K = signals.u.shape[-1]
    if model.n_inputs != K:
        raise ValueError(f"srivc(): the model has {model.n_inputs} inputs but the signals have "
                         f"K={K}; start from a model identified on these signals")
    if model.has_offset != signals.offset:
        raise ValueError(f"srivc(): model.has_offset={model.has_offset} but signals.offset="
                         f"{signals.offset}; identify the start on these signals")
    n, m = model.n, tuple(model.m)
    p = n + sum(mk + 1 for mk in m) + int(model.has_offset)
    T = signals.y.shape[-1]
    if T <= p:
        raise ValueError(f"srivc(): the record needs more samples than parameters (got T={T}, "
                         f"{p} parameters); use a longer record")
    traced = _b.is_traced(signals.y) or _b.is_traced(model.a) or _b.is_traced(max_iter)
    if not _b.is_traced(max_iter):
        max_iter = _b.integer("srivc", "max_iter", max_iter, lo=1, hi=MAX_ITER_LIMIT,
                              fix="give the largest number of IV solves")
    if not _b.is_traced(tol):
        tol = _b.number("srivc", "tol", tol, lo=0, lo_open=True,
                        fix="give a relative parameter change such as 1e-8")
    names = _names(n, m, model.has_offset)
    program = _program(n, m, tuple(signals.intersample), model.has_offset)
    (theta, a, bs, off, model_status, nan, std, cov, sigma2, E, it, status, converged) = program(
        model.a, tuple(model.b), model.offset, signals.y, signals.u, model.delays, max_iter,
        tol, signals.dt)
    new = Model(a=a, b=bs, offset=off, delays=model.delays, theta=theta, J=nan, J_rel=nan,
                cond=nan, status=model_status, mf=None, structure=model.structure,
                intersample=tuple(signals.intersample), has_offset=model.has_offset,
                output_name=signals.output_name, input_names=tuple(signals.input_names))
    fit = SrivcFit(new, model, theta, std, cov, sigma2, E, it, converged, status, names)
    if not traced and int(status) != 0:
        warnings.warn(f"srivc(): stopped without converging ({describe_srivc(int(status))}) "
                      f"after {int(it)} iterations; returned the best iterate by simulation "
                      "error. Check the start model and the data, or raise max_iter",
                      stacklevel=2)
    return fit
