import warnings

import numpy as np
import pytest

from mfmjax import Signals


def _ok(T=50):
    t = np.arange(T) * 0.1
    return np.sin(t), np.stack([np.cos(t), t], axis=1)


def test_from_arrays_and_time_column():
    y, u = _ok()
    s = Signals(y, u, t=1.0 + 0.1 * np.arange(50), intersample=("zoh", "foh"), delays=[0.25, 0])
    assert s.dt == pytest.approx(0.1) and s.t0 == 1.0 and s.n_inputs == 2
    assert s.intersample == ("zoh", "foh") and s.y.dtype == np.float64
    assert Signals(y, u[:, 0], dt=0.1).n_inputs == 1
    assert Signals(y, dt=0.1).n_inputs == 0


@pytest.mark.parametrize(
    "kwargs,match",
    [
        (dict(u_bad="nan"), "NaN or inf sample at row 7"),
        (dict(u_bad="inf"), "NaN or inf sample at row 7"),
        (dict(t=np.r_[0.0, 0.2, 0.1, np.arange(3, 50) * 0.1]), "strictly increasing"),
        (dict(t=np.r_[np.arange(25) * 0.1, 2.5 + np.arange(25) * 0.11]), "not uniformly"),
        (dict(u_len=49), "length mismatch"),
        (dict(intersample=("zoh", "spline")), "unknown intersample mode 'spline'"),
        (dict(delays=[-1.0, 0.0]), "delays must be finite and >= 0"),
        (dict(delays=[10.0, 0.0]), "not shorter than the record"),
        (dict(delays=[1.0]), "one entry per input"),
        (dict(dt=0.0), "dt must be > 0"),
        (dict(dt=None), "give the sampling interval"),
        (dict(t=np.arange(50) * 0.1, dt=0.1), "either t"),
        (dict(output_rule="quintic"), "unknown output_rule"),
    ],
)
def test_bad_signals(kwargs, match):
    y, u = _ok()
    bad = kwargs.pop("u_bad", None)
    if bad:
        u[7, 1] = float(bad)
    if "u_len" in kwargs:
        u = u[: kwargs.pop("u_len")]
    if "t" not in kwargs and "dt" not in kwargs:
        kwargs["dt"] = 0.1
    with pytest.raises(ValueError, match=match):
        Signals(y, u, **kwargs)


def _write(tmp_path, text):
    p = tmp_path / "data.csv"
    p.write_text(text)
    return p


def test_from_csv(tmp_path):
    y, u = _ok()
    rows = "\n".join(f"{0.1 * k:.10g},{float(y[k])!r},{float(u[k, 0])!r},{float(u[k, 1])!r}" for k in range(50))
    p = _write(tmp_path, "time,temp,q,p\n" + rows + "\n")
    s = Signals.from_csv(p, output="temp", inputs=["q", "p"], time="time")
    assert np.array_equal(np.asarray(s.y), y) and s.input_names == ("q", "p")
    with pytest.raises(ValueError, match="unknown column 'x' for inputs"):
        Signals.from_csv(p, output="temp", inputs=["x"], time="time")
    with pytest.raises(ValueError, match="time column"):
        Signals.from_csv(p, output="temp", inputs=["q"])
    # headerless whitespace file with names
    p2 = tmp_path / "data.dat"
    p2.write_text("\n".join(f"{k}  {float(u[k, 0])!r}  {float(y[k])!r}" for k in range(50)))
    s2 = Signals.from_csv(p2, output="y", inputs=["u"], time="k", names=["k", "u", "y"])
    assert s2.dt == 1.0 and np.array_equal(np.asarray(s2.y), y)


@pytest.mark.parametrize(
    "text,match",
    [
        ("", "empty"),
        ("a,b\n", "no data rows"),
        ("a,b\n1,2\n3\n", "line 3 has 1 fields"),
        ("a,b\n1,2\n3,x\n", "line 3 has a non-numeric value"),
        ("a,a\n1,2\n", "duplicate column"),
    ],
)
def test_bad_csv(tmp_path, text, match):
    with pytest.raises(ValueError, match=match):
        Signals.from_csv(_write(tmp_path, text), output="a", inputs=["b"], dt=1.0)


def test_names_of_another_count_than_the_fields_are_named(tmp_path):
    p = _write(tmp_path, "1,2,3\n4,5,6\n")
    with pytest.raises(ValueError, match=r"line 1 has 3 fields but 2 names were given"):
        Signals.from_csv(p, output="a", inputs=["b"], dt=1.0, names=["a", "b"])


def test_epoch_time_column_is_uniform_to_its_rounding():
    """Time stamps in epoch seconds (1.7e9 + k 0.1) carry 2.4e-7 s of rounding, above 1e-6 of
    the 0.1 s step: they are uniform to their own precision and accepted (they were refused as
    "not uniformly sampled", with both steps printed as 0.1); a real jitter of 1e-3 s is not."""
    y, u = _ok()
    t = 1.7e9 + 0.1 * np.arange(y.size)
    s = Signals.from_columns({"t": t, "y": y, "u": u[:, 0]}, output="y", inputs=["u"], time="t")
    # dt from the end stamps, each rounded by half a unit in the last place
    assert abs(s.dt - 0.1) <= np.spacing(t[-1]) / (y.size - 1) and s.t0 == t[0]
    t[20] += 1e-3
    with pytest.raises(ValueError, match=r"not uniformly sampled \(step at row 2[01] is 0\.(1009|0989)"):
        Signals.from_columns({"t": t, "y": y, "u": u[:, 0]}, output="y", inputs=["u"], time="t")


def test_missing_cell_is_reported_as_nan(tmp_path):
    p = _write(tmp_path, "a,b\n1,2\n3,\n4,5\n")
    with pytest.raises(ValueError, match="'b' has a NaN or inf sample at row 1"):
        Signals.from_csv(p, output="a", inputs=["b"], dt=1.0)


def test_from_dataframe():
    pd = pytest.importorskip("pandas")
    y, u = _ok()
    df = pd.DataFrame({"t": np.arange(50) * 0.5, "y": y, "u1": u[:, 0]})
    s = Signals.from_dataframe(df, output="y", inputs=["u1"], time="t", intersample="zoh")
    assert s.dt == 0.5 and s.intersample == ("zoh",)
    with pytest.raises(ValueError, match="unknown column 'u9'"):
        Signals.from_dataframe(df, output="y", inputs=["u9"], time="t")


def test_from_dataframe_reads_date_times_in_seconds():
    """A time column parsed by pandas (`parse_dates`) is datetime64: it was read as its integer
    count of (micro/nano)seconds, so dt = 1e6 and a 5 s delay meant 5 us, with status ok. Date-
    times (also tz-aware, also as the index) and durations are now seconds since the first; a
    text column in use is refused by name; text columns not in use are no obstacle."""
    pd = pytest.importorskip("pandas")
    y, u = _ok()
    stamps = pd.date_range("2024-03-05 08:00:00", periods=50, freq="500ms")
    df = pd.DataFrame({"time": stamps, "y": y, "u1": u[:, 0], "tag": ["ok"] * 50})
    unnamed = df.set_index("time").rename_axis(None)
    for frame, time in ((df, "time"), (df.set_index("time"), "time"), (unnamed, "index"),
                        (df.assign(time=stamps.tz_localize("Europe/Berlin")), "time"),
                        (df.assign(time=stamps - stamps[0]), "time")):
        s = Signals.from_dataframe(frame, output="y", inputs=["u1"], time=time)
        assert s.dt == 0.5 and s.t0 == 0.0
        np.testing.assert_array_equal(np.asarray(s.y), y)
    with pytest.raises(ValueError, match="column 'tag' holds 'ok', not a number"):
        Signals.from_dataframe(df, output="y", inputs=["tag"], time="time")


def test_frozen_rows_are_warned(tmp_path):
    """A logger that froze for 201 rows mid-record (every column repeating its value) was
    fitted as real data with status ok (b 27 % low in a walkthrough). Reading such a record
    now warns with the rows' times and the fix; a rest at the record's start does not warn,
    nor do 20 repeated rows (FROZEN_ROWS = 20 repeats, i.e. 21 equal rows, is the threshold)."""
    from mfmjax import _signals

    rng = np.random.default_rng(0)
    t = np.arange(600.0)
    y, u = rng.standard_normal(600), rng.standard_normal(600)
    y[:50], u[:50] = 0.0, 0.0  # the plant at rest before the experiment
    for n_equal, warns in ((_signals.FROZEN_ROWS, False), (_signals.FROZEN_ROWS + 1, True)):
        yf, uf = y.copy(), u.copy()
        yf[300 : 300 + n_equal], uf[300 : 300 + n_equal] = yf[300], uf[300]
        p = _write(tmp_path, "t,temp,fuel\n" + "".join(
            f"{a!r},{b!r},{c!r}\n" for a, b, c in zip(t.tolist(), yf.tolist(), uf.tolist())))
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            Signals.from_csv(p, output="temp", inputs=["fuel"], time="t")
        frozen = [w for w in caught if "repeat the same values" in str(w.message)]
        assert len(frozen) == int(warns), [str(w.message) for w in caught]
        if warns:
            assert (f"{n_equal} rows from row 300 (t=300) to row {299 + n_equal} "
                    f"(t={299 + n_equal}) (0-based) repeat the same values in every column "
                    "used ('temp', 'fuel')") in str(frozen[0].message)
    # an output alone (K = 0: a quantised, settled response) repeats without a fault
    yq = np.round(3 * np.sin(t / 50.0))
    p = _write(tmp_path, "t,temp\n" + "".join(f"{a!r},{b!r}\n" for a, b in zip(t.tolist(),
                                                                            yq.tolist())))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        Signals.from_csv(p, output="temp", time="t")


def test_gap_warning_names_the_column(tmp_path):
    t = np.r_[np.arange(0.0, 40.0), np.arange(60.0, 100.0)]
    p = _write(tmp_path, "t,temp,fuel\n" + "".join(f"{a!r},{float(np.sin(a))!r},{float(np.cos(a))!r}\n"
                                                   for a in t.tolist()))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        Signals.from_csv(p, output="temp", inputs=["fuel"], time="t", resample=1.0)
    gaps = [str(w.message) for w in caught if "has a gap" in str(w.message)]
    assert len(gaps) == 2 and "'temp' has a gap from 39 to 60" in gaps[0]  # not 'y'
    assert "'fuel' has a gap" in gaps[1] and "--identify-window" in gaps[0]


def test_missing_sample_with_and_without_resample(tmp_path):
    """A missing cell is refused by its column and row, with the way round it: resample=DT,
    which drops missing samples and interpolates across them (with resample= it was refused
    as "y has a NaN or inf value at index (2,)", and the advice to resample went round in a
    loop)."""
    p = _write(tmp_path, "t,temp,fuel,tag\n0,1,2,OK\n1,2,5,OK\n2,,4,OK\n3,4,#N/A,OK\n4,5,6,OK\n")
    with pytest.raises(ValueError, match=r"column 'temp' has a NaN or inf sample at row 2 "
                                         r"\(0-based\); .*resample=DT or --resample DT drops"):
        Signals.from_csv(p, output="temp", inputs=["fuel"], time="t")
    s = Signals.from_csv(p, output="temp", inputs=["fuel"], time="t", resample=1.0,
                         intersample="foh")  # the unused text column 'tag' is not read
    np.testing.assert_array_equal(np.asarray(s.y), [1, 2, 3, 4, 5])
    np.testing.assert_array_equal(np.asarray(s.u)[:, 0], [2, 5, 4, 5, 6])
    # inf is a value, not a missing sample: refused by row (it was interpolated across, unsaid)
    p = _write(tmp_path, "t,temp,fuel\n0,1,2\n1,2,5\n2,inf,4\n3,4,5\n4,5,6\n")
    with pytest.raises(ValueError, match=r"column 'temp' has an inf sample at row 2 "
                                         r"\(0-based\); resample drops missing samples"):
        Signals.from_csv(p, output="temp", inputs=["fuel"], time="t", resample=1.0)



def test_a_time_column_with_a_missing_time_is_refused_by_row(tmp_path):
    """It said only "contains NaN or inf; clean it first": now the row, and the way round it
    (resample= drops rows without a time)."""
    p = _write(tmp_path, "t,temp,fuel\n0,1,2\n1,2,5\n,3,4\n3,4,5\n4,5,6\n")
    with pytest.raises(ValueError, match=r"the time column has a NaN or inf at row 2 "
                                         r"\(0-based\); drop that row .*resample=DT"):
        Signals.from_csv(p, output="temp", inputs=["fuel"], time="t")
    s = Signals.from_csv(p, output="temp", inputs=["fuel"], time="t", resample=1.0)
    np.testing.assert_array_equal(np.asarray(s.y), [1, 2, 3, 4, 5])
