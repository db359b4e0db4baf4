"""Execute every committed notebook (they must run top to bottom on CPU) and check that its
committed text outputs are the ones the code prints now (stale outputs mislead a reader)."""

import pathlib
import re

import pytest

NOTEBOOKS = sorted((pathlib.Path(__file__).parent.parent / "notebooks").glob("*.ipynb"))

NUMBER = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")
DURATION = re.compile(NUMBER.pattern + r"\s*m?s\b")  # "compile 9.3 s": varies run to run
# Printed figures carry 4-7 significant digits of float64 results that agree across runs of
# this code to about 1e-8 (output error's rtol 1e-10, deterministic CPU reductions): 1e-3
# relative passes a last digit rounded the other way at 4 digits only when the value sits
# within 1e-8 of a rounding boundary, and fails a changed result (a standard error 3.1x).
RTOL = 1e-3


def _text(cell) -> str:
    """The cell's printed text (stdout: warnings on stderr carry the kernel's file names)."""
    return "".join(o.get("text", "") for o in cell.get("outputs", [])
                   if o.get("output_type") == "stream" and o.get("name") == "stdout")


def _stale(committed: str, now: str) -> str | None:
    """None when `now` is `committed` up to RTOL on every number, else the first difference."""
    committed, now = DURATION.sub("<time>", committed), DURATION.sub("<time>", now)
    shape = lambda s: NUMBER.sub("#", s)  # noqa: E731
    if shape(committed) != shape(now):
        a, b = shape(committed).splitlines(), shape(now).splitlines()
        line = next((i for i, (x, y) in enumerate(zip(a, b)) if x != y), min(len(a), len(b)))
        return (f"line {line}: committed {committed.splitlines()[line:line + 1]}, "
                f"now {now.splitlines()[line:line + 1]}")
    for x, y in zip(NUMBER.findall(committed), NUMBER.findall(now)):
        u, v = float(x), float(y)
        if abs(u - v) > RTOL * max(abs(u), abs(v)):
            return f"committed {x}, now {y}"
    return None


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.name for p in NOTEBOOKS])
def test_notebook_executes(path):
    nbformat = pytest.importorskip("nbformat")
    nbclient = pytest.importorskip("nbclient")
    if path.name == "real_data.ipynb":  # it prints why and runs nothing without the data:
        # its committed outputs are the data's (notebooks/README.md: it skips itself)
        from mfmjax.datasets import daisy

        try:
            daisy("heating_system")
        except FileNotFoundError as err:
            pytest.skip(f"the DaISy heating system is not here: {err}")
    nb = nbformat.read(path, as_version=4)
    committed = [_text(c) for c in nb.cells if c.cell_type == "code"]
    nbclient.NotebookClient(nb, timeout=600, kernel_name="python3").execute()
    errors = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])
              if o.get("output_type") == "error"]
    assert not errors
    now = [_text(c) for c in nb.cells if c.cell_type == "code"]
    stale = [(i, d) for i, (a, b) in enumerate(zip(committed, now))
             if (d := _stale(a, b)) is not None]
    assert not stale, (f"{path.name}: committed outputs differ from this code's (code cell, "
                       f"first difference): {stale}; execute the notebook and commit it")


def test_stale_outputs_are_found():
    text = "a_2   3.582265e-02   2.700e-04\ncompile 9.3 s"
    assert _stale(text, "a_2   3.582265e-02   2.7001e-04\ncompile 12.0 s") is None
    assert "2.700e-04" in _stale(text, "a_2   3.582265e-02   8.446e-04\ncompile 9.3 s")
    assert _stale(text, "a_2   3.582265e-02   2.700e-04\nFAIL") is not None
