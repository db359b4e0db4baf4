"""Benchmarks that run a child script in fresh processes, alternated with another mfmjax.

`--compare DIR` alternates every run with the package found in DIR (e.g. a `git archive` copy
of an earlier commit), so both see the same machine load; the persistent compilation cache is
off (MFMJAX_NO_COMPILE_CACHE=1), so every first call compiles.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent


def arguments(name: str) -> argparse.Namespace:
    """--runs, --compare and --json (default benchmarks/results/<name>.json)."""
    ap = argparse.ArgumentParser()
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--compare", help="a directory holding another mfmjax package")
    ap.add_argument("--json", default=str(HERE / "results" / f"{name}.json"))
    return ap.parse_args()


def run_child(child: str, pythonpath: str | None) -> dict:
    """Run `child` (BENCH and TESTS replaced by the benchmarks' and tests' folders) in a new
    process; its last output line is a JSON object."""
    env = dict(os.environ, MFMJAX_NO_COMPILE_CACHE="1")
    if pythonpath:
        env["PYTHONPATH"] = pythonpath
    child = child.replace("BENCH", repr(str(HERE))).replace("TESTS", repr(str(HERE.parent /
                                                                               "tests")))
    out = subprocess.run([sys.executable, "-c", child], env=env, capture_output=True, text=True,
                         check=True, cwd="/tmp")
    return json.loads(out.stdout.strip().splitlines()[-1])


def alternated(args, child: str, show) -> list[dict]:
    """`args.runs` rounds of the child, this package then (with --compare) the other; each
    row labelled "this" / "compare" with its round, printed by `show(row)`."""
    rows = []
    for i in range(args.runs):
        for label, path in [("this", None)] + ([("compare", args.compare)] if args.compare
                                                else []):
            r = run_child(child, path)
            r.update(label=label, run=i)
            rows.append(r)
            show(r)
    return rows


def by_label(rows: list[dict]):
    """(label, its rows) for each label of `alternated`'s rows ("compare", then "this")."""
    for label in sorted({r["label"] for r in rows}):
        yield label, [r for r in rows if r["label"] == label]


def spread(values, fmt: str = ".2f", scale: float = 1.0) -> str:
    """"min-max" of `values` (numbers), each times `scale`."""
    vals = [scale * v for v in values]
    return f"{min(vals):{fmt}}-{max(vals):{fmt}}"
