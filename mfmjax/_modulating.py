r"""Loeb-Cahen modulating functions $\phi(t) = t^N (h-t)^M$ (paper eq. 2).

Time is scaled by $h$: with $t = h r$, $r \in [0, 1]$,

$$\phi^{(i)}(t) = h^{N+M-i}\, p_i(r), \qquad
p_i(r) = \frac{d^i}{dr^i}\left[r^N (1-r)^M\right]
       = \sum_{j=0}^{i} \binom{i}{j} N^{\underline{j}}\, r^{N-j}\,
         (-1)^{i-j} M^{\underline{i-j}}\, (1-r)^{M-i+j},$$

($x^{\underline{j}}$ the falling factorial). The Leibniz form is evaluated directly: no monomial
expansion, so there is no cancellation, and it holds for real $N, M$ too (issue: relaxed orders).
$\phi^{(i)}(0) = \phi^{(i)}(h) = 0$ for $i < \min(N, M)$, which is what integration by parts in
eq. (3)-(4) needs for $i \le n - 1$.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.special as jsp
import numpy as np

from ._boundary import require_x64
from ._pytree import replace_fields

MAX_DEGREE = 20  # N + M bound that the fixed Gauss rule of _quadrature integrates exactly


def _is_concrete(x) -> bool:
    return not isinstance(x, jax.core.Tracer)


def frozen(x) -> np.ndarray:
    """A read-only float64 NumPy copy of a concrete setting: immutable like a JAX array, so a
    model never shares a buffer that the caller may change later."""
    out = np.array(x, dtype=np.float64)
    out.flags.writeable = False
    return out


class ModulatingFunction(eqx.Module):
    r"""Settings of one Loeb-Cahen modulating function $\phi(t) = t^N (h-t)^M$ on $[0, h]$.

    **Arguments:**

    - `N`, `M`: exponents (Python ints normally; arrays allowed for relaxed, differentiable
      exponents). The method needs $N, M \ge n$ (checked by `identify`).
    - `h`: support width in time units (a float or a JAX array; need not be a multiple of dt).
    - `h_max`: static upper bound on `h` that fixes the kernel length when `h` is traced (under
      `jit`/`vmap`/`grad`); defaults to `h` itself when `h` is concrete.
    """

    N: float | jax.Array
    M: float | jax.Array
    h: jax.Array
    h_max: float | None = eqx.field(static=True, default=None)

    def __init__(self, N, M, h, h_max: float | None = None):
        from ._boundary import check_modulating

        check_modulating(N, M, h, h_max)
        for name, val in (("N", N), ("M", M)):
            if _is_concrete(val):
                v = float(np.max(np.asarray(val)))
                if not math.isfinite(v) or v < 1:
                    raise ValueError(
                        f"ModulatingFunction(): {name} must be a finite number >= 1 (got {name}={v})"
                    )
        if _is_concrete(N) and _is_concrete(M):
            if float(np.max(np.asarray(N))) + float(np.max(np.asarray(M))) > MAX_DEGREE:
                raise ValueError(
                    f"ModulatingFunction(): N + M must be <= {MAX_DEGREE} (got N={N}, M={M}); "
                    "larger exponents add nothing but rounding"
                )
        self.N = N
        self.M = M
        if _is_concrete(h):
            hv = float(np.max(np.asarray(h, dtype=np.float64)))
            if not (math.isfinite(hv) and float(np.min(np.asarray(h, dtype=np.float64))) > 0):
                raise ValueError(f"ModulatingFunction(): h must be > 0 and finite (got h={h})")
            if h_max is None:
                h_max = hv
            elif hv > h_max * (1 + 1e-12):
                raise ValueError(
                    f"ModulatingFunction(): h={hv} exceeds h_max={h_max}; raise h_max"
                )
        # a concrete h stays on the host (a read-only NumPy copy): no device transfer per setting
        self.h = frozen(h) if _is_concrete(h) else jnp.asarray(h, dtype=jnp.float64)
        if h_max is not None and not h_max > 0:
            raise ValueError(f"ModulatingFunction(): h_max must be > 0 (got {h_max})")
        self.h_max = None if h_max is None else float(h_max)


def as_values(mf: ModulatingFunction) -> ModulatingFunction:
    """`mf` with N, M and h as float64 array leaves and no static bound: the form that jitted
    programs take, so that a new setting is a new value, never a new program (the kernel
    length is fixed separately, by `_quadrature.kernel_bucket`)."""
    def value(x):  # numpy for concrete values (no device dispatch), jnp for tracers
        return jnp.asarray(x, dtype=jnp.float64) if isinstance(x, jax.core.Tracer) else frozen(x)

    return replace_fields(mf, N=value(mf.N), M=value(mf.M), h_max=None)


def _falling(x, j: int, xp=jnp):
    """Falling factorial x (x-1) ... (x-j+1) (1 for j = 0); x may be real."""
    out = xp.ones_like(xp.asarray(x, dtype=xp.float64))
    for q in range(j):
        out = out * (x - q)
    return out


def derivative_order(fn: str, i) -> int:
    """`i`, the derivative order of phi: a static int >= 0 (a negative one gave zeros or the
    i = 0 integral silently)."""
    if isinstance(i, bool) or not isinstance(i, int | np.integer) or i < 0:
        raise ValueError(f"{fn}(): i, the derivative order, must be a Python integer >= 0 "
                         f"(static under jax.jit), got {i!r}")
    return int(i)


def phi_scaled(r, N, M, i: int, *, xp=jnp):
    r"""$p_i(r) = d^i/dr^i [r^N (1-r)^M]$ on $r \in [0, 1]$ (closed form, Leibniz rule).

    `i` is a static int; `r` an array; `N`, `M` numbers or arrays. Values outside $[0,1]$ are 0.
    `xp=numpy` evaluates on the host (plans: no compiled program per shape).
    """
    i = derivative_order("phi_scaled", i)
    if xp is jnp:
        require_x64("phi_scaled")
        # concrete exponents as float64 values: a Python int exponent is a static `integer_pow`
        # (one eager program per exponent); a float one is `pow`, one program for every (N, M)
        N, M = (np.float64(x) if _is_concrete(x) and np.ndim(x) == 0 else x for x in (N, M))
    r = xp.asarray(r, dtype=xp.float64)
    inside = (r > 0) & (r < 1)
    rs = xp.where(inside, r, 0.5)  # keeps gradients finite at and outside the ends
    total = xp.zeros_like(rs)
    for j in range(i + 1):
        term = (
            math.comb(i, j)
            * _falling(N, j, xp)
            * (-1.0) ** (i - j)
            * _falling(M, i - j, xp)
            * rs ** (N - j)
            * (1.0 - rs) ** (M - i + j)
        )
        total = total + term
    return xp.where(inside, total, 0.0)


def _modulating_function(fn: str, mf) -> None:
    if not isinstance(mf, ModulatingFunction):
        raise TypeError(f"{fn}(): mf must be a ModulatingFunction (ModulatingFunction(N, M, "
                        f"h)), got {type(mf).__name__}")


def _end_value(N, M, i: int, at_one: bool):
    r"""$p_i$'s one-sided limit at r = 0 (or 1 with `at_one`): the Leibniz terms whose power
    of r (of 1 - r) is 0 survive, positive powers vanish, negative ones (real N, M < i) are
    infinite; 0 for i < N (i < M), where phi^(i) is continuous there."""
    total = jnp.zeros(jnp.broadcast_shapes(jnp.shape(N), jnp.shape(M)))
    for j in range(i + 1):
        coef = math.comb(i, j) * _falling(N, j) * (-1.0) ** (i - j) * _falling(M, i - j)
        power = (M - i + j) if at_one else (N - j)
        total = total + jnp.where(power == 0, coef, jnp.where(
            (power < 0) & (coef != 0), jnp.sign(coef) * jnp.inf, 0.0))
    return total


def phi(t, mf: ModulatingFunction, i: int = 0):
    r"""$\phi^{(i)}(t) = h^{N+M-i} p_i(t/h)$ in physical time (0 outside $[0, h]$; at $t = 0$
    and $t = h$ the one-sided value from inside, which differs from 0 for $i \ge N$ or
    $i \ge M$; NaN at a NaN t)."""
    require_x64("phi")
    i = derivative_order("phi", i)
    _modulating_function("phi", mf)
    h = mf.h
    r = jnp.asarray(t, dtype=jnp.float64) / h
    p = phi_scaled(r, mf.N, mf.M, i)
    p = jnp.where(r == 0, _end_value(mf.N, mf.M, i, False), p)
    p = jnp.where(r == 1, _end_value(mf.N, mf.M, i, True), p)
    return h ** (mf.N + mf.M - i) * jnp.where(jnp.isnan(r), jnp.nan, p)


def phi_integral(a, b, mf: ModulatingFunction, i: int = 0):
    r"""Exact $\int_a^b \phi^{(i)}(t)\,dt$.

    For $i \ge 1$ this is $\phi^{(i-1)}(b) - \phi^{(i-1)}(a)$; for $i = 0$ it is
    $h^{N+M+1} B(N+1, M+1)\,[I_{b/h} - I_{a/h}]$ with the regularised incomplete beta $I$,
    differentiable in a, b and h but not in N and M (JAX's `betainc` has no gradient in its
    parameters; the estimators never integrate phi itself).
    """
    require_x64("phi_integral")
    i = derivative_order("phi_integral", i)
    _modulating_function("phi_integral", mf)
    if i >= 1:
        return phi(b, mf, i - 1) - phi(a, mf, i - 1)
    h = mf.h
    N1, M1 = mf.N + 1.0, mf.M + 1.0
    beta = jnp.exp(jsp.gammaln(N1) + jsp.gammaln(M1) - jsp.gammaln(N1 + M1))

    def reg(x):
        x = jnp.clip(jnp.asarray(x, dtype=jnp.float64) / h, 0.0, 1.0)
        return jsp.betainc(N1, M1, x)

    return h ** (mf.N + mf.M + 1) * beta * (reg(b) - reg(a))
