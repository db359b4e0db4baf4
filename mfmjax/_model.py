"""The identified (or given) continuous-time MISO model of eq. (1)."""

from __future__ import annotations

import functools
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._modulating import ModulatingFunction, as_values
from ._pytree import replace_fields
from ._status import Status, describe
from ._structure import Structure


class Model(eqx.Module):
    r"""$\sum_{i=0}^n a_i y^{(i)} = \sum_k \sum_{j=0}^{m_k} b_{kj} u_k^{(j)}(t - \tau_k)
    [+ b_{\text{off}}]$ with $a_n = 1$.

    Fields: `a` (n+1,), `b` (tuple of K arrays (m_k+1,)), `offset` (constant term, 0 when the
    model has none), `delays` (K,), and what identification reported: `theta` (the raw
    $\eta$-normalised vector of eq. 12, ordered [a; b_1; ..; b_K; b_off]), `J` (equation-error
    cost $\sqrt{\theta^T G \theta}$ of eq. 8), `J_rel` (scale-free equation error
    $\|c^T\theta\| / (\sum_i \theta_i^2 \|c_i\|^2)^{1/2}$), `cond` (cond of the equilibrated G), `status`
    (bit flags, see `Status`), `mf` (the modulating function used). A pytree: jit/vmap friendly.
    """

    a: jax.Array
    b: tuple[jax.Array, ...]
    offset: jax.Array
    delays: jax.Array
    theta: jax.Array
    J: jax.Array
    J_rel: jax.Array
    cond: jax.Array
    status: jax.Array
    mf: ModulatingFunction | None
    structure: Structure
    intersample: tuple[str, ...] = eqx.field(static=True)
    has_offset: bool = eqx.field(static=True)
    output_name: str = eqx.field(static=True, default="y")
    input_names: tuple[str, ...] = eqx.field(static=True, default=())

    @property
    def n(self) -> int:
        return self.structure.n

    @property
    def m(self) -> tuple[int, ...]:
        return self.structure.m

    @property
    def n_inputs(self) -> int:
        return len(self.structure.m)

    @property
    def ok(self):
        return self.status == 0

    @classmethod
    def from_coefficients(
        cls,
        a: Sequence[float],
        b: Sequence[Sequence[float]] = (),
        *,
        offset: float | None = None,
        delays: Sequence[float] | None = None,
        intersample: Sequence[str] | None = None,
        output_name: str = "y",
        input_names: Sequence[str] | None = None,
    ) -> Model:
        """A model from given coefficients a (a_0..a_n) and b (b_k0..b_km_k per input).

        Coefficients are normalised to a_n = 1. Raises if a_n = 0 or the orders are invalid.
        """
        from ._boundary import eager_only, number, require_x64

        require_x64("Model.from_coefficients")  # device_put narrowed to float32 without it
        if isinstance(b, (str, bytes)) or not hasattr(b, "__iter__"):
            raise TypeError(f"Model.from_coefficients(): b must be a sequence of per-input "
                            f"coefficient lists, got {type(b).__name__}; for one input write "
                            "b=[[b_0, b_1, ...]]")
        b = b if hasattr(b, "shape") else list(b)  # once: a generator was used up by the
        # checks (a model of no inputs); an array stays one (a traced b is refused below)
        eager_only("Model.from_coefficients", a, b, offset, delays)
        for name, value in (("a", a), *((f"b[{k}]", bk) for k, bk in enumerate(b)),
                            ("delays", delays)):  # True was read as 1.0
            if value is not None and any(isinstance(v, (bool, np.bool_)) for v in
                                         np.asarray(value, dtype=object).ravel()):
                raise TypeError(f"Model.from_coefficients(): {name} holds a bool; give numbers")
        offset = None if offset is None else number("Model.from_coefficients", "offset", offset)
        a = np.asarray(a, dtype=np.float64)
        if a.ndim != 1 or a.size < 2:
            raise ValueError("Model.from_coefficients(): a must list a_0..a_n with n >= 1")
        if not np.all(np.isfinite(a)):
            raise ValueError("Model.from_coefficients(): a contains NaN or inf")
        if a[-1] == 0:
            raise ValueError(
                "Model.from_coefficients(): a_n (the last entry of a) must be nonzero; "
                "drop trailing zeros to lower the order"
            )
        if any(np.ndim(bk) != 1 for bk in b):  # a flat [1.0, 0.5] read as two inputs
            raise ValueError(
                "Model.from_coefficients(): b must list each input's coefficients b_k0..b_km_k "
                f"as a sequence (got {b!r}); for one input write b=[[b_0, b_1, ...]], for two "
                "inputs of order 0 b=[[b_10], [b_20]]")
        bs = [np.asarray(bk, dtype=np.float64) for bk in b]
        for k, bk in enumerate(bs):
            if not np.all(np.isfinite(bk)):
                raise ValueError(f"Model.from_coefficients(): b[{k}] contains NaN or inf")
            if bk.size == 0:  # it said "Structure(): m[0] must be an integer >= 0 (got -1)"
                raise ValueError(f"Model.from_coefficients(): b[{k}] is empty; give at least "
                                 f"b_{k + 1}0 (or leave the input out of b)")
        structure = Structure(a.size - 1, [bk.size - 1 for bk in bs])
        K = len(bs)
        an = a[-1]
        if delays is None:
            delays = np.zeros(K)
        delays = np.asarray(delays, dtype=np.float64).reshape(-1)
        if delays.shape != (K,) or np.any(delays < 0) or not np.all(np.isfinite(delays)):
            raise ValueError(
                f"Model.from_coefficients(): delays needs {K} finite values >= 0 (got {delays})"
            )
        input_names = _check_names("Model.from_coefficients", output_name, input_names, K)
        if isinstance(intersample, str):
            intersample = (intersample,) * K
        intersample = (tuple(str(v) if isinstance(v, str) else v for v in intersample)
                       if intersample is not None else ("foh",) * K)  # np.str_ -> str
        if len(intersample) != K or any(s not in ("zoh", "foh") for s in intersample):
            raise ValueError(
                f"Model.from_coefficients(): intersample needs {K} entries of 'zoh'/'foh'"
            )
        with np.errstate(over="ignore"):
            scaled = np.concatenate([a / an] + [bk / an for bk in bs]
                                    + ([np.array([offset / an])] if offset is not None else []))
        if not np.all(np.isfinite(scaled)):  # (a = [inf, 1], status ok, before)
            raise ValueError(f"Model.from_coefficients(): a_n = {an:g} is so small that the "
                             "coefficients divided by it (a_n = 1 is the normal form) overflow "
                             "float64; rescale the equation (multiply a, b and offset by one "
                             "factor) or drop a_n if it is a rounding-level zero")
        theta = np.concatenate([a] + bs + ([np.array([offset])] if offset is not None else []))
        arrays = jax.device_put(dict(  # NumPy on the device: no eager programs
            a=a / an, b=tuple(bk / an for bk in bs),
            offset=np.float64(0.0 if offset is None else offset / an), delays=delays,
            theta=theta / np.sum(theta) if np.sum(theta) != 0 else theta,
            J=np.float64(np.nan), J_rel=np.float64(np.nan), cond=np.float64(np.nan),
            status=np.int32(0)))
        return cls(
            **arrays,
            mf=None,
            structure=structure,
            intersample=intersample,
            has_offset=offset is not None,
            output_name=output_name,
            input_names=tuple(input_names)
            if input_names is not None
            else tuple(f"u{k + 1}" for k in range(K)),
        )

    def unlabelled(self) -> Model:
        """Labels removed and the MF settings as values (`as_values`): what jitted programs see,
        so that names and settings never compile a new program."""
        return replace_fields(self, output_name="y", mf=None if self.mf is None else as_values(self.mf),
                              input_names=_input_names(self.n_inputs))

    def labelled(self, output_name: str, input_names: Sequence[str]) -> Model:
        """The same model with these labels (the inverse of `unlabelled` after a jitted call)."""
        names = _check_names("Model.labelled", output_name, input_names, self.n_inputs)
        if names is None:
            raise TypeError("Model.labelled(): input_names must be a list of strings, one per "
                            "input")
        return replace_fields(self, output_name=output_name, input_names=names)

    def summary(self) -> str:
        """A readable table of the parameters and fit diagnostics (concrete models only)."""
        lines = [
            f"continuous-time model  n={self.n}  m={list(self.m)}"
            + (
                f"  (N={plain_number(self.mf.N)}, M={plain_number(self.mf.M)}, h={float(self.mf.h):g})"
                if self.mf is not None
                else ""
            ),
            f"{'parameter':<14}{'value':>16}",
        ]
        for i, ai in enumerate(np.asarray(self.a)):
            lines.append(f"{f'a_{i}':<14}{ai:>16.6e}")
        for k, bk in enumerate(self.b):
            for j, bkj in enumerate(np.asarray(bk)):
                lines.append(f"{f'b_{k + 1}{j}':<14}{bkj:>16.6e}")
        if self.has_offset:
            lines.append(f"{'offset':<14}{float(self.offset):>16.6e}")
        for k, tau in enumerate(np.asarray(self.delays)):
            if tau:
                lines.append(f"{f'delay_{k + 1}':<14}{tau:>16.6g}")
        if self.mf is not None:
            lines.append(f"{'J':<14}{float(self.J):>16.6e}")
            lines.append(f"{'J_rel':<14}{float(self.J_rel):>16.6e}")
            lines.append(f"{'cond(G_eq)':<14}{float(self.cond):>16.3e}")
        lines.append(f"{'status':<14}{describe(int(self.status)):>16}")
        return "\n".join(lines)

    def to_dict(self) -> dict:
        """Plain-Python description (JSON-ready) of a concrete model."""
        out = {
            "n": self.n,
            "m": list(self.m),
            "a": [float(v) for v in np.asarray(self.a)],
            "b": [[float(v) for v in np.asarray(bk)] for bk in self.b],
            "delays": [float(v) for v in np.asarray(self.delays)],
            "intersample": list(self.intersample),
            "offset": float(self.offset) if self.has_offset else None,
            "theta": [float(v) for v in np.asarray(self.theta)],
            "J": finite_or_none(self.J),
            "J_rel": finite_or_none(self.J_rel),
            "cond": finite_or_none(self.cond),
            "status": describe(int(self.status)),
            "output_name": self.output_name,
            "input_names": list(self.input_names),
        }
        if self.mf is not None:
            out.update(N=plain_number(self.mf.N), M=plain_number(self.mf.M), h=float(self.mf.h))
        return out


def simulation_form(model: Model) -> Model:
    r"""`model` as the simulations and observers see it: unlabelled, every numerator zero-padded
    to order n ($b_{kj} = 0$ for $m_k < j \le n$: the same realisation, eq. 18),
    without the identification's theta and MF settings. Every structure of order n with the
    same inputs, rules and offset term is then one pytree, so `simulate` and the observers
    compile one program per order, not one per structure. NumPy for a concrete model (no
    program), JAX for a traced one."""
    from ._boundary import is_traced

    n, K = model.n, model.n_inputs
    b = model.b
    if any(bk.shape[0] != n + 1 for bk in b):
        xp = jnp if any(is_traced(bk) for bk in b) else np
        b = tuple(bk if bk.shape[0] == n + 1 else xp.concatenate(
            [xp.asarray(bk, dtype=np.float64), xp.zeros(n + 1 - bk.shape[0])]) for bk in b)
    return replace_fields(model, b=b, theta=_NO_THETA, mf=None, output_name="y",
                          structure=_full_structure(n, K), input_names=_input_names(K))


_NO_THETA = np.zeros(0)


@functools.cache
def _full_structure(n: int, K: int) -> Structure:
    return Structure(n, [n] * K)


@functools.cache
def _input_names(K: int) -> tuple[str, ...]:
    return tuple(f"u{k + 1}" for k in range(K))


def growing_poles(a) -> np.ndarray:
    """The roots of A(s) (coefficients a_0..a_n, host) with Re > 0 above the roots' rounding
    (np.roots puts an integrator's 0 at +-1e-17 |p|)."""
    p = np.roots(np.asarray(a, dtype=np.float64)[::-1])
    return p[p.real > 1e-9 * np.max(np.abs(p), initial=0.0)]


def is_stable(a) -> bool:
    """A(s) (coefficients a_0..a_n, host) has every root in the open left half plane."""
    return bool(np.all(np.roots(np.asarray(a, dtype=np.float64)[::-1]).real < 0))


def plain_number(x):
    """A float, or an int when it is integral (N and M print as 4, not 4.0)."""
    v = float(np.asarray(x))
    return int(v) if v == int(v) else v


def finite_or_none(x):
    """A float, or None when it is not finite (JSON has no NaN)."""
    v = float(np.asarray(x))
    return v if np.isfinite(v) else None


__all__ = ["Model", "Status"]


def _check_names(fn: str, output_name, input_names, K: int) -> tuple | None:
    """The input names as a tuple of strings, checked: a string output name and one string
    per input (a name list of another length was accepted by `labelled` and the file it
    saved was refused by `load_model`; a string "pq" became two names); read once (a
    generator)."""
    if not isinstance(output_name, str):
        raise TypeError(f"{fn}(): output_name must be a string, got "
                        f"{type(output_name).__name__}")
    if input_names is None:
        return None
    if isinstance(input_names, (str, bytes)):
        raise TypeError(f"{fn}(): input_names must be a list of strings, one per input, not "
                        f"the string {input_names!r}; write input_names=[{input_names!r}]")
    names = tuple(input_names)
    if len(names) != K:
        raise ValueError(f"{fn}(): input_names needs one name per input ({K}; got "
                         f"{list(names)})")
    if not all(isinstance(v, str) for v in names):
        raise TypeError(f"{fn}(): input_names must be strings (got {list(names)})")
    return names
