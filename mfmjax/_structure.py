"""Model structure: output order n and numerator orders m_k (paper eq. 1)."""

from __future__ import annotations

from collections.abc import Sequence

import equinox as eqx

from . import _boundary as _b


class Structure(eqx.Module):
    r"""Orders of $\sum_{i=0}^n a_i y^{(i)} = \sum_k \sum_{j=0}^{m_k} b_{kj} u_k^{(j)}$.

    **Arguments:**

    - `n`: output order, >= 1.
    - `m`: one numerator order per input, each 0 <= m_k <= n (m_k = n gives a direct
      feed-through D != 0). An int is repeated for every input.
    """

    n: int = eqx.field(static=True)
    m: tuple[int, ...] = eqx.field(static=True)

    def __init__(self, n: int, m: int | Sequence[int] = ()):
        n = _b.integer("Structure", "n", n, lo=1, fix="the output order is a whole number")
        m = _b.values("Structure", "m", m, allow_empty=True)
        m = [_b.integer("Structure", f"m[{k}]", mk, lo=0) for k, mk in enumerate(m)]
        for k, mk in enumerate(m):
            if mk > n:
                raise ValueError(
                    f"Structure(): m[{k}]={mk} exceeds n={n}; numerator orders must be <= n"
                )
        self.n, self.m = n, tuple(int(mk) for mk in m)

    def for_inputs(self, K: int, fn: str = "identify") -> Structure:
        """Broadcast a single m to K inputs, or check that m has K entries."""
        if len(self.m) == K:
            return self
        if len(self.m) == 1 and K > 1:
            return Structure(self.n, self.m * K)
        raise ValueError(
            f"{fn}(): the data have K={K} inputs but m has {len(self.m)} entries "
            f"(m={list(self.m)}); give one numerator order per input"
        )

    @property
    def n_params(self) -> int:
        """Length of theta = [a; b_1; ...; b_K] (n + 1 + sum(m_k + 1))."""
        return self.n + 1 + sum(mk + 1 for mk in self.m)
