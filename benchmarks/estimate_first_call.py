"""First and warm `estimate` call in fresh processes, with the programs it compiles.

A user's first `estimate` pays every compilation; this measures it without the persistent
compilation cache (MFMJAX_NO_COMPILE_CACHE=1), each run in a new process, and the median of five
warm calls on new realisations after it. `--compare DIR` alternates every run with the package
found in DIR (e.g. a `git worktree` of an earlier commit), so both see the same machine load.

    python benchmarks/estimate_first_call.py [--runs 3] [--compare /tmp/old]

Record: `third_order_two_input`, 1200 samples, dt 0.05, output noise 0.05; grid n in {2, 3},
N, M in {4, 5}, h in {2.5, 3.1} (16 settings; the structures come from the default m grid).
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

sys.path.insert(0, os.path.dirname(__file__))
import fresh_process  # noqa: E402

CHILD = r"""
import json, time, warnings
warnings.simplefilter("ignore")
import numpy as np
import mfmjax
from mfmjax.datasets import simulated_experiment, third_order_two_input

import sys
sys.path.insert(0, TESTS)
from jaxlog import compiles  # the tests' compile counter (JAX's own log)
grid = dict(n=(2, 3), N=(4, 5), M=(4, 5), h=(2.5, 3.1))
rec = lambda s: simulated_experiment(third_order_two_input(), dt=0.05, n_samples=1200, seed=s,
                                     noise_std=0.05)
first_rec = rec(3)
with compiles() as names:
    t = time.perf_counter()
    est = mfmjax.estimate(first_rec, **grid)
    first = time.perf_counter() - t
programs = len(names)
warm = []
for s in range(10, 15):
    r = rec(s)
    t = time.perf_counter()
    mfmjax.estimate(r, **grid)
    warm.append(time.perf_counter() - t)
print(json.dumps(dict(first_s=first, warm_ms=1e3 * float(np.median(warm)), programs=programs,
                      method=est.method, n=est.model.n, m=list(est.model.m))))
"""


def main() -> None:
    args = fresh_process.arguments("estimate_first_call")
    rows = fresh_process.alternated(args, CHILD, lambda r: print(
        f"{r['label']:8s} run {r['run']}: first call {r['first_s']:6.2f} s, "
        f"{r['programs']:3d} programs; warm median {r['warm_ms']:6.0f} ms "
        f"({r['method']}, n={r['n']}, m={r['m']})", flush=True))
    for label, sel in fresh_process.by_label(rows):
        print(f"{label:8s} first call {fresh_process.spread(r['first_s'] for r in sel)} s, "
              f"warm {fresh_process.spread((r['warm_ms'] for r in sel), '.0f')} ms, programs "
              f"{sel[0]['programs']}")
    Path(args.json).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
