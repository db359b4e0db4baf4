"""Speed of `read_csv` (numpy.loadtxt fast path) against the previous line-by-line reader.

    python benchmarks/csv_read.py [--rows 100000]

Writes a CSV with a header and 4 float columns (repr of random float64 values), reads it with
plain `numpy.loadtxt` (the peer the issue names: "a CSV reader about 7x slower than
numpy.loadtxt"), the previous line-by-line `read_csv` (copied below: "before"), `read_csv`
(numpy.loadtxt fast path: "after") and `read_csv` again with pandas imported (its other fast
path); checks they return identical arrays, and prints the median of 5 timed runs of each and
the ratios to numpy.loadtxt. Saves benchmarks/results/csv_read.json.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import sys
import tempfile
import time

import numpy as np

from mfmjax._signals import read_csv


def read_csv_line_by_line(path, names=None):  # the reader before the loadtxt fast path
    with open(path, newline="") as fh:
        lines = [ln for ln in fh.read().splitlines() if ln.strip()]
    comma = "," in lines[0]

    def split(line):
        return [c.strip() for c in (next(csv.reader([line])) if comma else line.split())]

    header, body = (split(lines[0]), lines[1:]) if names is None else (list(names), lines)
    rows = []
    for line in body:
        row = split(line)
        if len(row) != len(header):
            raise ValueError("bad row")
        rows.append([float(c) if c else math.nan for c in row])
    data = np.asarray(rows, dtype=np.float64)
    return {name: data[:, j] for j, name in enumerate(header)}


def median_time(fn, path, runs=5):
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        out = fn(path)
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--rows", type=int, default=100_000)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    data = rng.standard_normal((args.rows, 4))
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "data.csv")
        with open(path, "w") as fh:
            fh.write("t,y,u1,u2\n")
            for row in data:
                fh.write(",".join(repr(float(v)) for v in row) + "\n")
        size_mb = os.path.getsize(path) / 1e6
        t_np, ref = median_time(lambda p: np.loadtxt(p, delimiter=",", skiprows=1), path)
        t_old, old = median_time(read_csv_line_by_line, path)
        assert "pandas" not in sys.modules
        t_new, new = median_time(read_csv, path)  # numpy.loadtxt path
        t_imp = time.perf_counter()
        import pandas  # noqa: F401

        t_imp = time.perf_counter() - t_imp
        t_pd, new_pd = median_time(read_csv, path)  # pandas path (pandas already imported)
    assert all(np.array_equal(old[k], new[k]) for k in old), "the readers disagree"
    assert all(np.array_equal(old[k], new_pd[k]) for k in old), "the readers disagree"
    assert np.array_equal(new["y"], data[:, 1]) and np.array_equal(ref, data)
    res = {"rows": args.rows, "columns": 4, "file_MB": round(size_mb, 2),
           "numpy_loadtxt_s": t_np, "before_vs_loadtxt": t_old / t_np,
           "after_vs_loadtxt": t_new / t_np, "after_pandas_vs_loadtxt": t_pd / t_np,
           "line_by_line_s": t_old, "read_csv_loadtxt_s": t_new, "speedup_loadtxt": t_old / t_new,
           "read_csv_pandas_s": t_pd, "speedup_pandas": t_old / t_pd, "pandas_import_s": t_imp}
    print(f"{args.rows} rows x 4 columns ({size_mb:.1f} MB), median of 5 runs")
    print(f"{'reader':<28}{'time [s]':>10}{'/ loadtxt':>11}")
    for label, t in (("numpy.loadtxt (peer)", t_np), ("line by line (before)", t_old),
                     ("read_csv (loadtxt path)", t_new), ("read_csv (pandas imported)", t_pd)):
        print(f"{label:<28}{t:>10.3f}{t / t_np:>10.2f}x")
    print(f"speedup: loadtxt path {t_old / t_new:.1f}x, pandas path {t_old / t_pd:.1f}x "
          f"(importing pandas took {t_imp:.2f} s; read_csv imports it only above "
          "32 MB of text)")
    out = os.path.join(os.path.dirname(__file__), "results", "csv_read.json")
    with open(out, "w") as fh:
        json.dump(res, fh, indent=1)


if __name__ == "__main__":
    main()
