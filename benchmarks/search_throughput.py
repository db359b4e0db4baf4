"""Batched search throughput against a per-candidate NumPy/SciPy loop (same MFM, same data).

    python benchmarks/search_throughput.py [--quick]

Data: T = 8000 samples (dt = 1 s), K = 2 inputs (foh, zoh), 1 % output noise. Grid: N, M in
3..8, 16 values of h (40..250 s), n in 1..4, every m_k <= n - 1 (N, M >= n). The NumPy loop runs
on a random subset of candidates and is scaled (said in the table). Prints candidates/s of both,
the ratio, compile time, peak RSS, the largest parameter difference, and how time grows with T
and with the candidate count. Library times are the median of 5 warm runs (1 for the slower E
score); the peer's is one pass over its subset. Saves benchmarks/results/search_throughput.json.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(__file__))
import numpy_mfm  # noqa: E402

import mfmjax  # noqa: E402
from mfmjax.datasets import paper_table3_model1, simulated_experiment  # noqa: E402


def rss_mb():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def noisy(T):
    sig = simulated_experiment(paper_table3_model1(), dt=1.0, n_samples=T, seed=1)
    y = np.asarray(sig.y)
    y = y + 0.01 * np.std(y) * np.random.default_rng(2).standard_normal(T)
    return mfmjax.Signals(y, sig.u, dt=1.0, intersample=sig.intersample)


def timed_search(sig, repeats=5, **kw):
    """(result, compile s, median warm s): the first call compiles; then `repeats` warm calls,
    each a whole `search` (plan, chunks, ranking)."""
    t0 = time.perf_counter()
    res = mfmjax.search(sig, **kw)
    first = time.perf_counter() - t0
    warm = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        res = mfmjax.search(sig, **kw)
        warm.append(time.perf_counter() - t0)
    med = float(np.median(warm))
    return res, first - med, med


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="smaller grid and subset")
    args = ap.parse_args()
    T = 8000
    sig = noisy(T)
    hs = np.linspace(40, 250, 4 if args.quick else 16)
    NM = range(3, 6) if args.quick else range(3, 9)
    grid = dict(n=(1, 2, 3, 4), N=NM, M=NM, h=hs, m=None)
    out = {"T": T, "grid": {"N": list(NM), "M": list(NM), "h": hs.tolist(), "n": [1, 2, 3, 4]}}

    res_j, compile_j, warm_j = timed_search(sig, score="J", simulate=False, **grid)
    C = len(res_j)
    res_e, compile_e, warm_e = timed_search(sig, repeats=1, score="E", **grid)
    lib_rate_j, lib_rate_e = C / warm_j, C / warm_e

    rng = np.random.default_rng(0)
    subset = rng.choice(C, size=min(C, 60 if args.quick else 1000), replace=False)
    y, u = np.asarray(sig.y), np.asarray(sig.u)
    cols = res_j.columns
    t0 = time.perf_counter()
    peer = [numpy_mfm.identify(y, u, 1.0, sig.intersample, int(cols["n"][j]),
                               [int(v) for v in cols["m"][j]], cols["N"][j], cols["M"][j],
                               cols["h"][j]) for j in subset]
    peer_rate = len(subset) / (time.perf_counter() - t0)
    diffs = []
    for j, th in zip(subset, peer):
        n = int(cols["n"][j])
        if cols["status"][j] != 0 or cols["cond"][j] > 1e8:
            continue
        lib = np.concatenate([cols["a"][j][: n + 1]] + [cols["b"][j][k][: int(cols["m"][j][k]) + 1]
                                                        for k in range(2)])
        diffs.append(np.max(np.abs(lib - th)) / np.max(np.abs(th)))
    out.update(candidates=C, lib_rate_J=lib_rate_j, lib_rate_E=lib_rate_e,
               compile_J_s=compile_j, compile_E_s=compile_e, peer_rate=peer_rate,
               peer_subset=len(subset), ratio_J=lib_rate_j / peer_rate,
               ratio_E=lib_rate_e / peer_rate, max_param_diff=max(diffs),
               compared=len(diffs), peak_rss_mb=rss_mb())
    print(f"candidates: {C}   (NumPy peer on a random subset of {len(subset)}, scaled)")
    print(f"{'':34}{'candidates/s':>14}{'ratio':>10}{'compile s':>11}")
    print(f"{'numpy/scipy loop (eq. 12)':34}{peer_rate:>14.1f}{1.0:>10.1f}{'-':>11}")
    print(f"{'mfmjax.search, J only':34}{lib_rate_j:>14.1f}{lib_rate_j / peer_rate:>10.1f}"
          f"{compile_j:>11.1f}")
    print(f"{'mfmjax.search, J + E + fit + IC':34}{lib_rate_e:>14.1f}{lib_rate_e / peer_rate:>10.1f}"
          f"{compile_e:>11.1f}")
    print(f"largest parameter difference (status ok, cond < 1e8, {len(diffs)} compared): "
          f"{max(diffs):.2e}")
    print(f"peak RSS: {rss_mb():.0f} MB")

    small = dict(grid, h=hs[:: max(1, len(hs) // 4)], score="J", simulate=False)
    growth_T = []
    for TT in (2000, 8000, 32000):
        r, c, w = timed_search(noisy(TT), **small)
        growth_T.append({"T": TT, "candidates": len(r), "warm_s": w, "compile_s": c})
        print(f"T = {TT:>6}: {len(r)} candidates in {w:.3f} s (warm, J only; compile {c:.1f} s)")
    growth_C = []
    for nh in (2, 4, 8, 16) if not args.quick else (2, 4):
        r, c, w = timed_search(sig, **dict(grid, h=np.linspace(40, 250, nh), score="J",
                                         simulate=False))
        growth_C.append({"candidates": len(r), "warm_s": w})
        print(f"{len(r):>6} candidates (T = 8000): {w:.3f} s (warm, J only), "
              f"{len(r) / w:.0f} candidates/s")
    out.update(growth_T=growth_T, growth_candidates=growth_C)
    path = os.path.join(os.path.dirname(__file__), "results", "search_throughput.json")
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "w") as fh:
        json.dump(out, fh, indent=2)
    print(f"saved {path}")


if __name__ == "__main__":
    main()
