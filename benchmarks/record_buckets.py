"""Record-length buckets for `identify`, `simulate`, `observe`, `output_error` and `srivc`:
what a new record length costs, and what the padding costs warm. One process; the unpadded
programs (the behaviour before the buckets) are called through the same public functions
with the padding switched off, alternated with the padded ones.

- new length: a record of 2900 samples after one of 3000 (both pad to 3072): the padded call
  reuses the compiled program; the unpadded one compiles a program for 2900 samples.
- warm: the median of repeated calls on the 3000-sample record (padded to 3072 against 3000
  samples), identify at 40 new (N, M, h) settings inside one kernel bucket.

    python benchmarks/record_buckets.py [--repeats 5]
"""

from __future__ import annotations

import argparse
import json
import os
import time

import jax
import numpy as np

import mfmjax
import mfmjax._identify as _identify
import mfmjax._observers as _observers
import mfmjax._simulate as _simulate
import mfmjax._srivc as _srivc
from mfmjax import ModulatingFunction, Signals, Structure
from mfmjax.datasets import simulated_experiment, third_order_two_input

ST = Structure(3, (1, 0))


def _unpadded(on: bool):
    """Switch the padding off (`record_bucket` returns the length itself) or back on; output
    error pads with `_observers.padded_window`."""
    for mod in (_identify, _observers, _simulate, _srivc):
        mod.record_bucket = (lambda n: n) if on else _REAL


_REAL = _identify.record_bucket


def _timed(f):
    t = time.perf_counter()
    jax.block_until_ready(f())
    return time.perf_counter() - t


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    true = third_order_two_input()
    sig = simulated_experiment(true, dt=0.01, n_samples=3000, seed=1, noise_std=0.01)
    mf = ModulatingFunction(4, 5, 0.5)
    model = mfmjax.identify(sig, ST, mf)

    def short(T):
        return Signals(np.asarray(sig.y)[:T], np.asarray(sig.u)[:T], dt=0.01,
                       intersample=sig.intersample)

    calls = {
        "identify": lambda s: mfmjax.identify(s, ST, mf).theta,
        "simulate": lambda s: mfmjax.simulate(model, s.u, dt=0.01),
        "observe": lambda s: mfmjax.observe(model, s).E,
        "output_error": lambda s: mfmjax.output_error(s, model).E,
        "srivc": lambda s: mfmjax.srivc(s, model).E,
    }
    res = {"new_length": {}, "warm_ms": {}}
    for name, f in calls.items():
        rows = {"padded": [], "unpadded": []}
        for r in range(args.repeats):  # a fresh pair of lengths per repeat, alternated
            for mode in ("padded", "unpadded"):
                _unpadded(mode == "unpadded")
                first, second = 3000 - 20 * (2 * r + (mode == "unpadded")), 2900 - 10 * r
                f(short(first))  # the program of this bucket (or length) exists
                rows[mode].append(_timed(lambda s=short(second): f(s)))
        _unpadded(False)
        res["new_length"][name] = {m: float(np.median(v)) for m, v in rows.items()}
    rng = np.random.default_rng(0)
    mfs = [ModulatingFunction(int(rng.integers(4, 7)), int(rng.integers(4, 7)), float(h))
           for h in np.linspace(0.45, 0.6, 40)]
    warm = {"padded": [], "unpadded": []}
    for mode in ("padded", "unpadded"):
        _unpadded(mode == "unpadded")
        mfmjax.identify(sig, ST, mfs[0])
    for _ in range(args.repeats):
        for m in mfs:
            for mode in ("padded", "unpadded"):
                _unpadded(mode == "unpadded")
                warm[mode].append(_timed(lambda m=m: mfmjax.identify(sig, ST, m).theta))
    _unpadded(False)
    res["warm_ms"]["identify"] = {m: 1e3 * float(np.median(v)) for m, v in warm.items()}
    print("a new record length inside the bucket (2900 after 3000 samples), median of "
          f"{args.repeats}: seconds")
    print(f"{'':>12} {'padded':>10} {'unpadded':>10} {'ratio':>8}")
    for name, row in res["new_length"].items():
        print(f"{name:>12} {row['padded']:>10.4f} {row['unpadded']:>10.4f} "
              f"{row['unpadded'] / row['padded']:>8.1f}")
    w = res["warm_ms"]["identify"]
    print(f"warm identify at new settings, 3000 samples: padded {w['padded']:.3f} ms, "
          f"unpadded {w['unpadded']:.3f} ms, ratio {w['padded'] / w['unpadded']:.3f}")
    path = os.path.join(os.path.dirname(__file__), "results", "record_buckets.json")
    with open(path, "w") as fh:
        json.dump(res, fh, indent=1)
    print(f"saved {path}")


if __name__ == "__main__":
    main()
