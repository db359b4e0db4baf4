"""`estimate` with and without the structures nested in its best (`_estimate.NESTED`): how often
it chooses the true structure, and what the nested structures cost.

    python benchmarks/estimate_nested.py [--records 10] [--repeats 2]

The plant of an audit (2026-11-27): `third_order_two_input` (n = 3, m = (1, 0); foh, zoh),
dt = 0.05, 2000 samples, white output noise of 5 % of the output's standard deviation (26 dB),
records of seeds 100.. ; the grid h (1, 2), n (2, 3), N (3, 4), M (3, 4) and the default m
(every m_k <= n: 25 structures). In one process, `NESTED` = 8 (the default) and 0 (the best 8
structures only) alternated: the first calls compile (their time printed apart), then
`repeats` rounds of the records one at a time and as one batch (NESTED = 0 runs second and
reuses the programs NESTED = 8 compiled: its first calls are mostly run time). Prints the structure choices,
the times per record and the ratios; saves benchmarks/results/estimate_nested.json.
"""

from __future__ import annotations

import argparse
import json
import os
import time
import warnings

import numpy as np

import mfmjax
from mfmjax import Signals, _estimate
from mfmjax.datasets import simulated_experiment, third_order_two_input

HERE = os.path.dirname(os.path.abspath(__file__))
GRID = dict(h=(1.0, 2.0), n=(2, 3), N=(3, 4), M=(3, 4))
TRUTH = (3, (1, 0))


def records(count: int) -> list:
    true, out = third_order_two_input(), []
    for seed in range(count):
        clean = simulated_experiment(true, dt=0.05, n_samples=2000, seed=100 + seed)
        y = np.asarray(clean.y)
        y = y + 0.05 * np.std(y) * np.random.default_rng(seed).standard_normal(y.size)
        out.append(Signals(y, np.asarray(clean.u), dt=0.05, intersample=("foh", "zoh"),
                           offset=False))
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--records", type=int, default=10)
    ap.add_argument("--repeats", type=int, default=2)
    args = ap.parse_args()
    warnings.simplefilter("ignore")
    recs = records(args.records)
    settings = (8, 0)
    out = {k: {"compile_s": None, "one_ms": [], "batch_ms": [], "chosen": None} for k in settings}
    for nested in settings:  # first calls: compile + run, one record and the batch
        _estimate.NESTED = nested
        t = time.perf_counter()
        mfmjax.estimate(recs[0], **GRID)
        mfmjax.estimate(recs, **GRID)
        out[nested]["compile_s"] = time.perf_counter() - t
    for _ in range(args.repeats):
        for nested in settings:
            _estimate.NESTED = nested
            t = time.perf_counter()
            ests = [mfmjax.estimate(r, **GRID) for r in recs]
            out[nested]["one_ms"].append(1e3 * (time.perf_counter() - t) / len(recs))
            t = time.perf_counter()
            mfmjax.estimate(recs, **GRID)
            out[nested]["batch_ms"].append(1e3 * (time.perf_counter() - t) / len(recs))
            out[nested]["chosen"] = [[e.model.n, list(e.model.m)] for e in ests]
    _estimate.NESTED = 8
    print(f"{'NESTED':>6} {'truth':>7} {'first calls s':>14} {'one ms/record':>16} "
          f"{'batch ms/record':>16}")
    for k in settings:
        r = out[k]
        hits = sum((n, tuple(m)) == TRUTH for n, m in r["chosen"])
        r["truth"] = hits
        print(f"{k:>6} {hits:>4}/{len(recs):<2} {r['compile_s']:>14.1f} "
              f"{', '.join(f'{v:.0f}' for v in r['one_ms']):>16} "
              f"{', '.join(f'{v:.0f}' for v in r['batch_ms']):>16}")
    ratio = {key: [a / b for a, b in zip(out[8][key], out[0][key])] for key in ("one_ms", "batch_ms")}
    print("cost (NESTED=8 / NESTED=0, per round): one at a time "
          + ", ".join(f"{v:.2f}x" for v in ratio["one_ms"]) + "; batch "
          + ", ".join(f"{v:.2f}x" for v in ratio["batch_ms"]))
    path = os.path.join(HERE, "results", "estimate_nested.json")
    with open(path, "w") as fh:
        json.dump({"grid": GRID, "truth": TRUTH, "results": {str(k): v for k, v in out.items()},
                   "ratios": ratio}, fh, indent=1)
    print(f"saved {path}")


if __name__ == "__main__":
    main()
