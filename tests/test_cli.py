import json
import os
import re
import subprocess
import sys

import numpy as np
import pytest
from conftest import SHARED

from mfmjax._cli import main
from mfmjax.datasets import simulated_experiment, third_order_two_input


@pytest.fixture(scope="module")
def csv_file(tmp_path_factory):
    sig = simulated_experiment(third_order_two_input(), dt=0.01, n_samples=2000)
    p = tmp_path_factory.mktemp("cli") / "rec.csv"
    y, u = np.asarray(sig.y), np.asarray(sig.u)
    with open(p, "w") as fh:
        fh.write("t,temp,u1,u2\n")
        for k in range(len(y)):
            fh.write(f"{0.01 * k!r},{float(y[k])!r},{float(u[k, 0])!r},{float(u[k, 1])!r}\n")
    return p


ARGS = ["--output", "temp", "--inputs", "u1,u2", "--n", "3", "--m", "1,0", "--N", "4",
        "--M", "5", "--h", "2.0", "--time", "t", "--intersample", "foh,zoh"]


def test_identify_says_when_its_inputs_are_linearly_dependent(csv_file, tmp_path, capsys):
    """The CLI silenced identify's warnings, so two columns of one signal (a valve in 0-1 and
    in %) gave status ill_conditioned and gains 2248.7 and -22.47, but not why; the warning
    that names the inputs is now printed (one line, after the results)."""
    lines = csv_file.read_text().splitlines()
    rows = [line.split(",") for line in lines[1:]]
    dep = tmp_path / "dep.csv"
    dep.write_text("t,temp,u1,u1_pct\n" + "".join(
        f"{r[0]},{r[1]},{r[2]},{100.0 * float(r[2])!r}\n" for r in rows))
    argv = ["identify", str(dep), *ARGS]
    argv[argv.index("u1,u2")] = "u1,u1_pct"
    argv[argv.index("foh,zoh")] = "foh,foh"  # one signal, one rule
    assert main(argv) == 0
    cap = capsys.readouterr()
    assert "ill_conditioned" in cap.out
    assert ("warning: identify(): the inputs ['u1', 'u1_pct'] are linearly dependent"
            in cap.err), cap.err
    assert main(["identify", str(csv_file), *ARGS]) == 0
    cap = capsys.readouterr()
    assert "linearly dependent" not in cap.err
    # the record line says how each input is read between samples (the rule moves the model;
    # the text output never said it), and when that rule is the default
    assert (f"{csv_file}: 2000 samples, dt=0.01, K=2, inputs read as foh,zoh between samples\n"
            in cap.out), cap.out
    argv = ["identify", str(csv_file), *ARGS]
    del argv[argv.index("--intersample"): argv.index("--intersample") + 2]
    assert main(argv) == 0
    assert ("K=2, inputs read as foh,foh between samples (the default; --intersample zoh for "
            "inputs held between samples)" in capsys.readouterr().out)
    # following that advice: one value is every input's (it was refused on K = 2: "intersample
    # needs one entry per input (2), got 1")
    assert main(argv + ["--intersample", "zoh"]) == 0
    assert "K=2, inputs read as zoh,zoh between samples\n" in capsys.readouterr().out


def test_times_of_an_epoch_record_print_in_full(csv_file, tmp_path, capsys):
    """Windows and the detrend lines' t0 printed with %g read "validation on [1.7e+09,
    1.7e+09]" and "(t-1.7e+09)" for epoch-second times; now to 15 digits."""
    lines = csv_file.read_text().splitlines()
    epoch = tmp_path / "epoch.csv"
    epoch.write_text(lines[0] + "\n" + "".join(
        f"{1.7e9 + float(r.split(',')[0])!r},{r.split(',', 1)[1]}\n" for r in lines[1:]))
    assert main(["identify", str(epoch), *ARGS, "--identify-window", "1700000000,1700000012",
                 "--validate-window", "1700000012.5,1700000019.99", "--detrend",
                 "constant"]) == 0
    cap = capsys.readouterr()
    assert "validation on [1700000012.5, 1700000019.99]" in cap.out, cap.out
    assert "(fitted on --identify-window 1700000000,1700000012)" in cap.err, cap.err


def test_identify_json(csv_file, capsys):
    assert main(["identify", str(csv_file), *ARGS, "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    for key in ("a", "b", "n", "m", "N", "M", "h", "J"):
        assert key in out
    assert out["n"] == 3 and out["m"] == [1, 0] and out["a"][-1] == 1.0
    true = [1.0, 3.5, 3.5, 1.0]
    assert np.allclose(out["a"], true, rtol=5e-5)
    assert np.allclose(out["b"][0], [1.0, 0.5], rtol=5e-5)


def test_identify_table(csv_file, capsys):
    assert main(["identify", str(csv_file), *ARGS]) == 0
    got = capsys.readouterr()
    assert "a_0" in got.out and "b_11" in got.out and "cond(G_eq)" in got.out
    # the default offset rule's decision is said (on stderr, as --detrend's note)
    assert "note: no offset term (auto: the output has its mean within 2 standard " in got.err
    assert main(["identify", str(csv_file), *ARGS, "--no-offset"]) == 0
    assert "offset" not in capsys.readouterr().err  # the user chose


@pytest.mark.parametrize(
    "extra,match",
    [
        (["--inputs", "u1,nope"], "unknown column 'nope'"),
        (["--N", "2"], "N must be >= n"),
        (["--m", "4,0"], "exceeds n=3"),
        (["--m", "1,0,0"], "m has 3 entries"),
        (["--h", "-1"], "h must be > 0"),
        (["--h", "19.95"], "too short"),
        (["--delays", "0,-1"], "delays must be"),
        # a list starting with a minus was taken for an option by argparse ("expected one
        # argument"), the range check never reached (an audit of 2026-11-28)
        (["--delays", "-1,0"], "delays must be"),
        (["--intersample", "foh,cubic"], "unknown intersample mode"),
        (["--delays", "0,x"], "--delays: expected comma-separated numbers"),
    ],
)
def test_identify_user_errors(csv_file, capsys, extra, match):
    args = list(ARGS)
    for k in range(0, len(extra), 2):
        if extra[k] in args:
            i = args.index(extra[k])
            args[i + 1] = extra[k + 1]
        else:
            args += extra[k : k + 2]
    assert main(["identify", str(csv_file), *args]) == 2
    err = capsys.readouterr().err.strip()
    assert match in err and len(err.splitlines()) == 1


def test_a_file_name_after_the_separator_may_start_with_a_minus(csv_file, tmp_path, capsys,
                                                                monkeypatch):
    """Values that start with a minus are glued to their option ("--delays -1,0" reached
    argparse as an option); "--" itself is no option: a file "-1.csv" after it was glued
    into "--=-1.csv" and the file went missing (a review of 2026-11-28)."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "-1.csv").write_text(csv_file.read_text())
    assert main(["identify", *ARGS, "--json", "--", "-1.csv"]) == 0
    assert json.loads(capsys.readouterr().out)["n"] == 3


def test_cli_process_one_line_exit_2(tmp_path):
    r = subprocess.run([sys.executable, "-m", "mfmjax._cli", "identify", str(tmp_path / "x.csv"),
                        "--output", "y", "--n", "2", "--N", "3", "--M", "3", "--h", "1",
                        "--dt", "1"], capture_output=True, text=True)
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1
    assert "Traceback" not in r.stderr
    r = subprocess.run([sys.executable, "-m", "mfmjax._cli", "identify", "--bogus"],
                       capture_output=True, text=True)
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1


def test_demo_user_error(capsys):
    assert main(["demo", "--horizon", "100"]) == 2
    assert "--horizon" in capsys.readouterr().err


def test_dataset_cli(tmp_path, capsys):
    from mfmjax._signals import read_csv

    p = tmp_path / "fh.csv"
    assert main(["dataset", "forehearth", "--experiment", "2", "-o", str(p)]) == 0
    # the held pressure is named: read as foh (the CLI's default) it gives another model
    assert "read with --intersample foh,zoh" in capsys.readouterr().out
    cols = read_csv(p)
    assert list(cols) == ["time", "zone_temperature", "previous_zone_temperature",
                          "mixture_pressure"]  # the pull rate is not measured
    assert cols["time"].size == 9501
    assert main(["dataset", "nope", "-o", str(p)]) == 2


@pytest.mark.skipif(not os.path.isdir(os.path.join(SHARED, "daisy-heat-exchanger")),
                    reason="shared data not present")
def test_real_heat_exchanger(capsys):
    path = os.path.join(SHARED, "daisy-heat-exchanger", "exchanger.dat")
    assert main(["identify", path, "--names", "t,q,theta", "--time", "t", "--output", "theta",
                 "--inputs", "q", "--n", "1", "--m", "0", "--N", "3", "--M", "4", "--h", "40",
                 "--offset", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    # first-order local model: stable, negative gain (more flow -> lower outlet temperature)
    assert out["status"] == "ok" and out["a"][0] > 0 and out["b"][0][0] < 0


@pytest.mark.skipif(not os.path.isdir(os.path.join(SHARED, "daisy-heat-exchanger")),
                    reason="shared data not present")
def test_identify_prints_an_unstable_model_whose_validation_fails(tmp_path, capsys):
    """The heat exchanger in kelvin, n = 2, m = 0: the model is unstable (a_0 < 0) and the
    validation window cannot use it (its response overflows float64, or its state is not
    observable). The model is printed with its status and the validation line says why there
    is no fit (before: `observe()`'s overflow error as a user error, exit 2, and no model).
    (m = 1 gave the unstable model while eq. (11)'s constraint counted the offset, whose value
    carries the kelvin level; since 2026-11-27 the default leaves it out and m = 1 fits 42.65 %
    in kelvin as in degC.)"""
    data = np.loadtxt(os.path.join(SHARED, "daisy-heat-exchanger", "exchanger.dat"))
    path = tmp_path / "kelvin.csv"
    np.savetxt(path, np.column_stack([data[:, 0], data[:, 1], data[:, 2] + 273.15]),
               delimiter=",", header="t,q,theta", comments="", fmt="%.10g")
    assert main(["identify", str(path), "--time", "t", "--output", "theta", "--inputs", "q",
                 "--n", "2", "--m", "0", "--N", "4", "--M", "4", "--h", "40", "--offset",
                 "--identify-window", "1,2667", "--validate-window", "2668,4000"]) == 0
    out = capsys.readouterr().out
    assert "status                unstable" in out and "a_0" in out
    # which of the two the observer meets depends on the last digits of the data (a 9-digit
    # and a 10-digit CSV of the same record differ here): either way no fit, and why
    assert any(f"validation on [2668, 4000]: none, the model's {why}" in out for why in (
        "response overflows float64", "state is not observable"))


def test_validate_compares_columns_really_named_like_the_defaults(csv_file, tmp_path, capsys):
    """A CSV whose columns are named y, u1, u2: the saved model's names looked like a model
    without names (the defaults), so validating with the inputs swapped gave fit 69 % against
    99 % with nothing said. The file now records that the names are the CSV's columns."""
    rows = csv_file.read_text().splitlines()
    named = tmp_path / "named.csv"
    named.write_text("\n".join(["t,y,u1,u2"] + rows[1:]) + "\n")
    model_path = tmp_path / "m.json"
    args = [a if a != "temp" else "y" for a in ARGS]
    assert main(["identify", str(named), *args, "--save", str(model_path)]) == 0
    capsys.readouterr()
    common = [str(named), "--output", "y", "--time", "t", "--model", str(model_path)]
    assert main(["validate", *common, "--inputs", "u2,u1"]) == 0
    assert ("note: the model was identified from y <- u1, u2; these data are y <- u2, u1"
            in capsys.readouterr().err)
    assert main(["validate", *common, "--inputs", "u1,u2"]) == 0
    assert "note:" not in capsys.readouterr().err
    # --plot without an extension: matplotlib writes fig.png, and the JSON said "fig"
    assert main(["validate", *common, "--inputs", "u1,u2", "--plot", str(tmp_path / "fig"),
                 "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["plot"] == str(tmp_path / "fig.png")
    assert (tmp_path / "fig.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_validate_and_report_say_when_the_columns_differ_from_the_models(csv_file, tmp_path,
                                                                         capsys):
    """A saved model names its columns; `validate` and `report` on data whose columns are
    named otherwise (here the inputs swapped) say so on stderr after their results (a heating
    system's model validated on a heat exchanger's columns gave fit -4857 % with nothing
    said). The same columns: no note."""
    model_path = tmp_path / "model.json"
    assert main(["identify", str(csv_file), *ARGS, "--save", str(model_path)]) == 0
    capsys.readouterr()
    common = [str(csv_file), "--output", "temp", "--time", "t", "--model", str(model_path)]
    assert main(["validate", *common, "--inputs", "u1,u2"]) == 0
    assert "note:" not in capsys.readouterr().err
    assert main(["validate", *common, "--inputs", "u2,u1"]) == 0
    assert ("note: the model was identified from temp <- u1, u2; these data are temp <- u2, u1"
            in capsys.readouterr().err)
    assert main(["report", *common, "--inputs", "u2,u1", "-o", str(tmp_path / "rep")]) == 0
    assert "these data are temp <- u2, u1" in capsys.readouterr().err
    # --delays and --intersample other than the model's are said not to be used (the model's
    # are); they were ignored without a word
    assert main(["validate", *common, "--inputs", "u1,u2", "--delays", "0.5,0",
                 "--intersample", "zoh,zoh"]) == 0
    err = capsys.readouterr().err
    assert "note: --delays 0.5,0.0 is not used: the model's own (0,0) are" in err
    assert "note: --intersample zoh,zoh is not used: the model's own (foh,zoh) are" in err
    assert "warning: observe()" not in err  # the note says it (not the library's warning too)
    assert main(["validate", *common, "--inputs", "u1,u2", "--delays", "0,0"]) == 0  # its own
    assert "not used" not in capsys.readouterr().err
    # --offset / --no-offset against the model's own term: said not to be used (silent before)
    from mfmjax import load_model

    own = load_model(str(model_path)).has_offset
    flag = "--no-offset" if own else "--offset"
    assert main(["validate", *common, "--inputs", "u1,u2", flag]) == 0
    assert f"note: {flag} is not used: the model has" in capsys.readouterr().err
    # data read unlike the model's (saved with it: dt and --detrend): a model of detrended
    # data validated on the raw record gave fit -23434 %, one of a time column in seconds on
    # minutes -2 %, both with nothing said
    assert json.loads(model_path.read_text())["record"] == {
        "dt": 0.01, "detrend": None, "columns": ["temp", "u1", "u2"]}
    assert main(["validate", *common, "--inputs", "u1,u2", "--detrend", "linear"]) == 0
    assert ("note: the model was identified on data read without --detrend; these data are "
            "read with --detrend linear: drop --detrend") in capsys.readouterr().err
    scaled = tmp_path / "scaled.csv"
    rows = csv_file.read_text().splitlines()
    scaled.write_text("\n".join([rows[0]] + [f"{float(r.split(',', 1)[0]) * 100!r},"
                                              f"{r.split(',', 1)[1]}" for r in rows[1:]]))
    assert main(["report", str(model_path), str(scaled), "--output", "temp", "--inputs", "u1,u2",
                 "--time", "t", "-o", str(tmp_path / "rep2")]) == 0
    err = capsys.readouterr().err
    assert "note: the model was identified on data sampled at dt=0.01; these data have dt=1" in err
    # a sample counter read as time (an audit of 2026-11-28: --time k on 1, 2, 3, ...): the
    # fix the note names
    assert "if --time names a sample counter, read the file with --dt 0.01 instead" in err
    # identify on such a file has no model to compare with: the counter's name says it (the
    # model came out per sample, unsaid); a column named as a time says nothing
    counted = tmp_path / "counted.csv"
    counted.write_text("\n".join(["k,temp,u1,u2"] + [f"{k + 1},{r.split(',', 1)[1]}"
                                                      for k, r in enumerate(rows[1:])]))
    argv = ["identify", str(counted), *ARGS]
    argv[argv.index("--time") + 1], argv[argv.index("--h") + 1] = "k", "200"
    assert main(argv) == 0
    assert ("note: --time k counts samples (step 1), so the model's time unit is one sample"
            in capsys.readouterr().err)
    assert main(["identify", str(csv_file), *ARGS]) == 0
    assert "counts samples" not in capsys.readouterr().err
    detrended = tmp_path / "detrended.json"
    assert main(["identify", str(csv_file), *ARGS, "--detrend", "linear", "--save",
                 str(detrended)]) == 0
    capsys.readouterr()
    assert main(["validate", str(detrended), str(csv_file), "--output", "temp", "--inputs",
                 "u1,u2", "--time", "t"]) == 0
    assert ("note: the model was identified on data read with --detrend linear (the model is "
            "for deviations from those lines); these data are read as they are: give "
            "--detrend linear as then") in capsys.readouterr().err
    # the saved lines are read at this file's times: under --dt they start at 0 in each file,
    # wherever it lies on the identification record's clock (the DaISy heater's hold-out file
    # fitted 58.3 % under --dt 2 and 21.5 % under --time time), said; on that clock (time
    # columns in both commands, or the same file read from the same first time), nothing
    later = tmp_path / "later.csv"
    rows = csv_file.read_text().splitlines()
    later.write_text("\n".join([rows[0], *rows[1201:]]) + "\n")  # t from 12
    cols = ["--output", "temp", "--inputs", "u1,u2", "--detrend", "linear"]
    for file, clock in ((csv_file, ["--time", "t"]), (csv_file, ["--dt", "0.01"]),
                        (later, ["--time", "t"])):
        assert main(["validate", str(detrended), str(file), *cols, *clock]) == 0
        assert "warning: --detrend linear" not in capsys.readouterr().err, (file, clock)
    assert main(["validate", str(detrended), str(later), *cols, "--dt", "0.01"]) == 0
    assert ("warning: --detrend linear: the model's lines start at t=0 and are evaluated at "
            "this file's times, which start at t=0 (--dt: the first row is t=0): the result "
            "depends on") in capsys.readouterr().err
    # two time columns, but this file's clock restarts before the lines' start (a hold-out
    # log from 0 of a model identified on times 12..: fit -788 % unsaid in a review)
    late = tmp_path / "late.json"
    assert main(["identify", str(later), *ARGS, "--detrend", "linear", "--save", str(late)]) == 0
    capsys.readouterr()
    assert main(["validate", str(late), str(csv_file), *cols, "--time", "t"]) == 0
    assert ("warning: --detrend linear: the model's lines start at t=12 and are evaluated at "
            "this file's times, which start at t=0: the result") in capsys.readouterr().err


def test_validate_and_report_use_the_validation_lines_observer(tmp_path, capsys):
    """`validate` and `report` estimate the state from the first 20 % of the window, as the
    validation line of `identify`/`search` does, and print and save which: the same model on
    the same window gives the same E and fit % in all three (they used the whole window, the
    least-squares x0 for the very data scored, hence a smaller E: a DaISy heating model read
    fit 84.8 % in `validate` against -5.1 % in `identify`'s line). `--observer-window` still
    chooses; the whole window gives the smaller E (it is the least-squares x0 there)."""
    sig = simulated_experiment(third_order_two_input(), dt=0.01, n_samples=2000, seed=4,
                               noise_std=0.05)
    path = tmp_path / "noisy.csv"
    np.savetxt(path, np.column_stack([0.01 * np.arange(2000), np.asarray(sig.y),
                                      np.asarray(sig.u)]),
               delimiter=",", header="t,temp,u1,u2", comments="", fmt="%.17g")
    model_path, cols = tmp_path / "m.json", ["--output", "temp", "--inputs", "u1,u2", "--time",
                                             "t", "--intersample", "foh,zoh"]
    assert main(["identify", str(path), *ARGS[4:14], *cols, "--identify-window", "0,13",
                 "--validate-window", "13,19.99", "--save", str(model_path), "--json"]) == 0
    line = json.loads(capsys.readouterr().out)["validation"]
    assert main(["validate", str(model_path), str(path), *cols, "--window", "13,19.99",
                 "--json"]) == 0
    val = json.loads(capsys.readouterr().out)
    assert val["observer_window"] == pytest.approx(0.2 * 6.99) == line["observer_window"]
    assert val["E"] == pytest.approx(line["E"], rel=1e-12)
    assert val["fit"] == pytest.approx(line["fit"], rel=1e-12)
    assert main(["report", str(model_path), str(path), *cols, "--window", "13,19.99",
                 "-o", str(tmp_path / "rep")]) == 0
    assert "observer over the first 1.398 of the window" in capsys.readouterr().out
    rep = json.loads((tmp_path / "rep" / "report.json").read_text())
    assert rep["observer_window"] == val["observer_window"]
    assert rep["fit"] == pytest.approx(val["fit"], rel=1e-12)
    assert main(["validate", str(model_path), str(path), *cols, "--window", "13,19.99",
                 "--observer-window", "6.99", "--json"]) == 0
    whole = json.loads(capsys.readouterr().out)
    assert whole["observer_window"] == 6.99 and whole["E"] < val["E"]


def test_identify_save_and_validate(csv_file, tmp_path, capsys):
    model_path = tmp_path / "model.json"
    assert main(["identify", str(csv_file), *ARGS, "--save", str(model_path)]) == 0
    capsys.readouterr()
    png = tmp_path / "v.png"
    assert main(["validate", str(csv_file), "--output", "temp", "--inputs", "u1,u2", "--time",
                 "t", "--model", str(model_path), "--window", "2,18", "--plot", str(png),
                 "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["fit"] > 99.99 and res["E"] >= 0 and len(res["x0"]) == 3
    assert res["window"] == [2.0, 18.0]
    import matplotlib.image as mpimg

    img = mpimg.imread(png)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and img.shape[:2] == (350, 800)
    # the measured and simulated curves were drawn: many non-white pixels
    assert np.mean(img[..., :3] < 0.9) > 0.01
    assert main(["validate", str(csv_file), "--output", "temp", "--inputs", "u1,u2", "--time",
                 "t", "--model", str(model_path)]) == 0
    first = capsys.readouterr().out
    assert "fit" in first
    # `report`'s form (MODEL FILE) works too, with the same result; the model given twice or
    # not at all is a one-line user error (exit 2)
    cols = ["--output", "temp", "--inputs", "u1,u2", "--time", "t"]
    assert main(["validate", str(model_path), str(csv_file), *cols]) == 0
    assert capsys.readouterr().out == first
    for args in ([str(csv_file)], [str(model_path), str(csv_file), "--model", str(model_path)]):
        assert main(["validate", *args, *cols]) == 2
        err = capsys.readouterr().err.strip()
        assert err == "error: give the model JSON once: MODEL FILE, or FILE --model MODEL"


@pytest.mark.parametrize(
    "extra,content,match",
    [
        (["--window", "0,50"], None, "must lie inside the record"),
        (["--window", "1,2,3"], None, "--window: expected T0,T1"),
        ([], '{"format": "other"}', "not an mfmjax model file"),
        ([], '{"format": "mfmjax-model", "version": 2}', "version 2"),
        (["--inputs", "u1"], None, "model has 2 inputs"),
    ],
)
def test_validate_user_errors(csv_file, tmp_path, capsys, extra, content, match):
    model_path = tmp_path / "model.json"
    if content is None:
        assert main(["identify", str(csv_file), *ARGS, "--save", str(model_path)]) == 0
    else:
        model_path.write_text(content)
    capsys.readouterr()
    args = ["validate", str(csv_file), "--output", "temp", "--inputs", "u1,u2", "--time", "t",
            "--model", str(model_path)]
    if extra[:1] == ["--inputs"]:
        args[args.index("--inputs") + 1] = extra[1]
        extra = []
    assert main(args + extra) == 2
    err = capsys.readouterr().err.strip()
    assert match in err and len(err.splitlines()) == 1


def test_search_cli(csv_file, tmp_path, capsys):
    best = tmp_path / "best.json"
    assert main(["search", str(csv_file), "--output", "temp", "--inputs", "u1,u2", "--time", "t",
                 "--intersample", "foh,zoh", "--n", "2:3", "--m", "0:1;0", "--N", "4", "--M",
                 "4:5", "--h", "1.5", "--delays", "0,0.01", "--top", "3", "--json", "--save",
                 str(best)]) == 0
    cap = capsys.readouterr()
    out = json.loads(cap.out)
    # 4 structures x 8 groups (M x both inputs' delays): one grid for each input, which
    # identify would read as one delay per input, so a note says how to give that
    assert out["candidates"] == 32 and len(out["ranked"]) == 3
    assert "note: --delays 0,0.01 is searched as one grid for each of the 2 inputs; for a delay " \
        "per input, as identify reads it, give one grid per input separated by ';' (0;0.01)" \
        in cap.err
    assert out["ranked"][0]["n"] == 3 and out["ranked"][0]["m"] == [1, 0]
    assert out["ranked"][0]["delays"] == [0.0, 0.0]
    import mfmjax

    assert mfmjax.load_model(best).n == 3


def test_search_notes_a_single_delay_grid_for_several_inputs(capsys):
    """One --delays grid, even a single value, is searched for every input ("0.5" with two
    inputs: both delayed 0.5, where identify refuses the text); a grid per input, or one
    input, needs no note."""
    from mfmjax._cli import _delays_grid_note

    _delays_grid_note("0.5", 2)
    assert "note: --delays 0.5 is searched as one grid for each of the 2 inputs" in \
        capsys.readouterr().err
    for text, K in (("0.5", 1), ("0.5;0", 2), ("0,1", 1), (None, 2)):
        _delays_grid_note(text, K)
        assert capsys.readouterr().err == "", (text, K)


def test_search_with_a_validation_window_ranks_on_the_identification_window(csv_file, capsys):
    """`search --identify-window A --validate-window B` without `--validate` ranked the
    candidates by E over the whole record, B included, and then reported B's fit as data the
    model was not fitted on (a practitioner's dryer record: the winner changed and its
    "held-back" fit fell from 15.4 to 5.2 % once B was left out). It now ranks on A, as
    `search(identify=A, validate=A)`, and says so on stderr."""
    import mfmjax

    grid = ["--n", "2:3", "--m", "0:1;0", "--N", "4", "--M", "4:5", "--h", "1.5,2"]
    assert main(["search", str(csv_file), "--output", "temp", "--inputs", "u1,u2", "--time", "t",
                 "--intersample", "foh,zoh", *grid, "--identify-window", "0,12",
                 "--validate-window", "12.5,19.99", "--json"]) == 0
    cap = capsys.readouterr()
    assert "note: candidates ranked by E on --identify-window 0,12" in cap.err
    out = json.loads(cap.out)
    sig = mfmjax.Signals.from_csv(csv_file, output="temp", inputs=["u1", "u2"], time="t",
                                  intersample=("foh", "zoh"))
    ref = mfmjax.search(sig, n=(2, 3), m=[(0, 1), (0,)], N=4, M=(4, 5), h=(1.5, 2.0),
                        identify=(0.0, 12.0), validate=(0.0, 12.0), observer_window=0.2 * 12.0)
    assert [r["E"] for r in out["ranked"]] == pytest.approx(
        [ref.row(i)["E"] for i in range(len(out["ranked"]))], rel=1e-12)
    assert out["validation"]["window"] == [12.5, 19.99]
    assert out["observer_window"] == pytest.approx(0.2 * 12.0, rel=1e-15)


def test_search_measures_E_as_validate_does(tmp_path, capsys):
    """`search --validate A` scores E with the initial state observed over the first 20 % of A
    (or `--observer-window`), as `validate --window A` measures a saved model: the two print
    the same E for the search's winner (before, the search's observer ran over all of A, a
    flattering fit that `validate` did not reproduce). A noisy record, so that E is well above
    rounding; the same observer and simulation (eq. 14-17) in two programs: 1e-9 relative. The
    whole-window observer's E differs from it by far more (checked: the test tells them
    apart)."""
    import mfmjax

    sig = simulated_experiment(third_order_two_input(), dt=0.01, n_samples=2000, noise_std=0.05,
                               seed=7)
    path = tmp_path / "noisy.csv"
    t = 0.01 * np.arange(2000)
    np.savetxt(path, np.column_stack([t, np.asarray(sig.y), np.asarray(sig.u)]), delimiter=",",
               header="t,temp,u1,u2", comments="", fmt="%.17g")
    best = tmp_path / "best.json"
    common = [str(path), "--output", "temp", "--inputs", "u1,u2", "--time", "t",
              "--intersample", "foh,zoh"]
    for extra, ob in (([], 0.2 * 7.0), (["--observer-window", "3"], 3.0)):
        assert main(["search", *common, "--n", "2:3", "--m", "0:1;0", "--N", "4", "--M", "5",
                     "--h", "2", "--validate", "12,19", *extra, "--json", "--save",
                     str(best)]) == 0
        out = json.loads(capsys.readouterr().out)
        assert out["observer_window"] == pytest.approx(ob, rel=1e-15)
        assert main(["validate", *common, "--model", str(best), "--window", "12,19", *extra,
                     "--json"]) == 0
        val = json.loads(capsys.readouterr().out)
        E = out["ranked"][0]["E"]
        assert E > 1e-3 and val["E"] == pytest.approx(E, rel=1e-9, abs=0)
        whole = float(mfmjax.observe(mfmjax.load_model(best), mfmjax.Signals.from_csv(
            path, output="temp", inputs=["u1", "u2"], time="t", intersample=("foh", "zoh")),
            (12.0, 19.0)).E)
        assert abs(whole - E) > 1e-6 * E
    # a given observer is checked in the CLI's terms
    assert main(["search", *common, "--h", "2", "--validate", "12,19",
                 "--observer-window", "0.05"]) == 2
    assert "--observer-window 0.05 must hold at least 8 samples (>= 0.07 at dt = 0.01)" in \
        capsys.readouterr().err
    assert main(["search", *common, "--h", "2", "--estimate", "--observer-window", "3"]) == 2
    assert "--observer-window sets the observer" in capsys.readouterr().err


def test_search_short_record_and_no_inputs_notes(csv_file, tmp_path, capsys):
    """A whole record too short for a 20 % observer (30 samples: 7 in its first 20 %, the
    observer needs 8) is still searched, E with the state observed over all of it (the search's
    own default), and a note says so (the 20 % rule refused it first). Without --inputs the
    model is the output's alone, the file's other columns unused: a note names them. And a
    record without input is searched (K = 0: the search's reshapes could not infer an empty
    axis and raised ZeroDivisionError inside JAX)."""
    rows = csv_file.read_text().splitlines()
    short = tmp_path / "short.csv"
    short.write_text("\n".join(rows[:31]) + "\n")
    assert main(["search", str(short), "--output", "temp", "--inputs", "u1,u2", "--time", "t",
                 "--n", "1", "--N", "3", "--M", "3", "--h", "0.1", "--json"]) == 0
    cap = capsys.readouterr()
    assert "too short for an initial-state observer over its first 20 %" in cap.err
    assert json.loads(cap.out)["observer_window"] == pytest.approx(0.29, rel=1e-12)
    assert main(["search", str(csv_file), "--output", "temp", "--time", "t", "--n", "1:2",
                 "--N", "3", "--M", "3", "--h", "2", "--json"]) == 0
    cap = capsys.readouterr()
    assert "note: no --inputs: a model of temp alone" in cap.err
    assert "the file's columns u1, u2 are not used" in cap.err
    assert json.loads(cap.out)["candidates"] == 2


@pytest.mark.parametrize(
    "extra,match",
    [
        (["--n", "5:3"], "--n: empty range '5:3'"),
        (["--h", "a,b"], "--h: expected comma-separated numbers"),
        (["--h", "50"], "too few valid samples"),
        (["--m", "0;0;0"], "--m: give one grid per input"),
        (["--n", "1:2:3"], "--n: expected a range"),
    ],
)
def test_search_cli_errors(csv_file, capsys, extra, match):
    args = ["search", str(csv_file), "--output", "temp", "--inputs", "u1,u2", "--time", "t",
            "--h", "1.5"]
    for k in range(0, len(extra), 2):
        if extra[k] in args:
            args[args.index(extra[k]) + 1] = extra[k + 1]
        else:
            args += extra[k : k + 2]
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert match in err and len(err.splitlines()) == 1


def test_identify_and_search_refine(csv_file, capsys, tmp_path):
    import mfmjax

    saved = tmp_path / "refined.json"
    assert main(["identify", str(csv_file), *ARGS, "--refine", "--json", "--save",
                 str(saved)]) == 0
    out = json.loads(capsys.readouterr().out)
    ref = out["refined"]
    # the JSON carries the model it saved and validated (its top level is the MFM start)
    kept = mfmjax.load_model(saved)
    np.testing.assert_array_equal(ref["model"]["a"], np.asarray(kept.a))
    for bk, kk in zip(ref["model"]["b"], kept.b):
        np.testing.assert_array_equal(bk, np.asarray(kk))
    assert ref["model"]["a"] != out["a"]
    assert set(ref["settings"]) == {"h", "N", "M", "delays"}
    assert ref["refine_result"] in ("successful", "max_steps_reached")
    assert ref["E_output_error"] <= ref["E_mfm"] * (1 + 1e-9)
    # E of eq. 17 like the two before it (output error's own criterion was printed there)
    sig_all = mfmjax.Signals.from_csv(csv_file, output="temp", inputs=["u1", "u2"], time="t",
                                      intersample=("foh", "zoh"))
    assert ref["E_output_error"] == pytest.approx(
        float(mfmjax.performance_index(kept, sig_all)), rel=1e-9, abs=0)
    assert set(ref["parameters"]) == {"a_0", "a_1", "a_2", "b_10", "b_11", "b_20"}
    for p in ref["parameters"].values():
        assert p["std_error"] >= 0 and np.isfinite(p["value"])
    # no delays given: none fitted, none counted; a stable, determined fit says nothing more
    assert ref["delay_std_errors"] is None
    assert ref["output_error_unstable"] is False and ref["undetermined"] == []
    # search refines on the data it fitted: with --identify-window, that window (refine and
    # output error ran on the whole record, --validate-window's data included, which the
    # validation line then called held back); the refined E_mfm is the winner's E there
    assert main(["search", str(csv_file), "--output", "temp", "--inputs", "u1,u2", "--time", "t",
                 "--intersample", "foh,zoh", "--n", "3", "--m", "1;0", "--N", "4", "--M", "5",
                 "--h", "2.0", "--identify-window", "0,12", "--validate-window", "12.5,19.99",
                 "--refine", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["validation"]["overlaps_identification"] is False
    assert set(out["refined"]["parameters"]) == {"a_0", "a_1", "a_2", "b_10", "b_11", "b_20"}
    assert out["refined"]["model"]["n"] == 3
    row = out["ranked"][0]
    best = mfmjax.Model.from_coefficients(row["a"], row["b"], intersample=("foh", "zoh"))
    sig = mfmjax.Signals.from_csv(csv_file, output="temp", inputs=["u1", "u2"], time="t",
                                  intersample=("foh", "zoh"))
    on_window = float(mfmjax.observe(best, sig.window(0.0, 12.0)).E)
    assert out["refined"]["E_mfm"] == pytest.approx(on_window, rel=1e-9)
    assert abs(float(mfmjax.observe(best, sig).E) - on_window) > 1e-3 * on_window
    # the text report of the same job (its programs are those of the JSON run above)
    assert main(["search", str(csv_file), "--output", "temp", "--inputs", "u1,u2", "--time", "t",
                 "--intersample", "foh,zoh", "--n", "3", "--m", "1;0", "--N", "4", "--M", "5",
                 "--h", "2.0", "--identify-window", "0,12", "--validate-window", "12.5,19.99",
                 "--refine"]) == 0
    text = capsys.readouterr().out
    assert "refined settings" in text and "std. error" in text and "output error" in text


def test_refine_of_an_unstable_estimate_reports_instead_of_failing(tmp_path, capsys):
    """`identify --refine` on a record whose MFM estimate is unstable (a plant with a pole at
    +0.05; 200 s: the output grows 1e8-fold) exited 2 with observe()'s "not observable ...
    shorten the window" (E of the unstable models, which no window given could fix) and
    printed nothing; the report now comes, E undefined where it is, and output error (which
    mirrors the unstable poles) gives its model."""
    import mfmjax

    plant = mfmjax.Model.from_coefficients([-0.1, 1.0, 1.0], [[1.0]])
    t = np.arange(2000) * 0.1
    u = np.sin(1.3 * t) + 0.5 * np.sign(np.sin(0.4 * t))
    y = np.asarray(mfmjax.simulate(plant, u[:, None], dt=0.1))
    path = tmp_path / "unstable.csv"
    path.write_text("t,y,u\n" + "".join(f"{float(a)!r},{float(b)!r},{float(c)!r}\n"
                                         for a, b, c in zip(t, y, u)))
    argv = ["identify", str(path), "--time", "t", "--output", "y", "--inputs", "u", "--n", "2",
            "--m", "0", "--N", "3", "--M", "3", "--h", "2.0", "--refine"]
    assert main([*argv, "--json"]) == 0
    ref = json.loads(capsys.readouterr().out)["refined"]
    assert ref["E_mfm"] is None and ref["output_error_stabilised"]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "E (eq. 17) on the data fitted, the state observed over all of them: MFM undefined" \
        in out and "an unstable model" in out


def test_plot_to_a_folder_is_refused(csv_file, tmp_path, capsys):
    """`validate --plot FOLDER/` was accepted: the JSON named FOLDER/.png and matplotlib wrote
    the hidden file FOLDER/.png.png."""
    model_path = tmp_path / "model.json"
    assert main(["identify", str(csv_file), *ARGS, "--save", str(model_path)]) == 0
    capsys.readouterr()
    for folder in (str(tmp_path), str(tmp_path) + os.sep):
        assert main(["validate", str(csv_file), "--output", "temp", "--time", "t", "--inputs",
                     "u1,u2", "--model", str(model_path), "--plot", folder]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith(f"error: --plot {folder}: it is a folder; give a file name"), err
    assert not list(tmp_path.glob(".png*"))


def test_output_paths_are_checked_before_the_command_runs(csv_file, tmp_path, capsys):
    """`validate --plot /missing/x.png` printed `[Errno 2] No such file or directory` after
    the validation, and `report -o FILE` `[Errno 17] File exists`: both are said by option
    before anything runs."""
    model_path = tmp_path / "model.json"
    assert main(["identify", str(csv_file), *ARGS, "--save", str(model_path)]) == 0
    capsys.readouterr()
    common = [str(csv_file), "--output", "temp", "--time", "t", "--inputs", "u1,u2",
              "--model", str(model_path)]
    missing = tmp_path / "no" / "x.png"
    assert main(["validate", *common, "--plot", str(missing)]) == 2
    err = capsys.readouterr().err.strip()
    assert err == (f"error: --plot {missing}: the folder {missing.parent} does not exist or is "
                   "not writable; create it or give another path")
    assert main(["report", *common, "-o", str(csv_file)]) == 2
    assert capsys.readouterr().err.strip() == (
        f"error: -o {csv_file}: a file of that name exists; report writes a folder of "
        "figures: give a new or existing folder")


def test_cli_audit_slips_are_said_before_the_work(csv_file, tmp_path, capsys):
    """A CLI audit's slips: --save into a missing folder and a --validate-window outside the
    record were found after the search (the table lost; a model file written by a command
    that then failed with exit 2); --estimate dropped --validate and --score without a word;
    --dt beside the file's own time column ignored it (a logging gap in it went unseen)."""
    search = ["search", str(csv_file), *ARGS[:ARGS.index("--n")], "--n", "1,2", "--N", "3",
              "--M", "3", "--h", "1.0", "--time", "t", "--intersample", "foh,zoh"]
    saved = tmp_path / "m.json"
    assert main(search + ["--save", str(tmp_path / "nofolder" / "m.json")]) == 2
    err = capsys.readouterr().err
    assert "--save" in err and "does not exist" in err and len(err.strip().splitlines()) == 1
    assert main(search + ["--save", str(saved), "--validate-window", "15,50"]) == 2
    err = capsys.readouterr()
    assert "--validate-window 15,50 must lie inside the record" in err.err
    assert not saved.exists() and "candidates" not in err.out  # checked before the search
    for extra in (["--validate", "5,19"], ["--score", "fit"]):
        assert main(search + ["--estimate", *extra]) == 2
        assert "--validate and --score rank the plain search" in capsys.readouterr().err
    ident = ["identify", str(csv_file), *ARGS]
    dt_args = ident[:]
    i = dt_args.index("--time")
    dt_args[i:i + 2] = ["--dt", "0.01"]
    assert main(dt_args) == 0
    assert ("note: --dt 0.01 gives the sample times; the file's column 't' is not read "
            "(--time t reads it") in capsys.readouterr().err
    assert main(ident + ["--identify-window", "0,10", "--validate-window", "9,19.99"]) == 0
    assert "WARNING: the window overlaps the identification data" in capsys.readouterr().out
    # windows that only touch (one shared end sample) are adjacent: not flagged
    assert main(ident + ["--identify-window", "0,10", "--validate-window", "10,19.99"]) == 0
    assert "overlaps" not in capsys.readouterr().out


def test_refine_report_says_unstable_undetermined_and_fitted_delays(capsys):
    """`--refine` silences the library's warnings (its report says what matters): an unstable
    or undetermined output-error fit printed only its table (inf as `inf`), and the std
    errors of a delay refine fitted were not shown. The report's lines, from its fields."""
    from mfmjax._cli import _print_report

    rep = {"settings": {"N": 4, "M": 5, "h": 2.0, "delays": [0.4363, 0.0]},
           "refine_result": "successful", "refine_steps": 7, "E_mfm": 2.0, "E_refined": 1.5,
           "E_output_error": 1.2, "output_error_result": "successful",
           "output_error_converged": True, "output_error_stabilised": False,
           "output_error_unstable": True, "undetermined": ["b_20"],
           "parameters": {"a_0": {"value": 1.79, "std_error": 0.04},
                          "b_20": {"value": 0.3, "std_error": float("inf")}},
           "delay_std_errors": [0.033, None], "refine_improved": True, "refine_warnings": []}
    _print_report(rep)
    out = capsys.readouterr().out
    assert "no improvement" not in out and "note: refine()" not in out
    assert "WARNING: the output-error model is UNSTABLE" in out
    assert "WARNING: NOT DETERMINED by the data (infinite std error, the value is arbitrary): b_20" in out
    assert re.search(r"delay 1 +4\.363000e-01 +3\.300e-02", out) and "delay 2" not in out
    assert "the delays were fitted by refine; the standard errors include their uncertainty" in out
    # refine's own warnings were silenced too: a BFGS stalled at the start read "successful"
    _print_report({**rep, "refine_improved": False,
                   "refine_warnings": ["refine(): no improvement on the start (...)"]})
    out = capsys.readouterr().out
    assert ("(BFGS on E: successful, 7 steps, no improvement: the start kept)" in out
            and "note: refine(): no improvement on the start (...)" in out), out
