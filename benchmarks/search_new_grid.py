"""A new E-scored search grid on a record already searched: first call and warm, fresh processes.

A user exploring a record tries grid after grid (other n, N, M or h values). Each new grid
compiles its chunk program; this measures what that costs after a first grid of the same
largest order on the same record, with the persistent compilation cache off
(MFMJAX_NO_COMPILE_CACHE=1), each run in a new process. `--compare DIR` alternates every run
with the package found in DIR (e.g. a `git archive` copy of an earlier commit), so both see
the same machine load.

    python benchmarks/search_new_grid.py [--runs 3] [--compare /tmp/old]

Record: `paper_table3_model1` (two inputs, foh and zoh), 2000 samples, dt 2.5, 5 % output
noise. Grid A: n in {1, 2, 3}, N in {3, 4, 5}, M in {3, 4}, h in {150, 200, 250, 300} (336
candidates); grid B: n in {2, 3}, N, M in {3, 4} x {4, 5}, h in {120, 180} (new structures,
pairs and widths, the same largest order 3). Peer: the shared-work NumPy search
(`numpy_shared_peer.py`) on grid B, scored by J only (it runs no validation simulations, so it
is a lower bound for any NumPy answer to the E-scored job), in the same process as the
library's run. Saves benchmarks/results/search_new_grid.json.
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

sys.path.insert(0, os.path.dirname(__file__))
import fresh_process  # noqa: E402

CHILD = r"""
import json, sys, time
import numpy as np
import mfmjax
from mfmjax.datasets import paper_table3_model1, simulated_experiment

sys.path.insert(0, BENCH)
sys.path.insert(0, TESTS)
import numpy_shared_peer
from jaxlog import compiles  # the tests' compile counter (JAX's own log)

sig = simulated_experiment(paper_table3_model1(), dt=2.5, n_samples=2000, seed=1,
                           noise_std=0.05)
A = dict(n=(1, 2, 3), N=(3, 4, 5), M=(3, 4), h=(150.0, 200.0, 250.0, 300.0))
B = dict(n=(2, 3), N=(3, 4), M=(4, 5), h=(120.0, 180.0))


def timed(grid):
    with compiles() as names:
        t = time.perf_counter()
        res = mfmjax.search(sig, **grid)
        first = time.perf_counter() - t
    warm = []
    for _ in range(7):
        t = time.perf_counter()
        mfmjax.search(sig, **grid)
        warm.append(time.perf_counter() - t)
    big = sorted(set(names) - {"jit(stage)"})
    return res, first, 1e3 * float(np.median(warm)), len(names), big


res_a, first_a, warm_a, prog_a, big_a = timed(A)
res_b, first_b, warm_b, prog_b, big_b = timed(B)
t = time.perf_counter()
peer = numpy_shared_peer.search(sig.y, sig.u, sig.dt, sig.intersample, **B)
t_peer = time.perf_counter() - t
best = res_b.best(0)
print(json.dumps(dict(cand_a=len(res_a), first_a_s=first_a, warm_a_ms=warm_a, programs_a=prog_a,
                      cand_b=len(res_b), first_b_s=first_b, warm_b_ms=warm_b, programs_b=prog_b,
                      compiled_b=big_b, peer_b_s=t_peer, peer_cand_b=len(peer["n"]),
                      best_b=[best.n, list(best.m)],
                      E_b=np.asarray(res_b.columns["E"]).tolist())))
"""


def show(r: dict) -> None:
    print(f"{r['label']:8s} run {r['run']}: grid A ({r['cand_a']} cand.) first "
          f"{r['first_a_s']:5.2f} s warm {r['warm_a_ms']:5.1f} ms | new grid B ({r['cand_b']} cand.) first "
          f"{r['first_b_s']:5.2f} s warm {r['warm_b_ms']:5.1f} ms, compiled "
          f"{r['compiled_b']} | peer on B (J only) {1e3 * r['peer_b_s']:5.1f} ms: "
          f"B's first call {r['first_b_s'] / r['peer_b_s']:4.1f}x, warm "
          f"{1e-3 * r['warm_b_ms'] / r['peer_b_s']:4.2f}x", flush=True)


def main() -> None:
    args = fresh_process.arguments("search_new_grid")
    rows = fresh_process.alternated(args, CHILD, show)
    if args.compare:
        this = [r for r in rows if r["label"] == "this"]
        other = [r for r in rows if r["label"] == "compare"]
        same = all(a["E_b"] == b["E_b"] and a["best_b"] == b["best_b"]
                   for a, b in zip(this, other))
        print(f"grid B's E column and winner identical in both: {same}")
    for label, sel in fresh_process.by_label(rows):
        def rng(k, f=1.0, sel=sel):
            return fresh_process.spread((r[k] for r in sel), scale=f)

        print(f"{label:8s} grid A first {rng('first_a_s')} s, warm {rng('warm_a_ms')} ms; "
              f"new grid B first {rng('first_b_s')} s, warm {rng('warm_b_ms')} ms; "
              f"peer on B {rng('peer_b_s', 1e3)} ms")
    for r in rows:
        r.pop("E_b")
    Path(args.json).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
