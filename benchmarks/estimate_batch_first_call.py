"""First and warm `estimate` call on a batch of 10 realisations of the RHP-zero system, in fresh
processes (no persistent cache), optionally alternated with another mfmjax (`--compare DIR`).

    python benchmarks/estimate_batch_first_call.py [--runs 2] [--compare /tmp/old]

`noise_montecarlo.py`'s fourth-order system with a right-half-plane zero: PRBS input held zoh,
7500 samples, 20 dB output noise (seed 0), its `estimate_grid`. Prints the first call, the
warm calls (min-max of three) and a hash of the estimates (equal hashes: bitwise the same
parameters); saves benchmarks/results/estimate_batch_first_call.json.
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

sys.path.insert(0, os.path.dirname(__file__))
import fresh_process  # noqa: E402

CHILD = r"""
import hashlib, json, sys, time, warnings
warnings.simplefilter("ignore")
sys.path.insert(0, BENCH)
import numpy as np
import noise_montecarlo as nm
import mfmjax

spec = nm.SYSTEMS["fourth_order_rhp_zero_prbs"]
true = spec["model"]()
clean = nm._prbs_experiment(true, spec["dt"], spec["T"], spec["prbs"])
y0 = np.asarray(clean.y)
sd = np.std(y0) / 10 ** (20 / 20)
rng = np.random.default_rng(0)
sigs = [mfmjax.Signals(y0 + sd * rng.standard_normal(y0.shape), clean.u, dt=spec["dt"],
                       intersample=("zoh",), offset=False) for _ in range(10)]
grid = nm.estimate_grid(spec)
t = time.perf_counter()
mfmjax.estimate(sigs, **grid)
first = time.perf_counter() - t
warm = []
for _ in range(3):
    t = time.perf_counter()
    ests = mfmjax.estimate(sigs, **grid)
    warm.append(time.perf_counter() - t)
digest = hashlib.sha1(np.concatenate([e.model.theta for e in ests]).tobytes()).hexdigest()[:12]
print(json.dumps(dict(first_s=first, warm_s=warm, digest=digest)))
"""


def main() -> None:
    args = fresh_process.arguments("estimate_batch_first_call")
    rows = fresh_process.alternated(args, CHILD, lambda r: print(
        f"{r['label']:8s} run {r['run']}: first call {r['first_s']:6.2f} s, warm "
        f"{min(r['warm_s']):.2f}-{max(r['warm_s']):.2f} s, estimates {r['digest']}", flush=True))
    for label, sel in fresh_process.by_label(rows):
        print(f"{label:8s} first call {fresh_process.spread(r['first_s'] for r in sel)} s, "
              f"warm {fresh_process.spread(w for r in sel for w in r['warm_s'])} s")
    Path(args.json).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
