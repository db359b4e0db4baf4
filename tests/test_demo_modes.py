"""The forehearth demo in both modes (issue 17): figures, delay table, CLI --mode.

The full experiments take about 3 s each warm (plus ~40 s of compilation), so the figure tests
use the shortest horizon that yields models (3500 s: the first model after 8 intervals of 250 s
and a few re-identifications); the full-length claims (paper mode's numbers unchanged, delay
tracking) are in `test_online.py` and marked slow.
"""

import json
import math

import numpy as np
import pytest

from mfmjax._demo import delay_table, demo, residence_time
from mfmjax._plotting import broken_at_switches

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _png_size(path):
    """(width, height) from the IHDR chunk of a PNG file."""
    raw = path.read_bytes()
    assert raw[:8] == PNG_MAGIC and raw[12:16] == b"IHDR"
    return int.from_bytes(raw[16:20], "big"), int.from_bytes(raw[20:24], "big")


@pytest.mark.parametrize("mode", ["paper", "improved"])
def test_demo_figures_both_modes(tmp_path, capsys, mode):
    out = tmp_path / mode
    res = demo(str(out), horizon=3500.0, mode=mode)
    text = capsys.readouterr().out
    assert res["mode"] == mode and text.count("mean square prediction error") == 2
    assert text.count("true delay [s]") == 2  # the delay table of each experiment
    for ex in (1, 2):
        assert _png_size(out / f"experiment{ex}_inputs.png") == (1000, 600)
        assert _png_size(out / f"experiment{ex}_prediction.png") == (1000, 400)
    saved = json.loads((out / "results.json").read_text())
    assert saved["mode"] == mode
    for e in saved["experiments"]:
        assert len(e["delays"]) == len(e["models"]) >= 1
        for row in e["delays"]:  # the simulator's delay at that time (265-335 s)
            assert 260 <= row["true_delay"] <= 340


def test_demo_unknown_mode():
    with pytest.raises(ValueError, match="unknown mode 'fast'"):
        demo("unused", mode="fast")


def test_cli_demo_mode_paper(tmp_path, capsys):
    from mfmjax._cli import main

    assert main(["demo", "--out", str(tmp_path), "--horizon", "3000", "--mode", "paper"]) == 0
    assert json.loads((tmp_path / "results.json").read_text())["mode"] == "paper"
    assert main(["demo", "--mode", "bogus"]) == 2
    assert "--mode" in capsys.readouterr().err


def test_broken_at_switches_inserts_gaps():
    y = np.array([1.0, 2.0, 3.0, 4.0, 5.0])
    idx, yp = broken_at_switches(y, np.array([1, 1, 2, 2, 3]))
    # a NaN before the first sample of each new model (indices 2 and 4), nothing else changes
    np.testing.assert_array_equal(np.isnan(yp), [False, False, True, False, False, True, False])
    np.testing.assert_array_equal(yp[~np.isnan(yp)], y)
    np.testing.assert_array_equal(idx[~np.isnan(idx)], np.arange(5.0))


def test_residence_time_first_moment():
    # G(s) = (b0 + b1 s) e^{-s d} / (a0 + a1 s + s^2): -G'(0)/G(0) = d + a1/a0 - b1/b0
    rec = {"a": [0.5, 3.0, 1.0], "b": [[2.0, 4.0]], "delays": [100.0]}
    assert residence_time(rec, 0) == pytest.approx(100.0 + 6.0 - 2.0, rel=1e-15)
    # finite differences of G at s = 0 give the same first moment (derivation check)
    G = lambda s: (2.0 + 4.0 * s) * math.exp(-100.0 * s) / (0.5 + 3.0 * s + s * s)  # noqa: E731
    eps = 1e-6
    assert -(G(eps) - G(-eps)) / (2 * eps) / G(0) == pytest.approx(104.0, rel=1e-8)
    assert math.isnan(residence_time({"a": [0.0, 1.0], "b": [[1.0]], "delays": [0.0]}, 0))


def test_delay_table_interpolates_true_delay():
    data = {"t": np.array([0.0, 100.0]), "delay": np.array([260.0, 280.0])}
    rec = {"model": 1, "operating_point": "p1", "sim_start": 50.0, "a": [1.0, 1.0],
           "b": [[1.0]], "delays": [255.0]}
    row, = delay_table([rec], data)
    assert row["true_delay"] == 270.0 and row["delay"] == 255.0 and row["residence"] == 256.0
