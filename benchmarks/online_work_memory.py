"""Peak memory of the on-line identifier against its ring buffer (the CLI's memory bound).

    python benchmarks/online_work_memory.py

For T = 250, 2,500 and 25,000 samples per interval (Table 1's settings scaled with T: T_obfin =
2T, T_obinit = 4T, h in {0.2T, 0.4T}; n = 2, K = 2), each in a fresh process: the peak RSS
through the first identification (`datasets.switching_experiment`, 10 intervals). The growth of
the peak per byte of ring buffer gives `mfmjax._cli._WORK_PER_BUFFER` (measured 213, set 256).
Saves benchmarks/results/online_work_memory.json.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

CHILD = r"""
import json, resource, sys
from mfmjax import OnlineConfig, OnlineIdentifier
from mfmjax.datasets import switching_experiment
S = int(sys.argv[1])
t, y, u, _ = switching_experiment(interval=S, n_intervals=10, quiet=(0, 1), switches=(9,))
cfg = OnlineConfig(dt=1.0, n_inputs=2, interval=float(S), T_obfin=2.0 * S, T_obinit=4.0 * S,
                   h=(0.2 * S, 0.4 * S), n=(2,), intersample=("foh", "zoh"))
before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
ident = OnlineIdentifier(cfg, keep_history=False)
for c in range(0, len(t), S):
    ident.update(t[c : c + S], y[c : c + S], u[c : c + S])
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
print(json.dumps({"T": S, "buffer_samples": cfg.buffer, "buffer_bytes": cfg.buffer * 3 * 8,
                  "peak_rss_MB": peak / 1e3, "rss_before_MB": before / 1e3,
                  "models": len(ident.models)}))
"""


def main():
    rows = []
    for S in (250, 2500, 25000):
        out = subprocess.run([sys.executable, "-c", CHILD, str(S)], capture_output=True,
                             text=True, check=True).stdout
        rows.append(json.loads(out.strip().splitlines()[-1]))
    print(f"{'T':>7}{'buffer [samples]':>18}{'buffer [MB]':>13}{'peak RSS [MB]':>15}{'models':>8}")
    for r in rows:
        print(f"{r['T']:>7}{r['buffer_samples']:>18,}{r['buffer_bytes'] / 1e6:>13.2f}"
              f"{r['peak_rss_MB']:>15.0f}{r['models']:>8}")
    a, b = rows[-2], rows[-1]
    factor = (b["peak_rss_MB"] - a["peak_rss_MB"]) * 1e6 / (b["buffer_bytes"] - a["buffer_bytes"])
    print(f"peak RSS growth per byte of ring buffer (T {a['T']} -> {b['T']}): {factor:.0f}")
    path = os.path.join(os.path.dirname(__file__), "results", "online_work_memory.json")
    with open(path, "w") as fh:
        json.dump({"rows": rows, "work_per_buffer_byte": factor}, fh, indent=1)


if __name__ == "__main__":
    main()
