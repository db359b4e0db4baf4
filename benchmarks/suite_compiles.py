"""Where the test suite's compile time goes: the suite run with JAX's compile log
(`jax_log_compiles`) recorded per test by a pytest plugin (this file), then summed per
program and per test file.

    python benchmarks/suite_compiles.py [extra pytest arguments]

Prints the programs with the most XLA compile time and the test files that compile most;
saves benchmarks/results/suite_compiles.json (set MFMJAX_SUITE_COMPILES_KEEP=<folder> to keep
the per-test log: one line per compilation, test id then JAX's message). Times are taken
with the other xdist worker running: read shares, not absolute seconds. Persistent-cache hits
are counted apart.
"""

from __future__ import annotations

import collections
import glob
import json
import logging
import os
import re
import subprocess
import sys
import tempfile

HERE = os.path.dirname(os.path.abspath(__file__))
LOG_DIR = "MFMJAX_SUITE_COMPILES_DIR"
_XLA = re.compile(r"Finished XLA compilation of (\S+) in ([\d.e-]+) sec")
_HIT = re.compile(r"Persistent compilation cache hit for '(\S+)'")

# -- the pytest plugin (loaded in every worker with `-p suite_compiles`) ----------------------

if os.environ.get(LOG_DIR):
    import jax
    import pytest

    _test = {"id": "(collection)"}
    _out = open(os.path.join(os.environ[LOG_DIR], f"{os.getpid()}.log"), "a")  # noqa: SIM115

    class _Handler(logging.Handler):
        def emit(self, record):
            msg = record.getMessage()
            if _XLA.match(msg) or _HIT.match(msg):
                _out.write(f"{_test['id']}\t{msg.splitlines()[0]}\n")
                _out.flush()

    jax.config.update("jax_log_compiles", True)
    logging.getLogger("jax").addHandler(_Handler())

    @pytest.hookimpl(tryfirst=True)
    def pytest_runtest_setup(item):
        _test["id"] = item.nodeid


# -- the driver -------------------------------------------------------------------------------


def summarise(log_dir: str) -> dict:
    seconds, count, hits = collections.Counter(), collections.Counter(), collections.Counter()
    per_file = collections.Counter()
    for path in glob.glob(os.path.join(log_dir, "[0-9]*.log")):  # the workers' (by pid)
        with open(path) as fh:
            for line in fh:
                test, msg = line.rstrip("\n").split("\t", 1)
                if m := _XLA.match(msg):
                    seconds[m.group(1)] += float(m.group(2))
                    count[m.group(1)] += 1
                    per_file[test.split("::")[0]] += float(m.group(2))
                elif m := _HIT.match(msg):
                    hits[m.group(1)] += 1
    return {"total_xla_s": sum(seconds.values()),
            "programs": [{"program": k, "xla_s": v, "compiles": count[k]}
                         for k, v in seconds.most_common()],
            "files": [{"file": k, "xla_s": v} for k, v in per_file.most_common()],
            "cache_hits": dict(hits)}


def main():
    keep = os.environ.get("MFMJAX_SUITE_COMPILES_KEEP")  # a folder: keep the per-test log there
    with tempfile.TemporaryDirectory() as tmp:
        log_dir = keep or tmp
        os.makedirs(log_dir, exist_ok=True)
        env = dict(os.environ, **{LOG_DIR: log_dir})
        env["PYTHONPATH"] = os.pathsep.join([HERE] + [p for p in [env.get("PYTHONPATH")] if p])
        cmd = [sys.executable, "-m", "pytest", "-q", "-p", "suite_compiles", "-p", "no:logging",
               *sys.argv[1:]]
        rc = subprocess.call(cmd, env=env, cwd=os.path.dirname(HERE))
        out = summarise(log_dir)
    out["pytest_exit_code"] = rc
    print(f"\nXLA compilation, summed over workers: {out['total_xla_s']:.0f} s")
    print(f"{'program':<36}{'s':>8}{'compiles':>10}")
    for row in out["programs"][:15]:
        print(f"{row['program']:<36}{row['xla_s']:>8.1f}{row['compiles']:>10}")
    print(f"\n{'test file':<44}{'s':>8}")
    for row in out["files"][:15]:
        print(f"{row['file']:<44}{row['xla_s']:>8.1f}")
    path = os.path.join(HERE, "results", "suite_compiles.json")
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "w") as fh:
        json.dump(out, fh, indent=1)
    print(f"saved {path}")
    return rc


if __name__ == "__main__":
    sys.exit(main())
