"""Latency of the on-line identifier (Algorithm 1) and memory on an endless stream.

    python benchmarks/online_latency.py [--quick]

Data: `datasets.switching_experiment` (1 s sampling, T = 250 s intervals, a plant switch at an
operating point), Table 1's settings and the paper's candidate set (n in {2, 3}, m_k in {0, 1},
N in {3, 5}, M in {4, 6}, h in {50, 100}: 64 candidates). Prints

- median / 99th percentile latency of one interval update after warm-up (one interval of samples
  per call), split into prediction-only intervals and intervals that re-identify, for paper mode
  (Algorithm 1 as stated) and improved mode (`OnlineConfig(mode="improved")`, its default
  improvements; these data have no input delay, so its delay grid is the single value 0: the
  forehearth's delay-grid cost is in `forehearth_modes.py`);
- wall time of a whole 10,000 s run, cold (compiles) and warm;
- the peer: one re-identification's 64 candidates through the NumPy/SciPy MFM loop
  (`numpy_mfm.identify`, eq. 12 only, no E), against the library's batched re-identification
  (identification AND E of all 64 candidates);
- resident memory along a 10^6-sample stream (`--quick`: 10^5) fed with keep_history=False.

Saves benchmarks/results/online_latency.json.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(__file__))
import numpy_mfm  # noqa: E402

import mfmjax  # noqa: E402
from mfmjax import _online  # noqa: E402
from mfmjax.datasets import switching_experiment  # noqa: E402

S = 250


def rss_mb():
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def config(mode="paper"):
    return mfmjax.OnlineConfig(dt=1.0, n_inputs=2, intersample=("foh", "zoh"), mode=mode)


def run(t, y, u, chunk=S, keep_history=True, latencies=None, mode="paper"):
    ident = mfmjax.OnlineIdentifier(config(mode), keep_history=keep_history)
    for c0 in range(0, len(t), chunk):
        a = time.perf_counter()
        out = ident.update(t[c0 : c0 + chunk], y[c0 : c0 + chunk], u[c0 : c0 + chunk])
        dt = time.perf_counter() - a
        if latencies is not None and out.events:
            reid = any(e["action"] not in ("none",) and not e["action"].startswith("waiting")
                       for e in out.events)
            latencies.append((dt, reid))
    return ident


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    t, y, u, _ = switching_experiment()  # 40 intervals = 10,000 s
    a = time.perf_counter()
    run(t, y, u)
    cold = time.perf_counter() - a
    a = time.perf_counter()
    ident = run(t, y, u)
    warm = time.perf_counter() - a
    lat = []
    for _ in range(3 if args.quick else 10):
        run(t, y, u, latencies=lat)
    d = np.asarray([v for v, _ in lat]) * 1e3
    reid = np.asarray([r for _, r in lat])
    q = lambda x, p: float(np.percentile(x, p)) if x.size else float("nan")  # noqa: E731
    run(t, y, u, mode="improved")  # warm: compiles improved mode's programs
    lat_i = []
    for _ in range(3 if args.quick else 10):
        run(t, y, u, latencies=lat_i, mode="improved")
    d_i = np.asarray([v for v, _ in lat_i]) * 1e3
    reid_i = np.asarray([r for _, r in lat_i])
    # the peer: one re-identification window, 64 candidates through the NumPy loop
    c = config()
    win = slice(16 * S, 20 * S)
    structs = [(n, (m1, m2)) for n in c.n for m1 in (0, 1) for m2 in (0, 1)]
    mfs = [(N, M, h) for h in c.h for N in c.N for M in c.M]
    a = time.perf_counter()
    for N, M, h in mfs:
        for n, m in structs:
            numpy_mfm.identify(y[win], u[win], 1.0, c.intersample, n, m, N, M, h)
    peer = time.perf_counter() - a
    state = _online.init(c)
    state, _ = _online.update(state, t[: 20 * S], y[: 20 * S], u[: 20 * S])
    plan = _online._plan_for(c, c.n_reident)
    sig = _online._window_signals(c, y[win], u[win], 0.0)
    _online.run_plan(plan, sig)
    reps = []
    for _ in range(10):
        a = time.perf_counter()
        _online.run_plan(plan, sig)
        reps.append(time.perf_counter() - a)
    ours = float(np.median(reps))
    # memory along an endless stream
    n_total = 100_000 if args.quick else 1_000_000
    reps_needed = n_total // len(t)
    ident = mfmjax.OnlineIdentifier(config(), keep_history=False)
    marks, a = [], time.perf_counter()
    for r in range(reps_needed):
        off = r * len(t)
        for c0 in range(0, len(t), 10 * S):
            sl = slice(c0, c0 + 10 * S)
            ident.update(t[sl] + off, y[sl], u[sl])
        if r in (0, reps_needed // 10, reps_needed // 2, reps_needed - 1):
            marks.append((off + len(t), rss_mb()))
    stream_s = time.perf_counter() - a
    res = {
        "candidates": len(structs) * len(mfs),
        "latency_ms": {"all_median": q(d, 50), "all_p99": q(d, 99),
                       "predict_median": q(d[~reid], 50), "predict_p99": q(d[~reid], 99),
                       "reident_median": q(d[reid], 50), "reident_p99": q(d[reid], 99),
                       "intervals": int(d.size), "reident_intervals": int(reid.sum())},
        "latency_ms_improved": {
            "all_median": q(d_i, 50), "all_p99": q(d_i, 99),
            "predict_median": q(d_i[~reid_i], 50), "predict_p99": q(d_i[~reid_i], 99),
            "reident_median": q(d_i[reid_i], 50), "reident_p99": q(d_i[reid_i], 99),
            "intervals": int(d_i.size), "reident_intervals": int(reid_i.sum())},
        "run_10000s": {"cold_s": cold, "warm_s": warm},
        "reident_64": {"mfmjax_s": ours, "numpy_loop_s": peer, "ratio": peer / ours},
        "stream": {"samples": reps_needed * len(t), "wall_s": stream_s,
                   "rss_mb": [[int(s), round(m, 1)] for s, m in marks],
                   "models": len(ident.models)},
    }
    print(f"on-line identifier, {res['candidates']} candidates, T = 250 s, dt = 1 s")
    for mode, key in (("paper", "latency_ms"), ("improved", "latency_ms_improved")):
        L = res[key]
        print(f"{mode + ' mode: interval update latency [ms]':<44}{'median':>10}{'p99':>10}"
              f"{'count':>8}")
        print(f"{'  all intervals':<44}{L['all_median']:>10.2f}{L['all_p99']:>10.2f}"
              f"{L['intervals']:>8}")
        print(f"{'  prediction only':<44}{L['predict_median']:>10.2f}{L['predict_p99']:>10.2f}"
              f"{L['intervals'] - L['reident_intervals']:>8}")
        print(f"{'  with re-identification':<44}{L['reident_median']:>10.2f}"
              f"{L['reident_p99']:>10.2f}{L['reident_intervals']:>8}")
    print(f"whole 10,000 s run: cold {cold:.2f} s (compiles), warm {warm:.3f} s")
    r = res["reident_64"]
    print(f"one re-identification, 64 candidates: mfmjax {r['mfmjax_s'] * 1e3:.1f} ms (with E), "
          f"NumPy loop {r['numpy_loop_s'] * 1e3:.0f} ms (eq. 12 only): ratio {r['ratio']:.1f}x")
    st = res["stream"]
    print(f"stream of {st['samples']:,} samples in {st['wall_s']:.1f} s; RSS [MB] after "
          + ", ".join(f"{s:,}: {m:.0f}" for s, m in st["rss_mb"]))
    os.makedirs(os.path.join(os.path.dirname(__file__), "results"), exist_ok=True)
    with open(os.path.join(os.path.dirname(__file__), "results", "online_latency.json"), "w") as fh:
        json.dump(res, fh, indent=1)


if __name__ == "__main__":
    main()
