"""What a new record length costs `estimate` and `search` inside one record bucket: a call on
records of `--first` samples, then on records of each of `--lengths` (the same bucket), each
timed and its compiled programs counted (JAX's compile log), then the same call again (warm).

Run it on two commits to compare (the older one from a copy: `PYTHONPATH=/tmp/old python
benchmarks/estimate_record_lengths.py --out /tmp/old.json`); one process per run, the figures
of a run come from the same process.

    python benchmarks/estimate_record_lengths.py [--first 1200] [--lengths 1250,1100] [--batch 9]
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import time
import warnings

import numpy as np

import mfmjax
from mfmjax.datasets import simulated_experiment

TRUE = mfmjax.Model.from_coefficients([2.0, 3.0, 1.0], [[1.0]], intersample=["zoh"])
DT = 0.05
GRID = dict(h=2.0, n=(1, 2), N=3, M=3, m=[[0]])


class _Log(logging.Handler):
    def __init__(self):
        super().__init__()
        self.names = []

    def emit(self, record):
        msg = record.getMessage()
        if msg.startswith("Compiling "):
            self.names.append(msg.split()[1])


def _records(T: int, seeds) -> list:
    clean = simulated_experiment(TRUE, dt=DT, n_samples=T, seed=7)
    sd = float(np.std(np.asarray(clean.y))) / 10  # 20 dB
    return [simulated_experiment(TRUE, dt=DT, n_samples=T, seed=s, noise_std=sd) for s in seeds]


def _call(kind: str, T: int, batch: int, seed0: int):
    recs = _records(T, range(seed0, seed0 + batch))
    if kind == "estimate, one record":
        return lambda: mfmjax.estimate(recs[0], **GRID)
    if kind == f"estimate, {batch} records":
        return lambda: mfmjax.estimate(recs, **GRID)
    # the search scored on the last third (a hold-out share of the record)
    return lambda: mfmjax.search(recs[0], **GRID, validate=(round(T * 2 / 3) * DT, (T - 1) * DT))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--first", type=int, default=1200)
    ap.add_argument("--lengths", default="1250,1100")
    ap.add_argument("--batch", type=int, default=9)
    ap.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results",
                                                  "estimate_record_lengths.json"))
    args = ap.parse_args()
    import jax

    log = _Log()
    logging.getLogger("jax").addHandler(log)
    jax.config.update("jax_log_compiles", True)
    warnings.simplefilter("ignore")
    lengths = [int(x) for x in args.lengths.split(",")]
    rows = []
    kinds = ("search, validated on the last third", "estimate, one record",
             f"estimate, {args.batch} records")
    for kind in kinds:
        for i, T in enumerate([args.first] + lengths):
            f = _call(kind, T, args.batch, 100 * i)
            log.names.clear()
            t = time.perf_counter()
            f()
            first = time.perf_counter() - t
            programs = len(log.names)
            t = time.perf_counter()
            f()
            warm = time.perf_counter() - t
            rows.append(dict(kind=kind, samples=T, first_s=first, programs=programs,
                             warm_s=warm))
            print(f"{kind:<38} {T:>6} samples: first call {first:7.3f} s "
                  f"({programs:>2} programs), warm {warm:7.3f} s", flush=True)
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, "w") as fh:
        json.dump(dict(first=args.first, lengths=lengths, batch=args.batch, rows=rows,
                       mfmjax=os.path.dirname(mfmjax.__file__)), fh, indent=1)
    print(f"saved {args.out}")


if __name__ == "__main__":
    main()
