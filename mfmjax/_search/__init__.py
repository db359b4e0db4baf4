r"""Batched structure search over (N, M, h, delays) x (n, m_1..m_K): one compiled computation.

Work sharing:

- for one (h, delays), every $\phi^{(i)}$ of every (N, M) is a polynomial of degree
  $\le N + M$ in $s/h$. Each signal (output, inputs, offset, and the feed-through sources of
  candidates with $m_k = n$) is convolved once with the exact weights of the shifted Legendre
  polynomials $P_q(2s/h - 1)$ (`legendre_weights`, real FFT): its sliding moments. Every
  column of $c(t)$ for every (N, M) is an exact combination $C_{N,M}$ of moments, so with the
  moment Gram $H$ (one per (h, delays)) every Gram is $G_{N,M} = C_{N,M} H C_{N,M}^T$: the
  convolutions and the O(T) Gram work are shared across N, M, orders and derivatives;
- every structure is a masked sub-block of the grid's largest Gram: every candidate (each
  (N, M) with N, M >= n x each structure of order n, `Plan.cand`) is solved in the padded
  layout with its order traced and a column mask, by `constrained_solve` batched over all of
  them (masked columns get $\theta_j = 0$; one compiled solve for every order), exactly the
  problem `identify` solves for that structure. Its conditioning (flag `ill_conditioned`, `cond`)
  comes from Householder tridiagonalisation + Sturm bisection (`_linalg`);
- every candidate is then simulated from its initial-state-observer estimate on the validation
  window (eq. 14, 17) through a zero-padded realisation of order $n_{max}$ with a state mask,
  in vmapped batches of 32 (`VALIDATION_BATCH`) so memory stays flat. For `search` (one
  device) that is a program of its own (`validate_blocks`), whose shapes depend on the
  record, $n_{max}$ and the window only: a new grid on a searched record compiles its solves
  alone.

(h, delays) settings are processed in chunks of fixed size (one compilation for the whole
grid, memory flat in the candidate count; results go straight into preallocated columns).
Each chunk's setting axis is sharded over all `jax.devices()` with a 1-D mesh
(`NamedSharding`); within a device, the signal-sized work (moments, H) runs one setting at a
time (`lax.map`: cache-sized) and the small solves in blocks of `SOLVE_BLOCK` candidates.
With one device, the chunks of a compiled program run on a thread per core (a compiled chunk
runs its loops on one core); a program's first run runs its first chunk alone, which compiles.
"""

from ._engine import run_plan as run_plan
from ._grid import SCORES as SCORES
from ._grid import check_eta_reaches as check_eta_reaches
from ._grid import plan_search as plan_search
from ._grid import structures as structures
from ._result import SearchResult as SearchResult
from ._search import search as search
from ._validation import validate_candidate as validate_candidate
