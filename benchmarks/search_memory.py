"""Peak memory of a search over about 1,000,000 candidates (equation-error score, chunked).

    /usr/bin/time -v python benchmarks/search_memory.py      # "Maximum resident set size"

Grid: n in 1..4 with every m_k <= n - 1 (K = 2), N, M in 3..8, 48 values of h, 5 x 5 input
delays: 1200 (h, delays) settings x 36 (N, M) x 30 structures, minus N or M < n. T = 2000.
Prints the candidate count, the time and the peak RSS (also saved as JSON).
"""

import json
import os
import resource
import time

import numpy as np

import mfmjax
from mfmjax.datasets import paper_table3_model1, simulated_experiment


def main():
    sig = simulated_experiment(paper_table3_model1(), dt=1.0, n_samples=2000, seed=1)
    t0 = time.perf_counter()
    res = mfmjax.search(
        sig, n=(1, 2, 3, 4), N=range(3, 9), M=range(3, 9), h=np.linspace(40, 200, 48),
        delays=[np.linspace(0, 20, 5), np.linspace(0, 20, 5)], score="J", simulate=False,
        chunk_size=8,
    )
    wall = time.perf_counter() - t0
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"{len(res)} candidates in {wall:.0f} s ({len(res) / wall:.0f} candidates/s), "
          f"peak RSS {rss:.0f} MB; best: {res.row(0)['n']}, {res.row(0)['m']}")
    path = os.path.join(os.path.dirname(__file__), "results", "search_memory.json")
    with open(path, "w") as fh:
        json.dump({"candidates": len(res), "wall_s": wall, "peak_rss_mb": rss}, fh, indent=2)


if __name__ == "__main__":
    main()
