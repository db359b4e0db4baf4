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
derivatives are those of the continuous response to $O(dt^2)$. Both get the same rule, so
regressors and instruments are built alike. The estimate does not hinge on the rule: an
audit (2026-11-28) found zoh and foh filtering of y and $\hat x$ give estimates equal to
1e-14 relative (the difference of the filtered $\hat x$ lies in the instruments' span), and
at $\hat A = A$,
$\sum_i a_i (s^i/A)\,y_{int} = y_{int}$ for any interpolant, which equals $y$ at every sample,
so on noise-free data the true parameters are an exact fixed point whatever dt (the tests
check recovery to rounding), and under noise the equation error at the samples is the noise.
Filters start from rest at the first sample; inputs before the first sample are held at its
value (as in `simulate`).

The sample recursion is a `lax.scan` with the small matrix product written elementwise:
measured on 7000 samples, n = 4, 5 signals, 0.6 ms per pass, against 0.9-3 ms for a chunked
scan (64-sample chunks, chunk starts by a short scan) and 14 ms for `lax.associative_scan`.
Two passes per iteration (the signals, then $\hat x$): one cascaded scan forming $\hat x$
inside the loop was 4-6x slower (its reductions do not fuse). Around the scans, a pass
builds its regressors straight from the filter states (no (T, n + 1, S) array of every
derivative) and scales the IV system after its products: 0.66-0.70 ms against
0.81-0.87 ms per pass (7500 samples, n = 4), and `jax.vmap(srivc)` over 100 records
0.37 against 0.55-0.56 s. benchmarks/noise_montecarlo.py times whole fits against the
NumPy/SciPy peer.
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
from . import _padded as padded
from ._batch import as_records, map_pairs
from ._jit import array_jit
from ._linalg import hurwitz, small_matmul, solve
from ._model import Model
from ._pytree import replace_fields
from ._quadrature import delayed_samples, edge_padded, record_bucket, shift_samples, split_delay
from ._signals import Signals, start_and_error
from ._simulate import step_terms
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
    NO_EXCITATION = 16  # a regressor is zero over the record (an input zero throughout)


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

    def summary(self) -> str:
        """Parameters with standard errors, E, and the iteration's verdict (a fit that did not
        converge printed "status ok" through `model.summary()`, the model's own bits)."""
        if np.ndim(self.theta) != 1:
            raise ValueError("SrivcFit.summary(): one fit at a time; this holds a batch (from "
                             "jax.vmap): take one with jax.tree.map(lambda x: x[i], fit)")
        lines = [f"SRIVC fit  n={self.model.n}  m={list(self.model.m)}",
                 f"{'parameter':<12}{'value':>16}{'std error':>14}"]
        for name, v, e in zip(self.names, np.asarray(self.theta), np.asarray(self.std_errors)):
            lines.append(f"{name:<12}{v:>16.6e}{e:>14.3e}")
        lines.append(f"E: {float(self.E):.6e}  sigma2: {float(self.sigma2):.6e}")
        if int(self.model.status) & Status.UNSTABLE:
            lines.append("UNSTABLE: the returned A(s) has a root with Re >= 0 (see the model's "
                         "status): validate it before use")
        its = int(self.iterations)
        lines.append(f"converged after {its} iterations" if bool(self.converged) else
                     f"NOT CONVERGED ({self.describe()} after {its} iterations): the estimate "
                     "is the best iterate by simulation error and its standard errors are not "
                     "those of a converged fit; check the start model and the data, or raise "
                     "max_iter")
        return "\n".join(lines)


def _names(n, m, has_offset):
    names = [f"a_{i}" for i in range(n)]
    for k, mk in enumerate(m):
        names += [f"b_{k + 1}{j}" for j in range(mk + 1)]
    return tuple(names + (["offset"] if has_offset else []))


def _filter(Phi, drive):
    """States z_j (T, n, S) of z_{j+1} = Phi z_j + drive_j from z_0 = 0."""
    def step(z, d):
        return small_matmul(Phi, z) + d, z

    return jax.lax.scan(step, jnp.zeros(drive.shape[1:]), drive)[1]


def _companion(a, n):
    """Controllable canonical A_c of 1/A(s) (a_n = 1): state = (w, w', .., w^(n-1)), zero-padded
    to order n_max = len(a) - 1 (the states beyond n stay at rest: nothing drives them)."""
    i = jnp.arange(a.shape[0] - 1)
    A = jnp.where((i[None, :] == i[:, None] + 1) & (i[:, None] < n - 1), 1.0, 0.0)
    return jnp.where((i[:, None] == n - 1) & (i[None, :] < n), -a[:-1][None, :], A)


def _terms(Ac, n, modes, taus, dt):
    r"""Phi (n, n) and per column the step terms (S, 3, n) of
    $z_{j+1} = \Phi z_j + P x_{j-d-1} + Q x_{j-d} + R x_{j-d+1}$ (delay (d + f) dt): the
    columns enter the filter's last state, B = e_n (`step_terms`, as in `simulate`)."""
    S = len(modes)
    d, f = split_delay(taus, dt)
    e_n = (jnp.arange(Ac.shape[0]) == n - 1).astype(jnp.float64)
    Phi, terms = step_terms(Ac, jnp.tile(e_n[:, None], (1, S)), modes, [f[s] for s in range(S)],
                            dt)
    return Phi, d, jnp.stack([jnp.stack(t) for t in terms])


def _states(X, d, PQR, a, n, taus, dt, modes, Phi):
    """Filter states z (T, n_max, S) (derivatives 0..n-1, zero beyond) of the columns X (T, S)
    from their step terms, and their n-th filtered derivative top (T, S). The drive of every
    column is three products with its shifted samples, one fused loop (a (T, 3) @ (3, n) dot
    per column and their stack took about a sixth of the pass in a profile)."""
    N = a.shape[0] - 1
    cols = range(X.shape[1])
    drive = []
    for s in cols:  # P x_{j-d-1} + Q x_{j-d} + R x_{j-d+1}
        x = [shift_samples(X[:, s], d[s] + 1 - i) for i in range(3)]
        drive.append(sum(x[i][:, None] * PQR[s, i][None, :] for i in range(3)))
    z = _filter(Phi, jnp.stack(drive, axis=-1))
    vals = jnp.stack([delayed_samples(X[:, s], taus[s], dt, modes[s]) for s in cols], axis=-1)
    am = jnp.where(jnp.arange(N) < n, a[:N], 0.0)
    return z, vals - sum(am[i] * z[:, i, :] for i in range(N))


def _derivatives(z, top, n, count: int):
    """Filtered derivatives 0..count-1 (T, count) of one column from its states z (T, n_max)
    and n-th derivative top (T,): orders below n from z, order n from top, zero beyond n."""
    T, N = z.shape
    z = jnp.concatenate([z, jnp.zeros((T, max(count - N, 0)))], axis=1)[:, :count]
    j = jnp.arange(count)
    return jnp.where(j < n, z, jnp.where(j == n, top[:, None], 0.0))


def _step(theta, c, free, y, u, valid, *, modes, has_offset, dt):
    """One SRIVC pass at padded theta: (simulation error sum, next theta, Phi_hat^T Phi_hat);
    the entries outside `free` are zero columns with a unit diagonal in the IV system, so they
    stay zero and the free ones are those of the unpadded system. Only the first `valid`
    samples count (a record padded to its bucket: the filters are causal, so the samples
    before `valid` never see the padding)."""
    T, K, n, delays = y.shape[0], u.shape[1], c["n"], c["delays"]
    rows = (jnp.arange(T) < valid)[:, None]
    a, b, off = padded.split(theta, c, has_offset)
    N = a.shape[0] - 1
    Ac = _companion(a, n)
    # y first (foh, no delay; module docstring), then the inputs, then the constant
    X = [y] + [u[:, k] for k in range(K)] + ([jnp.ones(T)] if has_offset else [])
    cmodes = ("foh",) + tuple(modes) + (("zoh",) if has_offset else ())
    taus = jnp.concatenate([jnp.zeros(1), delays] + ([jnp.zeros(1)] if has_offset else []))
    Phi_d, d, PQR = _terms(Ac, n, cmodes, taus, dt)
    z, top = _states(jnp.stack(X, 1), d, PQR, a, n, taus, dt, cmodes, Phi_d)
    uf = [_derivatives(z[:, :, 1 + k], top[:, 1 + k], n, b.shape[1]) for k in range(K)]
    of = [_derivatives(z[:, :, -1], top[:, -1], n, 1)] if has_offset else []
    xhat = sum(uf[k] @ b[k] for k in range(K)) + (of[0][:, 0] * off if has_offset else 0.0)
    zx = _states(xhat[:, None], d[:1], PQR[:1], a, n, taus[:1], dt, ("foh",), Phi_d)[0]
    below = jnp.arange(N) < n
    Phi = jnp.where(free & rows, jnp.concatenate(
        [-jnp.where(below, z[:, :, 0], 0.0)] + uf + of, axis=1), 0.0)
    Phih = jnp.where(free & rows, jnp.concatenate(
        [-jnp.where(below, zx[:, :, 0], 0.0)] + uf + of, axis=1), 0.0)
    target = jnp.where(rows[:, 0], top[:, 0], 0.0)  # y's n-th filtered derivative
    G = Phih.T @ Phih
    cs = jnp.sqrt(jnp.sum(Phi**2, axis=0))
    ch = jnp.sqrt(jnp.diagonal(G))
    cs, ch = jnp.where(cs > 0, cs, 1.0), jnp.where(ch > 0, ch, 1.0)
    # equilibrated IV system (columns scaled to unit norm), scaled after the products
    R = (Phih.T @ Phi) / ch[:, None] / cs[None, :] + jnp.diag(jnp.where(free, 0.0, 1.0))
    new = solve(R, (Phih.T @ target) / ch) / cs
    E = jnp.sum(jnp.where(rows[:, 0], (y - xhat) ** 2, 0.0))
    return E, new, G


def _core(c, y, u, valid, max_iter, tol, *, modes, has_offset, dt):
    """The jitted iteration (see `srivc`); one traced SRIVC pass inside a while loop.

    E, sigma2 and the covariance belong to the last evaluated iterate: the returned one, or,
    when converged, the one before it (within `tol`)."""
    step = jax.tree_util.Partial(_step, modes=modes, has_offset=has_offset, dt=dt)
    N, n = c["a"].shape[0] - 1, c["n"]
    free, theta0 = padded.free(c, has_offset), padded.theta(c, has_offset)
    guess = jnp.asarray(_stable_guesses(N))[n]
    floor = ROUNDING_FLOOR * jnp.sum(jnp.where(jnp.arange(y.shape[0]) < valid, y**2, 0.0))

    def cond(s):
        return ~s["done"] & (s["it"] < max_iter)

    def body(s):
        theta = s["theta"]
        stable = hurwitz(padded.split(theta, c, has_offset)[0]) & jnp.all(jnp.isfinite(theta))
        # an unstable A is never filtered (it would overflow): a stable stand-in, discarded
        E, new, G = step(jnp.where(stable, theta, theta.at[:N].set(guess)), c, free, y, u,
                         valid)
        E = jnp.where(stable, E, jnp.inf)
        better = stable & (E < s["E_best"])
        pick = lambda now, old: jnp.where(better, now, old)  # noqa: E731
        best, E_best, G_best = pick(theta, s["best"]), pick(E, s["E_best"]), pick(G, s["G"])
        scale = jnp.maximum(jnp.abs(new), 1e-12 * jnp.max(jnp.abs(new)))
        change = jnp.max(jnp.where(free, jnp.abs(new - theta) / scale, 0.0))
        finite = jnp.all(jnp.isfinite(new)) & ~jnp.isnan(E)
        dead = jnp.any(free & (jnp.diagonal(G) == 0))  # a zero column: the IV system singular
        status = s["status"]
        status = status | jnp.where(~stable, int(SrivcStatus.UNSTABLE_FILTER), 0)
        status = status | jnp.where(stable & dead, int(SrivcStatus.NO_EXCITATION), 0)
        status = status | jnp.where(stable & ~dead & ~finite, int(SrivcStatus.NONFINITE), 0)
        diverged = stable & finite & (E > DIVERGENCE_FACTOR * jnp.maximum(E_best, floor))
        status = status | jnp.where(diverged, int(SrivcStatus.DIVERGED), 0)
        failed = status != 0
        conv = ~failed & (change < tol)
        return dict(theta=jnp.where(failed, theta, new), best=best, E_best=E_best,
                    G=G_best, E_last=E, G_last=G, it=s["it"] + 1, status=status,
                    done=failed | conv, conv=conv)

    p = theta0.shape[0]
    init = dict(theta=theta0, best=theta0, E_best=jnp.asarray(jnp.inf), G=jnp.zeros((p, p)),
                E_last=jnp.asarray(jnp.inf), G_last=jnp.zeros((p, p)), it=jnp.asarray(0),
                status=jnp.asarray(0), done=jnp.asarray(False), conv=jnp.asarray(False))
    s = jax.lax.while_loop(cond, body, init)
    status = s["status"] | jnp.where(~s["done"], int(SrivcStatus.MAX_ITER), 0)
    status = status | jnp.where(jnp.all(jnp.isfinite(y)) & jnp.all(jnp.isfinite(u)), 0,
                                int(SrivcStatus.NONFINITE))
    conv = s["conv"] & (status == 0)
    theta = jnp.where(conv, s["theta"], s["best"])
    E = jnp.where(conv, s["E_last"], s["E_best"])
    G = jnp.where(conv, s["G_last"], s["G"])  # Phi_hat^T Phi_hat (zero outside `free`)
    sigma2 = E / jnp.maximum(valid - jnp.sum(free), 1)
    ch = jnp.sqrt(jnp.diagonal(G))
    ch = jnp.where(ch > 0, ch, 1.0)
    Rn = G / ch[:, None] / ch[None, :] + jnp.diag(jnp.where(free, 0.0, 1.0))
    inv = jax.vmap(lambda e: solve(Rn, e))(jnp.eye(p)) / ch[:, None] / ch[None, :]
    cov = jnp.where(jnp.isfinite(E) & free[:, None] & free[None, :],
                    sigma2 * 0.5 * (inv + inv.T), jnp.where(jnp.isfinite(E), 0.0, jnp.nan))
    return theta, E * dt, sigma2, cov, s["it"], status


def _stable_guesses(n_max):
    """Row n: a_0..a_{n-1} of (s + 1)^n, zero-padded to n_max: a stable stand-in so that an
    unstable iterate is never filtered."""
    out = np.zeros((n_max + 1, n_max))
    for n in range(1, n_max + 1):
        out[n, :n] = np.polynomial.polynomial.polypow([1.0, 1.0], n)[:n]
    return out



def _run(c, y, u, valid, max_iter, tol, dt, modes, has_offset):
    """The iteration from the padded start `c` and the padded outputs of `srivc` (one program
    per padded shape, inputs, rules and record bucket)."""
    theta, E, sigma2, cov, it, status = _core(c, y, u, valid, max_iter, tol, modes=modes,
                                              has_offset=has_offset, dt=dt)
    a = padded.split(theta, c, has_offset)[0]
    model_status = jnp.where(hurwitz(a), 0, int(Status.UNSTABLE))
    # NaN or inf data (possible under jit/vmap): the model says so too (it read ok)
    finite = jnp.all(jnp.isfinite(y)) & jnp.all(jnp.isfinite(u))
    model_status = (model_status | jnp.where(finite, 0, int(Status.NONFINITE))).astype(jnp.int32)
    return dict(theta=theta, model_status=model_status, std=jnp.sqrt(jnp.diagonal(cov)),
                cov=cov, sigma2=sigma2, E=E, it=it, status=status)


@functools.cache
def _program(modes, has_offset):
    """The jitted SRIVC program (one per padded order, inputs and record bucket: every
    structure of one padded order shares it). Under `jax.vmap` its rule maps the records one
    after another (`lax.map`) inside the one compiled call: each record stops at its own
    convergence and its filter scans stay in cache, where the batched while loop ran every
    record to the slowest one's iteration count with a 4x slower batched scan per record
    (measured: 50 records of 7500 samples, n = 4: 1.8 s batched, 0.43 s mapped)."""
    def run(c, y, u, valid, max_iter, tol, dt):
        return _run(c, y, u, valid, max_iter, tol, dt, modes, has_offset)

    fn = custom_vmap(run)

    @fn.def_vmap
    def _rule(axis_size, in_batched, *args):
        def full(x, batched):
            return x if batched else jnp.broadcast_to(x, (axis_size,) + jnp.shape(x))

        args = jax.tree.map(full, args, tuple(in_batched))
        out = jax.lax.map(lambda xs: fn(*xs), args)
        return out, jax.tree.map(lambda _: True, out)

    return array_jit(fn)


def padded_fit(signals: Signals, c: dict, *, max_iter: int, tol: float,
               n_samples=None) -> dict:
    """The padded outputs of SRIVC from the padded start `c` (`padded_model`) on `signals`
    (checked by the caller): one program for every structure of `c`'s padded order. A
    concrete record is padded to its `record_bucket` (repeating the last sample; only its own
    samples count), so records of every length in a bucket share the program; `n_samples`:
    the record's own length when `signals` come padded (`_batch.map_pairs`)."""
    y, u, T = signals.y, signals.u, signals.y.shape[-1]
    if n_samples is None and not (_b.is_traced(y) or _b.is_traced(u)):
        y, u = (edge_padded(np.asarray(x), record_bucket(T) - T) for x in (y, u))
    valid = np.int32(T) if n_samples is None else n_samples
    # one type for the settings, whoever calls: a Python int is a weak int64 to `jax.jit`,
    # the batched stages' np.int32 another program
    max_iter = max_iter if _b.is_traced(max_iter) else np.int32(max_iter)
    tol = tol if _b.is_traced(tol) else np.float64(tol)
    return _program(tuple(signals.intersample), signals.offset)(
        c, y, u, valid, max_iter, tol, signals.dt)


def _fit(signals: Signals, model: Model, out: dict, shape: tuple[int, int]) -> SrivcFit:
    """`SrivcFit` of structure `model.structure` from the padded outputs of `padded_fit`
    (padded shape (n_max, w); sliced on the host when concrete: no program per shape)."""
    n, m, off = model.n, tuple(model.m), model.has_offset
    traced = _b.is_traced(out["theta"])
    xp = jnp if traced else np
    if not traced:
        out = jax.device_get(out)
    idx = padded.indices(model, *shape)
    theta = out["theta"][..., idx]
    cov = out["cov"][..., idx[:, None], idx[None, :]]
    pos, bs = n, []
    for mk in m:
        bs.append(theta[pos : pos + mk + 1])
        pos += mk + 1
    nan = xp.float64(np.nan)
    new = Model(a=xp.concatenate([theta[:n], xp.ones(1)]), b=tuple(bs),
                offset=theta[pos] if off else xp.zeros(()), delays=model.delays, theta=theta,
                J=nan, J_rel=nan, cond=nan, status=out["model_status"], mf=None,
                structure=model.structure, intersample=tuple(signals.intersample),
                has_offset=off, output_name=signals.output_name,
                input_names=tuple(signals.input_names))
    fit = SrivcFit(new, model, theta, out["std"][..., idx], cov,
                   out["sigma2"], out["E"], out["it"], out["status"] == 0, out["status"],
                   _names(n, m, off))
    return fit  # concrete: NumPy arrays, as `OutputErrorFit` (a put back cost 1 ms a fit)


def srivc(signals, model, *, max_iter: int = 30, tol: float = 1e-8):
    r"""SRIVC estimate (module docstring) started from `model` (e.g. the MFM estimate).

    Orders, offset term and delays come from `model`; intersample rules and data from
    `signals`. Stops when the largest relative parameter change is below `tol`, or after
    `max_iter` IV solves, or when an iterate's $A(s)$ is unstable (the filter $1/A$ would blow
    up), the simulation error diverges (`DIVERGENCE_FACTOR` times the best), or values turn
    non-finite: then the best iterate by simulation error is returned (the start when there is
    none) with the reason in `status`, and a warning in eager mode. One jitted program per
    order n, largest numerator order, inputs, rules and record bucket (the m_k are values:
    `padded_model`): new data, starts, dt, `max_iter` and `tol` are values too.
    Works under `jax.jit` and `jax.vmap` (over stacked `Signals` and `Model`s of equal shape).

    In eager mode it warns where the signals' intersample rules differ from the start's (the
    signals' are used), where the record does not start at rest (the output's first samples
    away from the fit's response from rest, an input at a level), and where the residuals from
    rest are not white (Box-Pierce, 1 %): the covariance assumes white noise, and under AR(1)
    noise of pole 0.95 the standard errors were 2.1-2.8x too small (`estimate` says the same
    in its notes).

    The filters start from rest at the first sample, on the data as given. A record with an
    offset term whose plant is at rest away from zero there (a heater switched on at the
    first sample from an ambient level) leaves a start-up transient: on such a record the
    standard errors came out 4.9x output error's. `estimate` shifts such records by their
    starting levels first (1.15x there); do the same (`y - y[0]`, `u - u[0]`, the offset
    mapped back: $b_{off} = b_{off}' - \sum_k b_{k0} u_k[0] + a_0 y[0]$) when calling this
    directly.

    **A batch of records** (Monte Carlo realisations, repeated experiments): `signals` a list of
    `Signals` of one layout and `model` one start or a list of them (one per record). Chunks of
    records with one structure run in one compiled call each, on a thread per core
    (`map_pairs`); one warning says how many fits did not converge. Eager only (under `jit`,
    `vmap` the single-record call).

    **Arguments:** `signals` (y (T,), u (T, K), or a list), `model` (the start, or a list),
    `max_iter`, `tol`.

    **Returns:** `SrivcFit` (a list of them for a list of records); its `model` is a `Model`
    (a, b, offset, delays) whose `status` has `Status.UNSTABLE` when the returned A is not
    Hurwitz.
    """
    if not isinstance(signals, Signals):
        return _srivc_batch(signals, model, max_iter, tol)
    max_iter, tol = _checked(signals, model, max_iter, tol)
    _b.start_notes("srivc", model, signals)
    traced = _b.is_traced(signals.y) or _b.is_traced(model.a) or _b.is_traced(max_iter)
    # padded to (n, largest m_k): each padded coefficient costs a step of the elimination in
    # every IV solve (p = 11 against 7 for n = 3, m = (1, 1): 8.6 against 6.1 ms per fit)
    w = max(model.m, default=0) + 1
    c = padded.padded_model(model, model.n, w - 1)
    fit = _fit(signals, model, padded_fit(signals, c, max_iter=max_iter, tol=tol), (model.n, w))
    away, white = ("", None) if traced else _start_and_noise(
        signals, fit.model if int(fit.status) == 0 else None)
    at_rest = not away
    if away and int(fit.status) == 0:  # converged, and maybe to a wrong model: an input at a
        # level of 100 (the output at rest) gave a = [5.8, 7.6, 1] for [2, 3, 1], status ok
        warnings.warn(f"srivc(): the filters start from rest at the first sample, and the "
                      f"signals do not ({away}): the start-up transient biases the fit, "
                      "converged or not; shift the record by its first samples (y - y[0], "
                      "u - u[0], as estimate does; see srivc's docstring)", stacklevel=2)
    if white is False and at_rest and int(fit.status) == 0:
        warnings.warn(f"srivc(): {_COLOURED}", stacklevel=2)
    if not traced and int(fit.status) != 0:
        zero = [name for name, uk in zip(signals.input_names, np.asarray(signals.u).T)
                if not np.any(uk)]
        dead = int(fit.status) & SrivcStatus.NO_EXCITATION
        warnings.warn(f"srivc(): stopped without converging ({describe_srivc(int(fit.status))})"
                      f" after {int(fit.iterations)} iterations; returned the best iterate by "
                      "simulation error. "
                      + (f"Input(s) {', '.join(map(repr, zero))} are zero over the whole "
                         "record: their coefficients cannot be estimated; drop them from the "
                         "signals and the start model" if dead and zero else
                         "A regressor is zero over the record (an output that is zero, or an "
                         "input delayed past the record's end): check the data and the delays"
                         if dead else
                         "Check the start model and the data, or raise max_iter")
                      + ("" if at_rest else
                         f"; the filters start from rest at the first sample, and the signals "
                         f"do not ({away}): shift the record by its first samples (y - y[0], "
                         "u - u[0], as estimate does; see srivc's docstring)"), stacklevel=2)
    return fit


_COLOURED = ("the residuals are not white (Box-Pierce on the simulation from rest, 1 % level): "
             "coloured noise, or dynamics the model misses; the standard errors assume white "
             "noise and are then too small (see residuals(model, signals); estimate says the "
             "same in its notes)")


def _start_and_noise(signals: Signals, model: Model | None) -> tuple[str, bool | None]:
    """(the signals that start away from rest, as "y starts at 96.9 (range 3.1), ..." or '',
    whether `model`'s residuals from rest are white (Box-Pierce, 1 %; None: undefined)).

    Away from rest: the output's first samples (mean of 10) more than 0.1 of its range from
    `model`'s response from rest over them (the fit's, its offset term a constant input from
    rest as in `simulate`), an input's more than its whole range (an operating level: an
    input that opens at a value of its own range is an experiment from rest, as a step at the
    first sample; a constant input is no level). The output was compared with zero: a record
    at rest whose input steps at the first sample rose within those 10 samples and was called
    not at rest on 22 of 30 PRBS records (an audit of 2026-11-28), with advice that broke the
    fit. Not white: the standard errors, which assume white noise, are too small (2.1-2.8x
    under AR(1) noise of pole 0.95 in that audit, status ok, unsaid). `model` None (a fit that
    did not converge: its best iterate can be far off, and its response from rest said "not
    at rest" of 3 of 6 records at rest in a review): the output's start against zero, read
    from the line through its first samples (`output_start`, which a step at the first sample
    barely moves) and beyond 3 of that line's standard errors (y[0] alone: one noise sample
    said "not at rest" of 3 of 30 records at rest at 10 dB, an audit of 2026-11-28); no
    whiteness."""
    from ._analysis import RESIDUAL_LAGS, whiteness
    from ._simulate import simulate

    y, u = np.asarray(signals.y), np.asarray(signals.u).reshape(signals.n_samples, -1)
    sim = None
    if model is not None:
        try:  # the model's own response from rest (its delays and offset, the signals' rules)
            rest = replace_fields(model, intersample=signals.intersample)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                sim = np.asarray(simulate(rest, u, dt=signals.host_dt))
        except ValueError:  # it overflows (an unstable model): the first sample, as for None
            pass
    if sim is not None:
        start = (f"{signals.output_name} starts {{:.4g}} away from the model's response from "
                 "rest", y[:10] - sim[:10], 0.0)
    else:  # the start read from the first samples' line, beyond 3 of its standard errors
        level, se = start_and_error(y)  # (y[0] alone: one 10 dB noise sample said "not at
        start = (f"{signals.output_name} starts at {{:.4g}}", [level], 3 * se)  # rest")
    cols = [(*start, np.ptp(y), 0.1)] + [
        (f"{name} starts at {{:.4g}}", uk[:10], 0.0, np.ptp(uk), 1.0)
        for name, uk in zip(signals.input_names, u.T)]
    out = []
    for text, x, margin, span, share in cols:
        x0 = float(np.mean(x))
        if span > 0 and abs(x0) > max(share * span, margin):
            out.append(text.format(x0) + f" (range {float(span):.3g})")
    white = None
    lags = min(RESIDUAL_LAGS, y.size // 4)
    if sim is not None and lags >= 5:
        e = y - sim
        white = whiteness(e, lags, y=y)[-1]
    return ", ".join(out), white


def _checked(signals: Signals, model: Model, max_iter, tol):
    """`srivc`'s argument checks (ValueError / TypeError naming the fix); max_iter and tol
    as numbers (or as given when traced)."""
    _b.require_x64("srivc")
    if not isinstance(signals, Signals):
        raise TypeError(f"srivc(): signals must be a Signals, got {type(signals).__name__}"
                        f"{_b.swap_hint('srivc', signals)}")
    if not isinstance(model, Model):
        raise TypeError(f"srivc(): model must be a Model (e.g. from identify), got "
                        f"{type(model).__name__}{_b.swap_hint('srivc', model)}")
    K = signals.u.shape[-1]
    if K == 0:
        raise ValueError("srivc(): the signals have no input; SRIVC's instruments are the "
                         "filtered inputs, so a model without inputs (an autonomous response) "
                         "is fitted by output_error instead")
    _b.start_layout("srivc", model, signals)
    n, m = model.n, tuple(model.m)
    p = n + sum(mk + 1 for mk in m) + int(model.has_offset)
    T = signals.y.shape[-1]
    if T <= p:
        raise ValueError(f"srivc(): the record needs more samples than parameters (got T={T}, "
                         f"{p} parameters); use a longer record")
    if not _b.is_traced(max_iter):
        max_iter = _b.integer("srivc", "max_iter", max_iter, lo=1, hi=MAX_ITER_LIMIT,
                              fix="give the largest number of IV solves")
    if not _b.is_traced(tol):
        tol = _b.number("srivc", "tol", tol, lo=0, lo_open=True, hi=1, hi_open=True,
                        fix="give a relative parameter change such as 1e-8 (tol=2 stopped at "
                            "the second iterate, 'converged')")
    return max_iter, tol


def srivc_many(records, models, *, n_max: int | None = None, max_iter: int = 30,
               tol: float = 1e-8, bucket: int | None = None) -> list:
    """`srivc(records[i], models[i])` for every pair (`Signals` of one layout), each chunk of
    pairs of one padded shape in one compiled call (`map_pairs`). `n_max`: every structure
    zero-padded to order `n_max` (`padded_model`: one program whatever the structures); None:
    each to its own order and largest numerator order, as `srivc` pads one. No warnings: the
    caller reads `status`. An entry is None where `srivc` would raise ValueError. `bucket`:
    the records' padded length (`map_pairs`)."""
    starts, live, shapes = [], [], []
    for i, (signals, model) in enumerate(zip(records, models)):
        try:
            _checked(signals, model, max_iter, tol)
        except ValueError:
            continue
        n, w = (model.n, max(model.m, default=0) + 1) if n_max is None else (n_max, n_max + 1)
        starts.append(padded.padded_model(model, n, w - 1))
        live.append(i)
        shapes.append((n, w))
    outs = map_pairs(padded_fit, [records[i] for i in live], starts, device=False,
                     bucket=bucket, max_iter=np.int32(max_iter), tol=np.float64(tol))  # values
    fits = [None] * len(models)
    for i, out, shape in zip(live, outs, shapes):
        fits[i] = None if out is None else _fit(records[i], models[i], out, shape)
    return fits


def _srivc_batch(signals, model, max_iter, tol) -> list:
    """`srivc` on a list of records (its docstring): checked like one record each."""
    records, _ = as_records("srivc", signals)
    models = list(model) if isinstance(model, list | tuple) else [model] * len(records)
    if len(models) != len(records):
        raise ValueError(f"srivc(): {len(records)} records but {len(models)} start models; give "
                         "one model for all records or one per record")
    for r, m in zip(records, models):
        max_iter, tol = _checked(r, m, max_iter, tol)
        if _b.is_traced(r.y) or _b.is_traced(m.a):
            raise TypeError("srivc(): a list of records is eager only; under jax.jit, "
                            "jax.vmap the single-record call over stacked Signals and Models")
    for r, m in zip(records, models):  # as one record's call (a repeated text shows once)
        _b.start_notes("srivc", m, r)
    fits = srivc_many(records, models, max_iter=max_iter, tol=tol)
    # the records that start away from rest (one record's call warns of each; the batch said
    # nothing, and a level of 100 at rest fitted a = [5.8, 7.6, 1] for [2, 3, 1], status ok)
    checked = [_start_and_noise(r, f.model if f is not None and int(f.status) == 0 else None)
               for r, f in zip(records, fits)]
    away = [(i, text) for i, (text, _) in enumerate(checked) if text]
    coloured = [i for i, ((text, white), f) in enumerate(zip(checked, fits))
                if white is False and not text and f is not None and int(f.status) == 0]
    if coloured:
        warnings.warn(f"srivc(): {len(coloured)} of {len(records)} fits (records "
                      f"{coloured[:10]}{'...' if len(coloured) > 10 else ''}): {_COLOURED}",
                      stacklevel=3)
    if away:
        warnings.warn(f"srivc(): {len(away)} of {len(records)} records do not start at rest "
                      f"(records {[i for i, _ in away][:10]}{'...' if len(away) > 10 else ''}; "
                      f"record {away[0][0]}: {away[0][1]}): the filters start from rest at the "
                      "first sample, and the start-up transient biases those fits, converged "
                      "or not; shift each record by its first samples (y - y[0], u - u[0], as "
                      "estimate does; see srivc's docstring)", stacklevel=3)
    bad = [i for i, f in enumerate(fits) if f is None or int(f.status) != 0]
    if bad:
        warnings.warn(f"srivc(): {len(bad)} of {len(fits)} fits stopped without converging "
                      f"(records {bad[:10]}{'...' if len(bad) > 10 else ''}); each returned the "
                      "best iterate by simulation error, with the reason in its status (None: "
                      "the fit could not run)", stacklevel=3)
    return fits
