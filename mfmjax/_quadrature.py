r"""Exact convolution weights of the modulated signals (paper eq. 3-4) for sampled data.

For a signal $x$ sampled at $t_k = t_0 + k\,dt$ and a delay $\tau \ge 0$,

$$\int_0^h x(t_k - \tau - s)\,\phi^{(i)}(s)\,ds
  = h^{N+M-i+1} \sum_{l=0}^{L-1} w_l\, x_{k-l},\qquad
  w_l = \frac1h \int_\tau^{\tau+h} \beta_l(s')\, p_i\!\left(\frac{s'-\tau}{h}\right) ds',$$

where $\beta_l$ is the cardinal function of sample $x_{k-l}$ in the interpolant of the samples
(in the lag variable $s' = t_k - t$). The interpolants ("rules") are

- `"zoh"`: piecewise constant, $x(t) = x_j$ on $[t_j, t_{j+1})$ (digital-controller input);
- `"foh"`: piecewise linear between samples;
- `"cubic"`: piecewise cubic Lagrange through the four nearest samples of each cell (one-sided
  at the ends of the support, never outside $[0, \lceil(\tau+h)/dt\rceil]$), O(dt^4) for smooth
  signals: the rule for the output and for signals marked smooth.

Every cell integral is a polynomial of degree $\le N+M+3$ integrated by a 12-point Gauss-Legendre
rule, which is exact for degree $\le 23$: the weights are exact up to rounding. A delay
that is not a multiple of dt shifts the kernel inside the cells, so the same interpolant is used.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from ._boundary import is_traced, require_x64
from ._modulating import ModulatingFunction, derivative_order, phi_scaled

RULES = ("zoh", "foh", "cubic")
_GAUSS_X, _GAUSS_W = np.polynomial.legendre.leggauss(12)
EDGE = 1e-9  # tolerance (in samples) on ceil((tau + h)/dt) and whole-sample delays against rounding


def support_samples(span, dt: float):
    r"""Index of the oldest sample the kernel touches: $\lceil (\tau + h)/dt \rceil$ (int array)."""
    return jnp.ceil(jnp.asarray(span) / dt - EDGE).astype(jnp.int32)


def kernel_length(span_max: float, dt: float) -> int:
    """Static kernel length for supports up to `span_max` = max(tau + h)."""
    return int(math.ceil(span_max / dt - EDGE)) + 1


MIN_KERNEL_BUCKET = 16  # shortest compiled kernel length


def kernel_bucket(length: int) -> int:
    """Compiled kernel length for a needed `length`: the next of 16, 24, 32, 48, 64, 96, ...

    Weights beyond a kernel's support are exactly zero, so a longer kernel changes results by
    rounding only; bucketing lets every setting (h, delays) whose support fits reuse one program,
    at most 1.5x the work of the exact length.
    """
    b = MIN_KERNEL_BUCKET
    while b < length:
        b = b * 3 // 2 if (b & (b - 1)) == 0 else b * 4 // 3
    return b


def record_bucket(n_samples: int) -> int:
    """Compiled record length for `n_samples`: the next of 4, 5, 6, 7 or 8 times a power of two
    (at most 1.25x the samples; records up to 64 samples keep their length). A search pads its
    record to it and masks the padding exactly, so records of every length in a bucket share
    one program."""
    if n_samples <= 64:
        return n_samples
    k = (n_samples - 1).bit_length() - 3
    return next(m << k for m in (4, 5, 6, 7, 8) if m << k >= n_samples)


SHARE_STEPS = 48  # a window's share of its record rounded up to k / 48 (`window_bucket`)


def window_bucket(length: int, n_samples: int) -> int:
    """Compiled length of a window of `length` samples of an `n_samples` record that is a
    share of it (a hold-out block of round(s T) samples, a fit part of the rest): the share
    (length - 1) / n_samples rounded up to k / SHARE_STEPS, times the record's bucket R, to
    its `record_bucket` (at least the window, at least 64, at most R). The sample taken off
    covers the +-0.5 by which a share's length rounds, so a share s gets k / 48 >= s for
    every record length of a record bucket, and one program (a share's own bucket crossed an
    edge inside it: 1290 samples after 1500 compiled 9 programs again; 1/3 and 2/3 of 1536
    are 512 and 1024, edges themselves). A buffer holds at most 1/48 of R more than the
    largest window of the share in the bucket, then up to 1.25x by `record_bucket`; the
    whole record gets R."""
    R = record_bucket(n_samples)
    steps = -(-max(length - 1, 0) * SHARE_STEPS // n_samples)
    return min(record_bucket(max(-(-steps * R // SHARE_STEPS), length, 64)), R)


def edge_padded(x: np.ndarray, pad: int) -> np.ndarray:
    """`x` (T, ...) with its last sample repeated `pad` times: every signal's range, hence the
    excitation and scale tests, is unchanged, and the delayed inputs see the held last sample
    that `shift_samples` gives beyond a record's end."""
    return np.concatenate([x, np.repeat(x[-1:], pad, axis=0)])


def kernel_weights(mf: ModulatingFunction, i: int, dt: float, rule: str, delay, length: int):
    r"""Weights $w_l$, $l = 0..$`length`$-1$, of the modulated signal $x_i$ (see module doc).

    `i`, `dt`, `rule`, `length` are static; `mf.h`, `mf.N`, `mf.M` and `delay` may be traced
    (differentiable). Weights beyond the support are exactly 0.
    """
    require_x64("kernel_weights")
    i = derivative_order("kernel_weights", i)
    if not isinstance(mf, ModulatingFunction):
        raise TypeError(f"kernel_weights(): mf must be a ModulatingFunction, got "
                        f"{type(mf).__name__}")
    if isinstance(length, bool) or not isinstance(length, int | np.integer) or length < 2:
        raise TypeError(f"kernel_weights(): length must be an int >= 2 (the number of "
                        f"weights, a static size), got {length!r}")
    concrete = lambda x: not any(is_traced(v) for v in jax.tree.leaves(x))  # noqa: E731
    if concrete(dt) and not (math.isfinite(float(dt)) and float(dt) > 0):
        raise ValueError(f"kernel_weights(): dt must be a finite number > 0, got {dt!r}")
    if concrete(delay) and (np.ndim(delay) != 0 or not np.isfinite(np.asarray(delay, float))
                            or np.asarray(delay) < 0):
        raise ValueError(f"kernel_weights(): delay must be one finite number >= 0 (one "
                         f"kernel's delay), got {delay!r}")
    if concrete(dt) and concrete(delay) and concrete(mf.h):
        need = kernel_length(float(np.max(mf.h)) + float(np.max(delay)), float(dt))
        if length < need:
            raise ValueError(f"kernel_weights(): length={length} is shorter than the support "
                             f"(h + delay) / dt: it needs {need} samples, or the weights are "
                             "cut off")
    w = profile_weights(lambda r: phi_scaled(r, mf.N, mf.M, i)[None], mf.h, dt, rule, delay,
                        length)[0]
    # traced values are not checked above: a support beyond `length` (cut-off weights) or a
    # negative delay gives NaN, not plausible weights
    span = jnp.asarray(mf.h, jnp.float64) + jnp.asarray(delay, jnp.float64)
    ok = (support_samples(span, dt) <= length - 1) & (jnp.asarray(delay) >= 0) & (
        jnp.asarray(dt) > 0)
    return jnp.where(ok, w, jnp.nan)


def legendre_weights(degree: int, h, dt: float, rule: str, delay, length: int):
    r"""Weights (degree+1, length) of the shifted Legendre polynomials $P_q(2r - 1)$, $q \le$
    `degree`, as profiles on $[0, 1]$: the basis in which every $p_i$ of every (N, M) with
    $N + M \le$ `degree` is an exact combination (`legendre_coefficients`)."""
    return profile_weights(lambda r: shifted_legendre(r, degree), h, dt, rule, delay, length)


def shifted_legendre(r, degree: int, xp=jnp):
    """P_q(2r - 1) for q = 0..degree, stacked on a new leading axis (three-term recurrence)."""
    x = 2.0 * xp.asarray(r) - 1.0
    out = [xp.ones_like(x), x]
    for q in range(1, degree):
        out.append(((2 * q + 1) * x * out[q] - q * out[q - 1]) / (q + 1))
    return xp.stack(out[: degree + 1])


def legendre_coefficients(N, M, i: int, degree: int) -> np.ndarray:
    r"""$c_q$ with $p_i(r) = \sum_q c_q P_q(2r-1)$ (exact projection by Gauss-Legendre).

    `N`, `M` may be equal-length sequences: the result is then (len, degree + 1), one row per
    (N, M), from one evaluation (a search's plan needs hundreds of them). On the host, in
    NumPy: a plan compiles nothing."""
    x, w = np.polynomial.legendre.leggauss(degree + 2)
    r = (x + 1) / 2
    Nv = np.asarray(N, dtype=np.float64)[..., None]
    Mv = np.asarray(M, dtype=np.float64)[..., None]
    vals = phi_scaled(r, Nv, Mv, i, xp=np)  # (..., nodes)
    basis = shifted_legendre(r, degree, np)  # (degree + 1, nodes)
    return (2 * np.arange(degree + 1) + 1) * ((w * vals) @ basis.T) / 2


def profile_weights(profile, h, dt: float, rule: str, delay, length: int):
    r"""Weights (Q, length) of a batch of profiles $f_q(r)$ on $[0, 1]$ (see module doc):
    $w_{q,l} = \frac1h \int_\tau^{\tau+h} \beta_l(s) f_q((s-\tau)/h)\,ds$.

    `profile(r)` maps an array of r to (Q, *r.shape); it is exact whenever the profiles are
    polynomials of degree <= 20 (12-point Gauss per cell against a cubic at most)."""
    if rule not in RULES:
        raise ValueError(f"kernel_weights(): rule must be one of {RULES} (got {rule!r})")
    tau = jnp.asarray(delay, dtype=jnp.float64)
    n_cells = length - 1
    cell = jnp.arange(n_cells, dtype=jnp.float64)
    lo = jnp.clip(tau, cell * dt, (cell + 1) * dt)  # cell l is s' in [l dt, (l+1) dt]
    hi = jnp.clip(tau + h, cell * dt, (cell + 1) * dt)
    half = 0.5 * (hi - lo)
    gx = jnp.asarray(_GAUSS_X)
    gw = jnp.asarray(_GAUSS_W)
    s = 0.5 * (hi + lo)[:, None] + half[:, None] * gx[None, :]  # (cells, gauss)
    kern = profile((s - tau) / h) * (half[:, None] * gw[None, :]) / h  # (Q, cells, gauss)
    xi = s / dt  # position in samples
    if rule == "zoh":
        idx = (cell + 1).astype(jnp.int32)[:, None]
        basis = jnp.ones_like(xi)[..., None]
    elif rule == "foh":
        idx = jnp.stack([cell, cell + 1], axis=-1).astype(jnp.int32)
        sig = xi - cell[:, None]
        basis = jnp.stack([1.0 - sig, sig], axis=-1)
    else:
        cap = support_samples(tau + h, dt)
        start = jnp.clip(cell.astype(jnp.int32) - 1, 0, jnp.maximum(cap - 3, 0))
        idx = start[:, None] + jnp.arange(4, dtype=jnp.int32)[None, :]
        z = xi - start[:, None].astype(jnp.float64)
        cubic = jnp.stack(
            [
                -(z - 1) * (z - 2) * (z - 3) / 6,
                z * (z - 2) * (z - 3) / 2,
                -z * (z - 1) * (z - 3) / 2,
                z * (z - 1) * (z - 2) / 6,
            ],
            axis=-1,
        )
        # a support of 2 samples (h + tau <= 2 dt) holds 3 nodes: the parabola through them
        # (a cubic's 4th node lay before the support: at the first valid sample, before
        # the record, read as 0)
        parabola = jnp.stack([(z - 1) * (z - 2) / 2, -z * (z - 2), z * (z - 1) / 2,
                              jnp.zeros_like(z)], axis=-1)
        basis = jnp.where(cap < 3, parabola, cubic)
    contrib = jnp.einsum("qcg,cgn->qcn", kern, basis)  # (Q, cells, nodes)
    idx = jnp.minimum(idx, length - 1)
    Q = contrib.shape[0]
    out = jnp.zeros((Q, length), dtype=jnp.float64)
    return out.at[:, idx.reshape(-1)].add(contrib.reshape(Q, -1))


def fft_size(n: int) -> int:
    """Smallest 2^a 3^b 5^c >= n (sizes the FFT library handles fastest)."""
    best = 1 << (n - 1).bit_length()
    p5 = 1
    while p5 < best:
        p35 = p5
        while p35 < best:
            p235 = p35 * (1 << max(0, (-(-n // p35) - 1).bit_length()))
            best = min(best, p235)
            p35 *= 3
        p5 *= 5
    return best


def modulate(x, weights):
    r"""Sliding convolution $\sum_l w_l x_{k-l}$ for every $k$ (zero before the record start).

    `x` is (T,), `weights` (..., L) (a batch of kernels); returns (..., T). Entries with
    $k < \lceil(\tau+h)/dt\rceil$ are not valid modulated values and are masked by the Gram
    quadrature. By real FFT of a size >= T + L - 1 (a linear, not circular, convolution: every
    entry is the direct sum up to rounding of order eps times the norms), about 10x faster than
    the direct sum for the kernels of this method (hundreds of taps).
    """
    T, L = x.shape[0], weights.shape[-1]
    n = fft_size(T + L - 1)
    spectrum = jnp.fft.rfft(x, n) * jnp.fft.rfft(weights, n, axis=-1)
    return jnp.fft.irfft(spectrum, n, axis=-1)[..., :T]


def gregory_weights(n_samples: int, first, dt: float, end=None):
    r"""Gregory (end-corrected trapezoid, O(dt^4)) weights on samples `first..end-1` (default
    end: `n_samples`), an array of length `n_samples`.

    Zero outside (`first` and `end` may be traced). End weights 3/8, 7/6, 23/24; needs at least
    6 valid samples.
    """
    k = jnp.arange(n_samples)
    ends = jnp.asarray([3 / 8, 7 / 6, 23 / 24])
    end = n_samples if end is None else end

    def end_weight(offset):
        return jnp.where(offset < 3, ends[jnp.clip(offset, 0, 2)], 1.0)

    w = end_weight(k - first) * end_weight(end - 1 - k)
    return dt * jnp.where((k >= first) & (k < end), w, 0.0)


def shift_samples(x, lag, rows=None):
    """x[j - lag] for every j (or every j in `rows`, consecutive samples `rows[0] + arange`),
    holding x[0] before the start and the last sample after the end (`lag` >= -1 and `rows`
    may be traced).

    One slice of the record edge-padded by the window's length before it and one sample (with
    `rows`, which may run past the end from a start inside the record: the window's length
    and one) after it: exactly x[clip(j - lag, 0, T - 1)] (a lag beyond the front padding
    starts the slice at its first sample: every value x[0], as it should be). A slice, not a
    gather of every index: the forced terms of the search's validation simulations took
    0.87x the time."""
    L = x.shape[0] if rows is None else rows.shape[0]
    first = 0 if rows is None else rows[0]
    # rows may run past the record's end (a window buffer beyond it, `window_bucket`)
    after = 1 if rows is None else L + 1
    padded = jnp.concatenate([jnp.full(L, x[0]), x, jnp.full(after, x[-1])])
    # clamped here: dynamic_slice reads a negative start from the end
    return jax.lax.dynamic_slice_in_dim(padded, jnp.maximum(L + first - lag, 0), L)


def split_delay(delay, dt: float):
    """tau = (d + f) dt with integer d >= 0 and 0 <= f < 1 (traced-friendly). A delay within
    `EDGE` samples of a whole number of samples is that number, f exactly 0 (its derivative
    kept): tau / dt of a delay typed in decimals rounds to either side of the integer
    (22 * 0.37 / 0.37 = 22.000000000000004), and for a zoh input the held value read at
    t_j - tau changes sample at f = 0 (`delayed_samples`)."""
    steps = jnp.asarray(delay) / dt
    whole = jnp.round(steps)
    snap = jnp.abs(steps - whole) <= EDGE
    d = jnp.where(snap, whole, jnp.floor(steps))
    f = steps - d
    f = jnp.where(snap, f - jax.lax.stop_gradient(f), jnp.clip(f, 0.0, 1.0))
    return d.astype(jnp.int32), f


def delayed_samples(x, delay, dt: float, mode: str, rows=None):
    r"""Values $\tilde x(t_j - \tau)$ of the zoh/foh interpolant of `x` at the sample times
    (those of `rows` when given)."""
    d, f = split_delay(delay, dt)
    prev, cur = shift_samples(x, d + 1, rows), shift_samples(x, d, rows)
    if mode == "zoh":
        return jnp.where(f > 0, prev, cur)
    return f * prev + (1 - f) * cur
