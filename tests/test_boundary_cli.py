"""The command line's boundary: every user error is one stderr line and exit code 2, an internal
error is one line with a bug-report hint and exit code 1; CSV files, package attributes, data
paths. The cases are those of issue 16."""

import importlib
import json
import os
import re
import subprocess
import sys
import warnings

import numpy as np
import pytest

import mfmjax
from mfmjax import _cli, _signals
from mfmjax._cli import main
from mfmjax.datasets import simulated_experiment, switching_experiment, third_order_two_input


def _write_csv(path, header, columns):
    with open(path, "w") as fh:
        fh.write(",".join(header) + "\n")
        for row in zip(*columns):
            fh.write(",".join(repr(float(v)) for v in row) + "\n")
    return path


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("boundary")
    sig = simulated_experiment(third_order_two_input(), dt=0.01, n_samples=2000)
    y, u = np.asarray(sig.y), np.asarray(sig.u)
    t = 0.01 * np.arange(y.size)
    rec = _write_csv(d / "rec.csv", ["t", "temp", "u1", "u2"], [t, y, u[:, 0], u[:, 1]])
    const = _write_csv(d / "const.csv", ["t", "temp", "u1", "u2"],
                       [t, np.full_like(y, 21.5), u[:, 0], u[:, 1]])
    model = d / "model.json"
    assert main(["identify", str(rec), *IDENT, "--save", str(model)]) == 0
    return {"rec": str(rec), "const": str(const), "model": str(model), "dir": d}


COLS = ["--output", "temp", "--inputs", "u1,u2", "--time", "t"]
IDENT = COLS + ["--n", "3", "--m", "1,0", "--N", "4", "--M", "5", "--h", "2.0",
                "--intersample", "foh,zoh"]


def _set(args, option, value):
    args = list(args)
    if option in args:
        args[args.index(option) + 1] = value
    else:
        args += [option, value]
    return args


def _one_line_error(capsys, code, argv, match):
    assert main(argv) == code
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert match in err, err
    return err


@pytest.mark.parametrize(
    "command, option, value, match",
    [
        ("identify", "--N", "inf", "argument --N: expected a finite number, got 'inf'"),
        ("identify", "--N", "nan", "argument --N: expected a finite number, got 'nan'"),
        ("identify", "--M", "1e999", "argument --M: expected a finite number, got '1e999'"),
        ("identify", "--h", "inf", "argument --h: expected a finite number, got 'inf'"),
        ("identify", "--n", "2.5", "argument --n: expected an integer >= 1, got '2.5'"),
        ("identify", "--n", "inf", "argument --n: expected an integer >= 1"),
        ("identify", "--inputs", "temp", "'temp' is also the output (--output temp)"),
        ("identify", "--inputs", "u1,temp", "'temp' is also the output (--output temp)"),
        ("identify", "--inputs", "u1,u1", "'u1' is given twice"),
        ("identify", "--inputs", "t,u1", "'t' is also the time column (--time t)"),
        ("identify", "--delays", "0,inf", "--delays: inf is not a finite number"),
        ("search", "--N", "inf", "--N: inf is not a finite number"),
        ("search", "--h", "nan", "--h: nan is not a finite number"),
        ("search", "--validate", "0,inf", "--validate: inf is not a finite number"),
        ("search", "--validate", "nan,3", "--validate: nan is not a finite number"),
        ("search", "--validate", "5", "--validate: expected T0,T1 (two numbers), got '5'"),
        ("search", "--validate", "1,2,3", "--validate: expected T0,T1"),
        ("search", "--validate", "9,2", "--validate: T0 must be below T1"),
        ("search", "--top", "0", "argument --top: expected an integer >= 1"),
        ("search", "--n", ":,", "--n: expected a range a:b of two integers, got ':,'"),
        ("search", "--N", "1,2:3", "--N: expected a range a:b of two integers"),
        ("search", "--n", "1:1e12", "--n: the range '1:1e12' has 1,000,000,000,000 values; at "
                                    "most 10,000"),
        ("validate", "--window", "0,inf", "--window: inf is not a finite number"),
        ("validate", "--window", "nan,nan", "--window: nan is not a finite number"),
        ("validate", "--window", "4", "--window: expected T0,T1 (two numbers), got '4'"),
        ("validate", "--window", "x", "--window: expected comma-separated numbers"),
        # its observer's 20 %: 2 samples (the message used to name observer_window, which the
        # CLI user never gave)
        ("identify", "--validate-window", "10,10.05", "--validate-window 10,10.05 is too short: "
         "its first 20% (the initial-state observer) needs at least 8 samples; widen it to at "
         "least 0.35, or give --observer-window (windows are times, not sample numbers: "
         "dt = 0.01)"),
    ],
)
def test_option_errors_are_one_line_exit_2(files, capsys, command, option, value, match):
    if command == "identify":
        args = ["identify", files["rec"], *IDENT]
    elif command == "search":
        args = ["search", files["rec"], *COLS, "--h", "1.5", "--n", "1", "--N", "3", "--M", "3"]
    else:
        args = ["validate", files["rec"], *COLS, "--model", files["model"]]
    _one_line_error(capsys, 2, _set(args, option, value), match)


def test_abbreviated_options_are_refused(files, capsys):
    """argparse took `--delay 2` as `--delays 2` (a prefix): an option is spelt out or refused."""
    _one_line_error(capsys, 2, ["identify", files["rec"], *IDENT, "--delay", "2"],
                    "unrecognized arguments: --delay 2")


@pytest.mark.parametrize("value", ["inf", "nan", "-1", "0"])
def test_dt_option_finite_and_positive(files, capsys, value):
    args = ["identify", files["rec"], *IDENT]
    i = args.index("--time")
    del args[i : i + 2]
    _one_line_error(capsys, 2, args + ["--dt", value], "argument --dt: expected a finite number > 0")


@pytest.mark.parametrize("value", ["nan", "inf", "100", "-3"])
def test_demo_horizon(capsys, value):
    _one_line_error(capsys, 2, ["demo", "--horizon", value], "argument --horizon: expected a "
                    "finite number >= 2500")


def test_dataset_seed(capsys, tmp_path):
    _one_line_error(capsys, 2, ["dataset", "forehearth", "--seed", "-1", "-o",
                                str(tmp_path / "x.csv")], "argument --seed: expected an integer")


def test_validate_constant_output_fit_undefined(files, capsys):
    args = ["validate", files["const"], *COLS, "--model", files["model"]]
    assert main(args + ["--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["fit"] is None and "constant" in res["fit_note"] and np.isfinite(res["E"])
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "fit           undefined: the measured temp is constant" in out and "inf" not in out


def test_help_lists_validate_with_percent(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    assert "E, fit % and observed x0 of a saved model on a record" in out


@pytest.mark.parametrize("command", ["identify", "search", "validate", "online", "dataset",
                                     "demo"])
def test_subcommand_help(capsys, command):
    with pytest.raises(SystemExit) as exc:
        main([command, "--help"])
    assert exc.value.code == 0 and f"usage: mfmjax {command}" in capsys.readouterr().out


@pytest.mark.parametrize("flag", [["--resample", "2"], ["--detrend", "linear"], ["--offset"],
                                  ["--no-offset"]])
def test_online_refuses_the_record_options_it_does_not_read(capsys, tmp_path, flag):
    """--resample, --detrend and --offset/--no-offset belong to identify and search; `online`
    listed them in its help and ran with the same MSE whatever they said. Now refused (before
    the file is read) and not in its help."""
    err = _one_line_error(capsys, 2, ["online", str(tmp_path / "x.csv"), "--output", "y",
                                      "--inputs", "u", "--dt", "1", *flag],
                          "online does not take it")
    assert err.startswith("error: " + ("--offset/--no-offset" if "offset" in flag[0]
                                       else flag[0])), err
    with pytest.raises(SystemExit):
        main(["online", "--help"])
    assert flag[0] not in capsys.readouterr().out


def test_internal_error_exit_1_with_bug_hint(capsys, monkeypatch, tmp_path):
    import mfmjax.datasets as ds

    def broken(*a, **k):
        return {}["t"]  # a KeyError: a bug, not a user mistake

    monkeypatch.setattr(ds, "forehearth", broken)
    err = _one_line_error(capsys, 1, ["dataset", "forehearth", "-o", str(tmp_path / "x.csv")],
                          "internal error (KeyError: 't'); this is a bug in mfmjax")
    assert "MFMJAX_TRACEBACK=1" in err
    monkeypatch.setenv("MFMJAX_TRACEBACK", "1")
    with pytest.raises(KeyError):
        main(["dataset", "forehearth", "-o", str(tmp_path / "x.csv")])


def test_value_check_inside_jit_is_a_user_error(capsys, monkeypatch, tmp_path):
    import equinox as eqx
    import jax

    import mfmjax.datasets as ds

    @jax.jit
    def checked(x):
        return eqx.error_if(x, x > 0, "simulate(): the input u has a NaN or inf sample")

    def data_problem(*a, **k):
        checked(1.0)

    monkeypatch.setattr(ds, "forehearth", data_problem)
    _one_line_error(capsys, 2, ["dataset", "forehearth", "-o", str(tmp_path / "x.csv")],
                    "error: simulate(): the input u has a NaN or inf sample")


def test_warnings_are_one_line(capsys, monkeypatch, tmp_path):
    import warnings

    import mfmjax.datasets as ds

    def warns(*a, **k):
        warnings.warn("cond(G) is large:\n  results may be inaccurate", UserWarning, stacklevel=2)
        raise ValueError("forehearth(): stop here")

    monkeypatch.setattr(ds, "forehearth", warns)
    assert main(["dataset", "forehearth", "-o", str(tmp_path / "x.csv")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["warning: cond(G) is large: results may be inaccurate",
                   "error: forehearth(): stop here"]


# -- on-line command: config, memory, checkpoints -----------------------------------------------

CUT = 2345


@pytest.fixture(scope="module")
def plant(tmp_path_factory):
    d = tmp_path_factory.mktemp("online")
    t, y, u, _ = switching_experiment(n_intervals=20)
    full = _write_csv(d / "plant.csv", ["time", "temp", "u1", "u2"], [t, y, u[:, 0], u[:, 1]])
    head = _write_csv(d / "head.csv", ["time", "temp", "u1", "u2"],
                      [t[:CUT], y[:CUT], u[:CUT, 0], u[:CUT, 1]])
    cfg = d / "n2.toml"
    cfg.write_text("[online]\nn = [2]\n")
    return {"full": str(full), "head": str(head), "cfg": str(cfg), "dir": d}


ONLINE = ["--output", "temp", "--inputs", "u1,u2", "--time", "time", "--intersample", "foh,zoh"]


@pytest.mark.parametrize(
    "toml, match",
    [
        ("interval = inf\n", "--config: interval = inf in"),
        ("interval = nan\n", "--config: interval = nan in"),
        ("h = [50.0, inf]\n", "--config: h = [50.0, inf] in"),
        ("interval = 1e9\n", "GiB"),  # 1e9 samples per interval: refused before allocating
        ("online = 3\n", "must be a table"),
        # a flat m read as one fixed order per input (16 candidates instead of 64, silently)
        ("m = [0, 1]\n", "m must list, per input, the numerator orders to try (e.g. "
         "m=[[0, 1]] * 2, one list per input), got [0, 1]"),
        ('offset = "false"\n', "offset must be True or False, got 'false'"),  # read as True
        ('smooth = "yes"\n', "smooth must be True or False"),
        # the CLI names them from the columns (a short list crashed at the first identification)
        ('input_names = ["a"]\n', "--config: input_names come from --output and --inputs"),
        ("n_start = 1\n", "T_obinit (1000) must fit in the identification window of n_start "
         "intervals (n_start * interval = 250); raise n_start or lower T_obinit"),
        ("T_obfin = 1e9\n", "T_obfin=1e+09 (1e+09 samples) sets it; lower T_obfin"),
    ],
)
def test_online_config_values(plant, capsys, tmp_path, toml, match):
    cfg = tmp_path / "c.toml"
    cfg.write_text(toml)
    _one_line_error(capsys, 2, ["online", plant["head"], *ONLINE, "--config", str(cfg)], match)


def test_online_output_folders_are_checked_before_the_run(plant, capsys, monkeypatch):
    """--plot and --checkpoint in a folder that does not exist: one line, exit 2, before any
    sample is processed (they were written after the whole run, whose work was then lost)."""
    from mfmjax import _online

    def never(*args, **kwargs):
        raise AssertionError("the stream was processed before the paths were checked")

    monkeypatch.setattr(_online.OnlineIdentifier, "update", never)
    for option in ("--plot", "--checkpoint"):
        _one_line_error(capsys, 2, ["online", plant["head"], *ONLINE, option,
                                    "/nonexistent/out.file"],
                        f"{option} /nonexistent/out.file: the folder /nonexistent does not exist")


def test_online_jittered_time_column_suggests_dt(plant, capsys, tmp_path):
    """A time column with a drifting step (a historian's timestamps): dt is its median step,
    not a whole fraction of the interval; the error says where dt came from and to give --dt."""
    t, y, u, _ = switching_experiment(n_intervals=20)
    n = CUT
    jittered = _write_csv(tmp_path / "jit.csv", ["time", "temp", "u1", "u2"],
                          [t[:n] * 1.00007, y[:n], u[:n, 0], u[:n, 1]])
    _one_line_error(capsys, 2, ["online", str(jittered), *ONLINE],
                    "is the median step of --time time: give --dt with the sampling interval")


def test_online_off_grid_time_is_named_by_its_data_row(plant, capsys, tmp_path):
    """One time off the grid in the middle of a file: the error named update()'s chunk
    ("t[0] = 700.5", the CLI feeding one interval per chunk), not the file's row."""
    t, y, u, _ = switching_experiment(n_intervals=20)
    t = t[:CUT].copy()
    t[701] += 0.3
    path = _write_csv(tmp_path / "off.csv", ["time", "temp", "u1", "u2"],
                      [t, y[:CUT], u[:CUT, 0], u[:CUT, 1]])
    _one_line_error(capsys, 2, ["online", str(path), *ONLINE],
                    f"the time at data row 702 = {float(t[701])!r} is +0.3 from its grid point")


def test_online_memory_bound(plant, capsys, tmp_path, monkeypatch):
    """interval = 1e5 samples: a 0.8 M-sample buffer (19 MB) whose identification work is
    about _WORK_PER_BUFFER times that (4.9 GB), refused when 1 GiB is available."""
    monkeypatch.setattr(_cli, "_available_memory", lambda: 2**30)
    cfg = tmp_path / "c.toml"
    cfg.write_text("interval = 1e5\nT_obfin = 500.0\n")
    _one_line_error(capsys, 2, ["online", plant["head"], *ONLINE, "--config", str(cfg)],
                    "needs a buffer of 800,000 samples and about 4.58 GiB of memory (available: "
                    "1.0 GiB); use a shorter interval or a coarser dt")


def test_online_says_what_held_the_first_model_back(plant, capsys, tmp_path):
    """No prediction: the note gives the last interval's reason (it said "the first model needs
    n_start intervals" also when 16 had passed, on the DaISy heat exchanger with no steady
    interval): waiting for n_start = 12 of 9 intervals; and, on signals that are never steady
    (a sine of two intervals' period in every column), no operating point."""
    cfg = tmp_path / "c.toml"
    cfg.write_text("[online]\nn = [2]\nn_start = 12\n")
    assert main(["online", plant["head"], *ONLINE, "--config", str(cfg), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["mse_note"] == (
        "no prediction yet: waiting: 9 of 12 intervals")
    t = np.arange(2250.0)
    wave = np.sin(2 * np.pi * t / 500.0)
    path = _write_csv(tmp_path / "wave.csv", ["time", "temp", "u1", "u2"],
                      [t, wave, np.cos(2 * np.pi * t / 500.0), wave])
    assert main(["online", str(path), *ONLINE]) == 0
    assert "no prediction yet: no operating point was detected" in capsys.readouterr().out


@pytest.fixture(scope="module")
def checkpoint_run(plant):
    """An uninterrupted run and a run resumed from a checkpoint at CUT (both JSON)."""
    import contextlib
    import io

    ck = str(plant["dir"] / "state.npz")
    out = {}
    for name, argv in [
        ("full", ["online", plant["full"], *ONLINE, "--config", plant["cfg"], "--json"]),
        ("head", ["online", plant["head"], *ONLINE, "--config", plant["cfg"], "--json",
                  "--checkpoint", ck]),
        ("resumed", ["online", plant["full"], *ONLINE, "--json", "--checkpoint", ck]),
    ]:
        buf = io.StringIO()
        with contextlib.redirect_stdout(buf):
            assert main(argv) == 0
        out[name] = json.loads(buf.getvalue())
    out["ck"] = ck
    return out


def test_resumed_mse_covers_the_whole_run(checkpoint_run):
    full, head, res = checkpoint_run["full"], checkpoint_run["head"], checkpoint_run["resumed"]
    assert res["models"] == full["models"] and res["intervals"] == full["intervals"] == 20
    # the same squared errors summed in another order: equal to a few ulps
    assert res["mse"] == pytest.approx(full["mse"], rel=1e-12)
    # and how many of them were predicted, which the MSE is over (it said "over 16
    # intervals" of a run predicted on 11): the same count resumed as uninterrupted
    assert res["mse_scope"] == ("the whole run: 9 intervals before the checkpoint and 11 in "
                                "this call (12 of the 20 predicted)")
    assert full["mse_scope"] == "20 intervals (12 of them predicted)"
    # the first part predicted interval 8 alone, the resumed one all its 11: 12 of 20
    assert head["mse_scope"] == "9 intervals (1 of them predicted)"
    assert res["mse_this_call"] != res["mse"]


@pytest.mark.parametrize(
    "extra, match",
    [
        (["--delays", "5,0"], "was written with delays=0,0, --delays gives delays=5,0"),
        (["--intersample", "zoh,zoh"], "was written with intersample=foh,zoh, --intersample "
                                       "gives intersample=zoh,zoh"),
        ("toml:n = [3]\n", "was written with n=2, --config n gives n=3"),
        ("toml:tr_corr = 0.25\n", "was written with tr_corr=0.5, --config tr_corr gives "
                                  "tr_corr=0.25"),
    ],
)
def test_checkpoint_conflicting_options_refused(plant, checkpoint_run, capsys, tmp_path, extra,
                                                match):
    args = ["online", plant["full"], *ONLINE, "--checkpoint", checkpoint_run["ck"]]
    if isinstance(extra, str):
        cfg = tmp_path / "c.toml"
        cfg.write_text(extra[5:])
        extra = ["--config", str(cfg)]
    for k in range(0, len(extra), 2):
        args = _set(args, extra[k], extra[k + 1])
    _one_line_error(capsys, 2, args, match)


def test_checkpoint_same_options_accepted_and_other_columns_refused(plant, checkpoint_run,
                                                                    capsys, tmp_path):
    import shutil

    ck = tmp_path / "copy.npz"
    shutil.copy(checkpoint_run["ck"], ck)
    assert main(["online", plant["full"], *ONLINE, "--config", plant["cfg"], "--delays", "0,0",
                 "--checkpoint", str(ck), "--json"]) == 0
    capsys.readouterr()
    args = _set(["online", plant["full"], *ONLINE, "--checkpoint", str(ck)], "--inputs", "u2,u1")
    _one_line_error(capsys, 2, args, "was written for output 'temp' and inputs ['u1', 'u2'], "
                    "the command line gives 'temp' and ['u2', 'u1']")


@pytest.mark.parametrize(
    "damage, match",
    [
        (lambda b: b"", "is empty (0 bytes)"),
        (lambda b: b[: len(b) // 2], "is truncated or corrupted"),
        (lambda b: b[:-200] + bytes(200), "is truncated or corrupted"),
        (lambda b: b"PK\x03\x04" + bytes(64), "is truncated or corrupted"),
    ],
)
def test_damaged_checkpoint_one_line(plant, checkpoint_run, capsys, tmp_path, damage, match):
    ck = tmp_path / "bad.npz"
    with open(checkpoint_run["ck"], "rb") as fh:
        ck.write_bytes(damage(fh.read()))
    _one_line_error(capsys, 2, ["online", plant["full"], *ONLINE, "--checkpoint", str(ck)], match)


def test_damaged_checkpoint_subprocess_no_traceback(plant, checkpoint_run, tmp_path):
    """The one subprocess smoke test: what a shell user sees (jax's own logging included)."""
    ck = tmp_path / "bad.npz"
    with open(checkpoint_run["ck"], "rb") as fh:
        ck.write_bytes(fh.read()[:1000])
    r = subprocess.run([sys.executable, "-m", "mfmjax._cli", "online", plant["full"], *ONLINE,
                        "--checkpoint", str(ck)], capture_output=True, text=True)
    assert r.returncode == 2 and r.stdout == ""
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "truncated or corrupted" in lines[0] and "Traceback" not in r.stderr


# -- demo: strict JSON ---------------------------------------------------------------------------


def test_demo_results_json_is_strict_when_no_prediction(tmp_path, capsys):
    """A horizon too short for any prediction (600 s: the first model needs 8 intervals of
    250 s) gives MSE NaN: results.json has null and says why (the CLI's 3000 s case, cheaper)."""
    from mfmjax._demo import demo

    demo(str(tmp_path), horizon=600.0)
    out = capsys.readouterr().out
    # with the reason, as `mfmjax online` gives it (the demo said only "no prediction yet")
    reasons = re.findall(r"mean square prediction error: undefined \(no prediction yet: "
                         r"(.+); a longer --horizon", out)
    assert len(reasons) == 2 and all(reasons), out

    def refuse(name):
        raise AssertionError(f"non-standard JSON constant {name}")

    res = json.loads((tmp_path / "results.json").read_text(), parse_constant=refuse)
    for e, reason in zip(res["experiments"], reasons):
        # the printed reason (the note blamed n_start where no operating point had been
        # detected), and what a longer horizon does: no model yet here
        assert e["mse"] is None and e["mse_note"] == (
            f"null: no prediction yet: {reason}; a longer --horizon lets the plant reach an "
            "operating point")


# -- CSV files -----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "content, match",
    [
        (bytes(range(256)) * 4, "binary file"),
        (b"\x89PNG\r\n\x1a\n" + bytes(100), "binary file"),
        (b"t;y;u\n0;1,5;2\n1;2,5;3\n", "separated by ';'"),
        # a name holding a comma ("line 2 has 5 fields but the header has 2 columns")
        (b"t;TI101 [degC, PV];u\n0;1,5;2\n", r"separated by ';'.*sep=';', decimal=','"),
        ("t,y,u\n0,1,2\n1,2,\xe93\n".encode("latin-1"), r"not a UTF-8 text file \(byte 0xe9"),
        # a comment line in the data: said by its number (a file with comment lines read
        # "line 2 has 3 fields but the header has 2 columns")
        (b"t,y,u\n0,1,2\n# pause\n1,2,\n", r"line 3 starts with '#'; .* remove them"),
    ],
)
def test_csv_binary_and_semicolon(tmp_path, content, match):
    p = tmp_path / "x.csv"
    p.write_bytes(content)
    with pytest.raises(ValueError, match=match):
        _signals.read_csv(p)
    with pytest.raises(ValueError, match=match):
        mfmjax.Signals.from_csv(p, output="y", inputs=["u"], dt=1.0)


def test_csv_header_of_numpy_savetxt_is_read(tmp_path):
    """numpy.savetxt writes its header as a comment ("# t,y,u"): the names are read without
    the '#' (the first column was named '# t')."""
    p = tmp_path / "x.csv"
    p.write_bytes(b"# t,y,u\n0,1,2\n1,2,3\n")
    assert list(_signals.read_csv(p)) == ["t", "y", "u"]


def test_csv_without_a_header_is_said(tmp_path):
    """Its first row of numbers reads as column names: the unknown-column error says so (a
    DaISy .dat file read "available: ['0.00', '9.000', '129.320']" and nothing more)."""
    p = tmp_path / "x.csv"
    p.write_bytes(b"0.00,9.0,129.3\n2.00,9.0,129.5\n")
    with pytest.raises(ValueError, match=r"unknown column 'y' .* the first line holds "
                                         r"numbers, so the file has no header"):
        mfmjax.Signals.from_csv(p, output="y", inputs=["u"], dt=1.0)


@pytest.fixture(params=["loadtxt", "pandas"])
def fast_path(request, monkeypatch):
    if request.param == "pandas":
        pytest.importorskip("pandas")
        monkeypatch.setattr(_signals, "_PANDAS_MIN_CHARS", 0)
    else:
        monkeypatch.setattr(_signals, "_PANDAS_MIN_CHARS", 10**18)
        monkeypatch.delitem(sys.modules, "pandas", raising=False)
    return request.param


def test_csv_fast_paths_equal_careful_path(tmp_path, fast_path, monkeypatch):
    rng = np.random.default_rng(1)
    data = rng.standard_normal((500, 4)) * 10.0 ** rng.integers(-300, 300, (500, 4))
    p = _write_csv(tmp_path / "x.csv", ["t", "y", "u1", "u2"], data.T)
    fast = _signals.read_csv(p)
    monkeypatch.setattr(_signals, "_parse_fast", lambda *a: None)  # the line-by-line path
    careful = _signals.read_csv(p)
    for j, k in enumerate(["t", "y", "u1", "u2"]):
        assert np.array_equal(fast[k], careful[k]) and np.array_equal(fast[k], data[:, j])


def test_csv_date_times_and_tabs(tmp_path, fast_path):
    """A historian's export: ISO 8601 time stamps (refused as text, with advice about unit rows)
    are read as seconds since the first; a tab-separated header may hold names with spaces
    (they were split at every space: "line 2 has 4 fields but the header has 7 columns")."""
    p = tmp_path / "x.csv"
    p.write_bytes(b"time,y,u\n2024-03-05 08:00:00,1,2\n2024-03-05T08:00:00.5Z,1.5,\n"
                  b"2024-03-05 08:00:01,2,3\n")
    cols = _signals.read_csv(p)
    np.testing.assert_array_equal(cols["time"], [0.0, 0.5, 1.0])
    np.testing.assert_array_equal(cols["u"], [2.0, np.nan, 3.0])
    assert mfmjax.Signals.from_csv(p, output="y", time="time").dt == 0.5
    p.write_bytes(b"time\tTI 101 PV\tFuel flow\n0\t1.5\t2\n1\t1.6\t2.5\n")
    cols = _signals.read_csv(p)
    assert list(cols) == ["time", "TI 101 PV", "Fuel flow"]
    np.testing.assert_array_equal(cols["Fuel flow"], [2.0, 2.5])
    p.write_bytes(b"time,y\n2024-03-05 08:00:00,1\n05.03.2024 08:00:01,2\n")
    with pytest.raises(ValueError, match=r"line 3 has a non-numeric value '05.03.2024 08:00:01' "
                                         r"in column 'time'.*ISO 8601"):
        _signals.read_csv(p)
    # an offset and a lower-case z are UTC (no numpy warning escapes); numpy's words are no
    # date-times; a whole column of other date-times or text is said to be one, not a unit row
    p.write_bytes(b"time,y\n2024-03-05T09:00:00+01:00,1\n2024-03-05T08:00:02z,2\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        np.testing.assert_array_equal(_signals.read_csv(p)["time"], [0.0, 2.0])
    for cells in ("now,today", "05.03.2024 08:00:00,05.03.2024 08:00:01", "OK,OK"):
        a, b = cells.split(",")
        p.write_bytes(f"time,y\n{a},1\n{b},2\n".encode())
        with pytest.raises(ValueError, match=r"line 2 .*the column holds text or date-times not "
                                             r"in ISO 8601"):
            _signals.read_csv(p)
    p.write_bytes(b"time,y\ns,degC\n2024-03-05 08:00:00,1\n2024-03-05 08:00:01,2\n")
    with pytest.raises(ValueError, match=r"line 2 .*'s' in column 'time'.*a unit row"):
        _signals.read_csv(p)  # a unit row above a date-time column is one, not "text"
    # tab files: a trailing tab, data split by spaces under a tab header; ';' inside a
    # comma file's names
    for body in (b"t\ty\tu\n0\t1\t2\t\n1\t2\t3\t\n", b"t\ty\tu\n0 1 2\n1 2 3\n",
                 b"t,T;PV;degC,u\n0,1,2\n1,2,3\n"):
        p.write_bytes(body)
        cols = _signals.read_csv(p)
        np.testing.assert_array_equal(list(cols.values())[1], [1.0, 2.0])


@pytest.mark.parametrize(
    "text, match, expect",
    [
        ("a,b\n1,2\n3\n", "line 3 has 1 fields", None),  # pandas would pad with NaN
        ("a,b\n1,2\n3,4,5\n", "line 3 has 3 fields", None),
        ("a,b\n1,2\n3,x\n", "line 3 has a non-numeric value 'x' in column 'b'.*empty, NaN "
                            "or #N/A", None),
        # missing values as historians and spreadsheets write them (#N/A was refused as text)
        ("a,b\n1,#N/A\n3,NULL\nN/A,2\n", None, [[1, 3, np.nan], [np.nan, np.nan, 2]]),
        # a units row under the header, a decimal comma: named, with the fix (the message
        # used to ask for --names, as if the file had no header)
        ("a,b\ns,degC\n1,2\n", "line 2 has a non-numeric value 's' in column 'a'; every "
                                 "row after the header must hold numbers .a unit row", None),
        ('a,b\n"1,5",2\n', "non-numeric value '1,5' in column 'a'", None),
        ("a,b\n1,2\n\n  \n3,\n", None, [[1, 3], [2, np.nan]]),  # blank lines, empty cell
        ('a,b\n"1",2\n3,4\n', None, [[1, 3], [2, 4]]),  # quoted numbers
        ("a,b\r\n1, 2\r\n3 ,4\r\n", None, [[1, 3], [2, 4]]),
        ("\ufeffa,b\n1,2\n", None, [[1], [2]]),  # UTF-8 byte-order mark
    ],
)
def test_csv_edge_cases_both_paths(tmp_path, fast_path, text, match, expect):
    p = tmp_path / "x.csv"
    p.write_bytes(text.encode())
    if match:
        with pytest.raises(ValueError, match=match):
            _signals.read_csv(p)
    else:
        cols = _signals.read_csv(p)
        assert list(cols) == ["a", "b"]
        np.testing.assert_array_equal(np.array([cols["a"], cols["b"]]), np.array(expect))


def test_csv_whitespace_file_with_names(tmp_path, fast_path):
    p = tmp_path / "x.dat"
    p.write_text(" 1  2.5 3\n4 5 6e-3\n")
    cols = _signals.read_csv(p, names=["k", "u", "y"])
    np.testing.assert_array_equal(cols["y"], [3.0, 6e-3])


# -- package attributes and data paths ------------------------------------------------------------


def test_datasets_is_a_package_attribute():
    """`import mfmjax; mfmjax.datasets.forehearth(1)` (an AttributeError before)."""
    d = mfmjax.datasets.forehearth(1)
    assert d["t"].size > 0 and "datasets" in dir(mfmjax)


def test_daisy_and_tests_honour_mfmjax_data(tmp_path, monkeypatch):
    folder = tmp_path / "daisy-heating-system"
    folder.mkdir()
    rows = "\n".join(f"{2.0 * k} {np.sin(k / 5):.6f} {np.cos(k / 7):.6f}" for k in range(30))
    (folder / "heating_system.dat").write_text(rows + "\n")
    monkeypatch.setenv("MFMJAX_DATA", str(tmp_path))
    sig = mfmjax.datasets.daisy("heating_system")
    assert sig.n_samples == 30 and sig.dt == 2.0
    import conftest

    try:
        assert importlib.reload(conftest).SHARED == str(tmp_path)
    finally:
        monkeypatch.delenv("MFMJAX_DATA")
        importlib.reload(conftest)


# -- property: random option values never give a traceback ---------------------------------------
# Each numeric option of each subcommand gets random text (finite, huge, tiny, negative, NaN,
# inf, lists, ranges, garbage) through the real parser, checks, file reading and object
# construction (Signals, Structure, ModulatingFunction, OnlineConfig, the on-line identifier).
# The numerical cores (identify, search, observe, the forehearth simulation, the demo) are
# replaced by stubs that return a fixed result of the right shape: each new value compiles a new
# program there (10-40 s each on this CPU), and their own argument checks are fuzzed directly in
# tests/test_fuzz.py. Property: exit 0, or exit 2 with exactly one "error: " line on stderr;
# never exit 1, never a traceback. Example counts were profiled: about 0.1 s each.

from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

_ODD = ["", " ", "nan", "NaN", "inf", "-inf", "1e999", "1e9", "1e300", "1e-320", "0", "-0", "-1",
        "2.5", "3", "x", "1,2", "1,", ",", "0,inf", "nan,1", "1:3", "3:1", "1:", "1:2:3", "1;2",
        "0;0;0", "2,1", "1e5", "16", "250", "1:1e12", "0:99999", "-5:5", ":,", "1,2:3", "--", "-"]
TEXT = st.one_of(
    st.sampled_from(_ODD),
    st.floats(0.01, 20.0).map(lambda v: repr(round(v, 2))),  # mostly valid values
    st.integers(0, 8).map(str),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.integers(-(10**12), 10**12).map(str),
    st.lists(st.floats(-1e4, 1e4), max_size=3).map(lambda v: ",".join(repr(x) for x in v)),
    st.text("0123456789.,:;-+eE naif", max_size=8),
)
FUZZ = settings(max_examples=int(os.environ.get("MFMJAX_FUZZ_EXAMPLES", 60)), deadline=None,
                derandomize=not os.environ.get("MFMJAX_FUZZ_EXAMPLES"),
                suppress_health_check=[HealthCheck.function_scoped_fixture,
                                       HealthCheck.too_slow])


class _FakeResult:
    compile_s = run_s = 0.0

    def __init__(self, model):
        self.model = model

    def __len__(self):
        return 1

    def best(self, i=0):
        return self.model

    def table(self, top=10):
        return "rank ..."

    def to_dict(self, top=None):
        return {"candidates": 1, "ranked": [self.model.to_dict()]}


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    d = tmp_path_factory.mktemp("fuzz")
    rng = np.random.default_rng(0)
    T = 40  # fewer samples than one on-line interval (16 samples at least): no compilation
    t = 0.05 * np.arange(T)
    u = rng.standard_normal((T, 2))
    y = np.cumsum(u[:, 0]) * 0.05
    rec = _write_csv(d / "tiny.csv", ["t", "y", "u1", "u2"], [t, y, u[:, 0], u[:, 1]])
    model = mfmjax.Model.from_coefficients([2.0, 1.0], [[1.0], [0.5]],
                                           intersample=("foh", "foh"))
    mpath = d / "m.json"
    mfmjax.save_model(model, mpath)
    return {"rec": str(rec), "model": str(mpath), "dir": d, "fake": model}


@pytest.fixture
def stubbed(tiny, monkeypatch):
    from mfmjax import _demo, _observers
    from mfmjax import datasets as ds

    fake = tiny["fake"]

    def identify(sig, structure, mf, *a, **k):
        assert isinstance(sig, mfmjax.Signals) and isinstance(mf, mfmjax.ModulatingFunction)
        return fake

    def search(sig, progress=None, **kw):
        assert isinstance(sig, mfmjax.Signals)
        return _FakeResult(fake)

    class _Obs:
        def __init__(self, n):
            self.y_sim, self.E = np.zeros(n), 0.0
            self.x_initial = self.x_final = np.zeros(1)

    def observe(model, sig, window=None, **k):
        _, length, _ = _observers.validation_window(sig, window, None, model.n, "observe",
                                                     "window")
        return _Obs(length)

    def forehearth(experiment, seed=0):
        if experiment not in (1, 2):
            raise ValueError("forehearth(): experiment must be 1 or 2")
        z = np.zeros(3)
        return {"t": z, "y": z, "u": np.zeros((3, 2)), "pull": z, "delay": z,
                "names": ["a", "b", "c"], "intersample": ("foh", "zoh")}  # (as the real one)

    monkeypatch.setattr(mfmjax, "identify", identify)
    monkeypatch.setattr(mfmjax, "search", search)
    monkeypatch.setattr(mfmjax, "observe", observe)
    monkeypatch.setattr(ds, "forehearth", forehearth)
    monkeypatch.setattr(_demo, "demo", lambda out, horizon=None: None)
    return tiny


def _check_property(argv):
    import contextlib
    import io

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = main(argv)
    text = err.getvalue()
    from hypothesis import event

    event(f"exit {rc}")
    assert "Traceback" not in text, (argv, text)
    lines = [ln for ln in text.splitlines() if ln.strip()]
    if rc == 2:
        errors = [ln for ln in lines if not ln.startswith("warning: ")]
        assert len(errors) == 1 and errors[0].startswith("error: "), (argv, text)
    else:
        assert rc == 0, (argv, rc, text)


def _fuzzed(options):
    """One or two of `options` with random text; the others keep their valid defaults."""
    return st.lists(st.tuples(st.sampled_from(options), TEXT), min_size=1, max_size=2)


def _argv(base, defaults: dict, fuzzed):
    values = {**defaults, **dict(fuzzed)}
    argv = list(base)
    for opt, val in values.items():
        if val is not None:
            argv.append(f"{opt}={val}")  # '=' lets values starting with '-' reach the checks
    return argv


F_DATA = ["--output", "y", "--inputs", "u1,u2"]
F_TIME = {"--time": "t"}


def _time(fuzzed):  # --dt replaces --time when it is fuzzed (they exclude each other)
    return {} if any(opt == "--dt" for opt, _ in fuzzed) else F_TIME


F_IDENT = {"--n": "1", "--m": "0,0", "--N": "3", "--M": "3", "--h": "0.5", "--delays": None,
         "--dt": None}


@FUZZ
@given(fuzzed=_fuzzed(list(F_IDENT)))
def test_fuzz_identify(stubbed, fuzzed):
    _check_property(_argv(["identify", stubbed["rec"], *F_DATA],
                          {**F_IDENT, **_time(fuzzed)}, fuzzed))


F_SEARCH = {"--n": None, "--m": None, "--N": None, "--M": None, "--h": "0.5", "--top": None,
          "--validate": None, "--delays": None, "--dt": None}


@FUZZ
@given(fuzzed=_fuzzed(list(F_SEARCH)))
def test_fuzz_search(stubbed, fuzzed):
    _check_property(_argv(["search", stubbed["rec"], *F_DATA], {**F_SEARCH, **_time(fuzzed)}, fuzzed))


F_VALIDATE = {"--window": None, "--delays": None, "--dt": None}


@FUZZ
@given(fuzzed=_fuzzed(list(F_VALIDATE)))
def test_fuzz_validate(stubbed, fuzzed):
    _check_property(_argv(["validate", stubbed["rec"], *F_DATA, "--model", stubbed["model"]],
                          {**F_VALIDATE, **_time(fuzzed)}, fuzzed))


ONLINE_KEYS = ["interval", "n_start", "n_reident", "T_obfin", "T_obinit", "tr_corr", "steady_rel",
               "h", "N", "M", "n", "delays", "eta"]
TOML_VALUE = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(
        lambda v: {"nan": "nan", "inf": "inf", "-inf": "-inf"}.get(repr(v), repr(v))),
    st.integers(-(10**12), 10**12).map(str),
    st.integers(0, 600).map(str),
    st.lists(st.floats(-1e3, 1e3), max_size=3).map(lambda v: "[" + ", ".join(map(repr, v)) + "]"),
    st.sampled_from(["true", '"x"', "[]", "[0]", "1e9", "16", "0.8", "[2.5]", "[2, 3]"]),
)


@FUZZ
@given(settings_=st.dictionaries(st.sampled_from(ONLINE_KEYS), TOML_VALUE, max_size=2),
       fuzzed=st.lists(st.tuples(st.sampled_from(["--delays", "--dt"]), TEXT), max_size=1))
def test_fuzz_online(stubbed, settings_, fuzzed):
    cfg = stubbed["dir"] / "fuzz.toml"
    cfg.write_text("".join(f"{k} = {v}\n" for k, v in settings_.items()))
    _check_property(_argv(["online", stubbed["rec"], *F_DATA, "--config", str(cfg), "--json"],
                          _time(fuzzed), fuzzed))


@FUZZ
@given(fuzzed=_fuzzed(["--experiment", "--seed", "--horizon"]))
def test_fuzz_dataset_and_demo(stubbed, fuzzed):
    out = str(stubbed["dir"] / "d.csv")
    data = [(o, v) for o, v in fuzzed if o != "--horizon"]
    demo = [(o, v) for o, v in fuzzed if o == "--horizon"]
    _check_property(_argv(["dataset", "forehearth", "-o", out], {}, data))
    _check_property(_argv(["demo", "--out", str(stubbed["dir"] / "demo")], {}, demo))


@pytest.mark.parametrize("command", ["identify", "online"])
def test_no_time_column_and_no_dt_is_one_line_that_does_not_assume_seconds(capsys, tmp_path,
                                                                         command):
    """Neither --time nor --dt: one line naming both; --dt is the step in the data's own
    time unit (it said "--dt SECONDS" for records in minutes or hours)."""
    path = tmp_path / "r.csv"
    path.write_text("y,u\n" + "".join(f"{k % 3},{k % 2}\n" for k in range(40)))
    extra = ["--n", "1", "--N", "2", "--M", "2", "--h", "5"] if command == "identify" else []
    err = _one_line_error(capsys, 2, [command, str(path), "--output", "y", "--inputs", "u",
                                      *extra], "give --time COLUMN or --dt STEP")
    assert "time unit" in err and "SECONDS" not in err, err
