"""`mfmjax report model.json data.csv -o dir/`: end to end on a small CSV written here."""

from __future__ import annotations

import json

import numpy as np
import pytest

import mfmjax
from mfmjax._cli import main

DT, T = 0.05, 1200
PNG = b"\x89PNG\r\n\x1a\n"
TRUE = dict(a=[1.0, 0.8, 1.0], b=[[1.0]], delays=[0.15], intersample=["zoh"],
            input_names=["valve"], output_name="temp")
COV = np.diag([2e-3, 1e-3, 1e-3])


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """A 2nd-order plant with a delay, white zoh input, 3 % white output noise (seed fixed)."""
    folder = tmp_path_factory.mktemp("report")
    model = mfmjax.Model.from_coefficients(TRUE["a"], TRUE["b"], delays=TRUE["delays"],
                                           intersample=TRUE["intersample"],
                                           input_names=TRUE["input_names"],
                                           output_name=TRUE["output_name"])
    rng = np.random.default_rng(3)
    u = rng.standard_normal(T)
    y = np.asarray(mfmjax.simulate(model, u, dt=DT))
    y = y + 0.03 * np.std(y) * rng.standard_normal(T)
    with open(folder / "data.csv", "w") as fh:
        fh.write("t,valve,temp\n")
        for k in range(T):
            fh.write(f"{DT * k!r},{float(u[k])!r},{float(y[k])!r}\n")
    mfmjax.save_model(model, folder / "model.json", covariance=COV)
    mfmjax.save_model(model, folder / "nocov.json")
    return folder, model


ARGS = ["--output", "temp", "--inputs", "valve", "--time", "t", "--intersample", "zoh"]


def _png(path):
    data = path.read_bytes()
    assert data[:8] == PNG and len(data) > 10_000, (path, len(data))


def test_report_writes_figures_and_json(files, capsys):
    folder, model = files
    out = folder / "out"
    rc = main(["report", str(folder / "model.json"), str(folder / "data.csv"), *ARGS,
               "--window", "10,59.95", "--lags", "20", "-o", str(out)])
    cap = capsys.readouterr()
    assert rc == 0, cap.err
    text = cap.out
    for name in ("compare", "residuals", "step", "bode"):
        _png(out / f"{name}.png")
    rep = json.loads((out / "report.json").read_text())
    sig = mfmjax.Signals.from_csv(folder / "data.csv", output="temp", inputs=["valve"],
                                  time="t", intersample="zoh")
    # the state from the observer over the first 20 % of the window, as the CLI's validation
    # lines (the Python functions' default is the whole window)
    ob = 0.2 * (59.95 - 10.0)
    cmp = mfmjax.compare(model, sig, (10.0, 59.95), observer_window=ob)
    res = mfmjax.residuals(model, sig, (10.0, 59.95), lags=20, observer_window=ob)
    assert rep["observer_window"] == pytest.approx(ob, rel=1e-12)
    assert rep["fit"] == pytest.approx(cmp.fit, rel=1e-12)
    assert rep["window"] == [pytest.approx(10.0), pytest.approx(59.95)]
    assert rep["residuals"]["lags"] == 20 and rep["residuals"]["N"] == res.e.size
    assert rep["residuals"]["whiteness"]["pass"] is True  # the true model on white noise
    assert rep["residuals"]["independence"]["valve"]["pass"] is True
    assert rep["residuals"]["whiteness"]["Q"] == pytest.approx(res.whiteness_stat, rel=1e-12)
    assert rep["bands"] is True and "99 %" in rep["bands_note"]
    assert rep["nyquist"] == pytest.approx(np.pi / float(sig.dt), rel=1e-15)  # marked in bode.png
    assert "whiteness" in text and "fit" in text


def test_report_without_covariance_says_no_bands(files, capsys):
    folder, _ = files
    out = folder / "plain"
    assert main(["report", str(folder / "nocov.json"), str(folder / "data.csv"), *ARGS,
                 "-o", str(out)]) == 0
    text = capsys.readouterr().out
    assert "no bands: the model file has no covariance" in text
    rep = json.loads((out / "report.json").read_text())
    assert rep["bands"] is False
    _png(out / "step.png")
    # `validate`'s form (FILE --model MODEL) works too and writes the same report
    again = folder / "plain-option"
    assert main(["report", str(folder / "data.csv"), "--model", str(folder / "nocov.json"),
                 *ARGS, "-o", str(again)]) == 0
    assert capsys.readouterr().out == text.replace(str(out), str(again))
    same = json.loads((again / "report.json").read_text())
    assert same.pop("figures").keys() == rep.pop("figures").keys() and same == rep


@pytest.mark.parametrize("extra,match", [
    (["--lags", "0"], "--lags"),
    (["--lags", "400"], "lags=400 is more than a quarter"),
    # named as the option (it said "observe(): window (50, 80) must lie ...")
    (["--window", "50,80"], "--window 50,80 must lie inside the record [0, 59.95]"),
    (["--observer-window", "-1"], "--observer-window"),
])
def test_report_user_errors_one_line_exit_2(files, capsys, extra, match):
    folder, _ = files
    rc = main(["report", str(folder / "model.json"), str(folder / "data.csv"), *ARGS,
               "-o", str(folder / "bad"), *extra])
    err = capsys.readouterr().err
    assert rc == 2 and match in err and err.count("\n") == 1, err


def test_report_missing_files(files, capsys):
    folder, _ = files
    assert main(["report", str(folder / "nope.json"), str(folder / "data.csv"), *ARGS,
                 "-o", str(folder / "bad")]) == 2
    assert "cannot read" in capsys.readouterr().err
    assert main(["report", str(folder / "model.json"), *ARGS, "-o", str(folder / "bad")]) == 2
    assert capsys.readouterr().err.startswith("error: ")


def test_search_estimate_save_keeps_the_covariance_for_report(files, capsys):
    """The CLI-only path: search --estimate --save writes SRIVC's covariance; report bands it.
    estimate's warnings reach stderr as `warning:` lines (the CLI silenced them) and its JSON
    keeps the chosen orders and every note (it kept neither): the true delay 0.15 lies beyond
    the grid (0.05, 0.1), and output error, fitting the delay from the grid's largest, moves
    it there (said, and warned: the structure was chosen at the grid's edge)."""
    folder, _ = files
    saved = folder / "estimated.json"
    assert main(["search", str(folder / "data.csv"), *ARGS, "--n", "2", "--m", "0", "--N", "4",
                 "--M", "4", "--h", "3", "--delays", "0.05,0.1", "--estimate", "--save",
                 str(saved), "--json"]) == 0
    cap = capsys.readouterr()
    edge = ("the delay of 'valve' was the largest of its grid (0.05..0.1), 0.1, and output "
            "error moved it beyond")
    said = [ln for ln in cap.err.splitlines() if ln.startswith("warning: estimate(): ")]
    assert len(said) == 1 and edge in said[0], cap.err
    est = json.loads(cap.out)["estimated"]
    assert (est["n"], est["m"]) == (2, [0]) and any(edge in note for note in est["notes"])
    # the delay picked from the grid is then fitted with the parameters, its std error kept
    assert est["method"] == "srivc + output error" and est["delay_std_errors"][0] > 0
    assert abs(est["model"]["delays"][0] - 0.15) < 4 * est["delay_std_errors"][0]
    doc = json.loads(saved.read_text())
    assert doc["covariance"]["names"] == ["a_0", "a_1", "b_10"]
    # the fitted delay's share is saved with it, and the report's bands hold it (they held
    # the delay known, unsaid: a phase band 7.5x too narrow at w = 10 in an audit's case)
    assert doc["joint_covariance"]["names"] == ["a_0", "a_1", "b_10", "delay valve"]
    joint = np.array(doc["joint_covariance"]["matrix"])
    assert joint[3, 3] == pytest.approx(est["delay_std_errors"][0] ** 2, rel=1e-9)
    np.testing.assert_array_equal(joint[:3, :3], doc["covariance"]["matrix"])
    assert main(["report", str(saved), str(folder / "data.csv"), *ARGS, "-o",
                 str(folder / "est")]) == 0
    assert json.loads((folder / "est" / "report.json").read_text())["bands"] is True
    assert "the fitted delays' uncertainty included" in capsys.readouterr().out


def test_report_of_detrended_data_says_its_curves_are_deviations(files, capsys, monkeypatch):
    """With --detrend, compare.png plots deviations from the removed line but read as the
    signal itself ("T_degC" over -70..0 for a plate near 140 degC: a DaISy heater report);
    the output's name now says what is plotted, in the figure and the summary."""
    folder, _ = files
    saved, out = folder / "detrended.json", folder / "dev"
    assert main(["identify", str(folder / "data.csv"), *ARGS, "--n", "2", "--N", "4", "--M",
                 "4", "--h", "1.5", "--delays", "0.15", "--detrend", "constant", "--save",
                 str(saved)]) == 0
    capsys.readouterr()
    level = np.mean(np.loadtxt(folder / "data.csv", delimiter=",", skiprows=1)[:, 2])
    assert main(["report", str(saved), str(folder / "data.csv"), *ARGS, "--detrend",
                 "constant", "-o", str(out)]) == 0
    assert f"compare temp - {float(level):.6g} (deviation) on " in capsys.readouterr().out
    _png(out / "compare.png")
    # and validate --plot, which plotted the same deviations as "measured temp" (a review)
    from matplotlib.figure import Figure

    labels, save = [], Figure.savefig

    def saved_fig(fig, *a, **k):
        labels.append([(ax.get_ylabel(), [t.get_text() for t in ax.get_legend().get_texts()])
                       for ax in fig.axes])
        return save(fig, *a, **k)

    monkeypatch.setattr(Figure, "savefig", saved_fig)
    assert main(["validate", str(saved), str(folder / "data.csv"), *ARGS, "--detrend",
                 "constant", "--plot", str(folder / "dev.png")]) == 0
    name = f"temp - {float(level):.6g} (deviation)"
    assert labels[0][0][0] == name and labels[0][0][1][0] == f"measured {name}", labels


def test_cli_warnings_spell_windows_as_the_commands_options(files, capsys):
    """observe()'s advice "start the window at 0.15 or later (window=(t_start, t_end))" is
    the Python spelling; on the command line it names --window (validate/report)."""
    folder, _ = files
    assert main(["validate", str(folder / "model.json"), str(folder / "data.csv"), *ARGS,
                 "--window", "0,59.95"]) == 0
    err = capsys.readouterr().err
    assert "start the window at 0.15 or later (--window T0,T1)" in err, err
    assert "window=(" not in err
