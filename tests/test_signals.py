import warnings

import numpy as np
import pytest

from mfmjax import Signals
from mfmjax._signals import read_csv


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
    "not uniformly sampled", with both steps printed as 0.1); a real jitter of 1e-3 s is not,
    where the stamps resolve it (written to 1e-4 s; written to 1e-3 s, a 1e-3 s step is what a
    grid half a quantum off the digits shows: accepted, test_prepare.py's 80 Hz in ms)."""
    y, u = _ok()
    t = 1.7e9 + 0.1 * np.arange(y.size)
    s = Signals.from_columns({"t": t, "y": y, "u": u[:, 0]}, output="y", inputs=["u"], time="t")
    # dt from the end stamps, each rounded by half a unit in the last place
    assert abs(s.dt - 0.1) <= np.spacing(t[-1]) / (y.size - 1) and s.t0 == t[0]
    t[20] += 1e-3
    t[30] += 1e-4  # stamps written to 1e-4 s
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


def _csv(tmp_path, name, text):
    path = tmp_path / name
    path.write_text(text)
    return path


def test_one_input_name_as_a_string_is_one_column(tmp_path):
    """inputs="heat" was split into its letters ("unknown column 'h'"), and inputs="uv" over
    columns t, y, u, v silently read two inputs u and v."""
    pd = pytest.importorskip("pandas")
    t = np.arange(40) * 0.5
    rows = "".join(f"{a},{np.sin(a)},{np.cos(a)},{a % 3}\n" for a in t)
    path = _csv(tmp_path, "h.csv", "t,y,heat,uv\n" + rows)
    s = Signals.from_csv(path, output="y", inputs="heat", time="t")
    assert s.input_names == ("heat",) and s.u.shape == (40, 1)
    assert Signals.from_csv(path, output="y", inputs="uv", time="t").input_names == ("uv",)
    df = pd.read_csv(path)
    assert Signals.from_dataframe(df, output="y", inputs="heat", time="t").input_names == \
        ("heat",)


def test_dataframe_labels_are_matched_as_text_and_duplicates_refused():
    """Integer labels: output=1 said "unknown column 1 ... the file has no header: give
    names=[...]" (DataFrames take no names=); a used duplicated label crashed with
    AttributeError."""
    pd = pytest.importorskip("pandas")
    t = np.arange(30) * 0.1
    df = pd.DataFrame({0: t, 1: np.sin(t), 2: np.cos(t)})
    s = Signals.from_dataframe(df, output=1, inputs=[2], time=0)
    assert (s.output_name, s.input_names, s.dt) == ("1", ("2",), pytest.approx(0.1))
    assert np.array_equal(np.asarray(s.y), np.sin(t))
    dup = pd.DataFrame(np.c_[t, np.sin(t), np.cos(t), t], columns=["t", "y", "u", "u"])
    with pytest.raises(ValueError, match=r"DataFrame: the column name\(s\) \['u'\] occur more "
                                         "than once: rename"):
        Signals.from_dataframe(dup, output="y", inputs=["u"], time="t")
    assert Signals.from_dataframe(dup, output="y", time="t").n_inputs == 0  # unused: fine


@pytest.mark.parametrize("text,match", [
    ("t;y;u\n0;1,5;2,5\n1;1,6;2,7\n", "fields are separated by ';'.*decimal=','"),
    ("time;T [degC, PV];P\n0;1,5;2,5\n1;1,6;2,7\n", "fields are separated by ';'"),
    ("t\ty\tu\n0\t1,5\t2,5\n1\t1,6\t2,7\n", "'1,5'.*a decimal comma\\?.*decimal=','"),
    ('t,y,u\n0,"1,5",2.5\n1,"1,6",2.7\n', "'1,5'.*a decimal comma\\?"),
    # a thousands separator: "1,000" is 1000 or, with a decimal comma, 1.0 (the hint named
    # decimal=',' alone, which reads 1.0); "12,345.5" can only be a separator
    ('t,y,u\n0,"1,000",2.5\n1,"1,250",2.7\n',
     "'1,000'.*thousands separator or a decimal comma\\?.*thousands=','.*or decimal=','"),
    ('t,y,u\n0,"12,345.5",2.5\n1,"1,250.0",2.7\n',
     "'12,345.5'.*a thousands separator\\? .*thousands=','\\) \\(1,000 is 1000\\) and "),
    # Python's float() reads "1_00" as 100 (digit grouping): it was read so, silently, on the
    # fast path and the careful one (an empty cell elsewhere)
    ("t,y,u\n0,1_00,2.5\n1,2,2.7\n", "'1_00'.*'_' inside a number.*1_00 as 100"),
    ("t,y,u\n0,1_00,2.5\n1,,2.7\n", "'1_00'.*'_' inside a number"),
])
def test_decimal_commas_are_named(tmp_path, text, match):
    """A European export (';' and decimal commas) said "unknown column 'y'; available:
    ['t;y;u']", "line 2 has 3 fields but the header has 2", or "the column holds text"."""
    path = _csv(tmp_path, "eu.csv", text)
    output, inputs, time = ("T [degC, PV]", ["P"], "time") if "PV" in text else \
        ("y", ["u"], "t")
    with pytest.raises(ValueError, match=match):
        Signals.from_csv(path, output=output, inputs=inputs, time=time)


def test_misleading_causes_are_named_rightly(tmp_path):
    """Each refusal names its real cause: a header read with names= ("a unit row under the
    header?"), a window that rounds to one sample ("must lie inside the record"), float32
    epoch times ("drop duplicate rows"), t0 beside a time column (ignored, or a raw
    TypeError with resample=), and a two-row record ("input 'u' is the output 'y' itself")."""
    path = _csv(tmp_path, "hdr.csv", "t,y,u\n0,1,2\n1,2,3\n2,3,1\n")
    with pytest.raises(ValueError, match="line 1 .*the file has a header row: drop names="):
        Signals.from_csv(path, output="y", inputs=["u"], time="t", names=["t", "y", "u"])
    y, u = _ok()
    s = Signals(y, u, dt=1.0, t0=2.0)
    with pytest.raises(ValueError, match=r"\(11.99, 12\) rounds to one sample \(t = 12\) of the "
                                         "grid of step 1; a window needs at least 2 samples"):
        s.window(11.99, 12.0)
    epoch = (1.7e9 + 0.5 * np.arange(50)).astype(np.float32)
    with pytest.raises(ValueError, match="the time column is float32, whose precision at "
                                         "1.7e\\+09 is 128: give it as float64"):
        Signals(y, u, t=epoch)
    # the same column through from_columns or a DataFrame: they converted it to float64 first,
    # and the advice was "sort the record or drop duplicate rows" for rows in order
    pd = pytest.importorskip("pandas")
    cols = {"t": epoch, "y": y, "u": u[:, 0]}
    for build in (lambda: Signals.from_columns(cols, output="y", inputs=["u"], time="t"),
                  lambda: Signals.from_dataframe(pd.DataFrame(cols), output="y", inputs=["u"],
                                                 time="t")):
        with pytest.raises(ValueError, match="the time column is float32, whose precision at "
                                             "1.7e\\+09 is 128: give it as float64"):
            build()
    with pytest.raises(ValueError, match="give either t .* or t0, not both"):
        Signals(y, u, t=np.arange(50.0), t0=5.0)
    with pytest.raises(ValueError, match="give either a time column .* or t0, not both"):
        Signals.from_csv(path, output="y", inputs=["u"], time="t", t0=5.0, resample=0.5)
    two = Signals(np.array([1.0, 3.0]), np.array([[2.0], [1.0]]), dt=2.0)
    assert two.n_samples == 2


def test_a_time_column_in_ms_resampled_in_seconds_warns(tmp_path):
    """Times in ms with resample=0.5 (meant in s) built 39,801 interpolated samples from 200
    rows without a word (only a grid coarser than the median step warned)."""
    t = np.arange(200) * 100.0  # ms
    rows = "".join(f"{a},{np.sin(a / 1e3)},{np.sign(np.sin(a / 7e2))}\n" for a in t)
    path = _csv(tmp_path, "ms.csv", "time,y,u\n" + rows)
    with pytest.warns(UserWarning, match=r"dt=0.5 is 200x finer than the output's median step "
                                         r"\(100\).*another unit than dt"):
        s = Signals.from_csv(path, output="y", inputs=["u"], time="time", resample=0.5)
    assert s.n_samples == 39801
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a grid within 10x of the step: no warning
        Signals.from_csv(path, output="y", inputs=["u"], time="time", resample=50.0)


def test_a_constant_output_away_from_zero_says_so_and_quoted_names_are_read(tmp_path):
    s = Signals(np.full(50, 7.0), np.sin(np.arange(50.0)), dt=1.0)
    assert "is constant at 7" in s.offset_note and "e+303" not in s.offset_note
    path = _csv(tmp_path, "q.csv", 't, "y", "u"\n0, 1, 2\n1, 2, 3\n2, 3, 1\n3, 1, 1\n')
    assert Signals.from_csv(path, output="y", inputs="u", time="t").input_names == ("u",)


def test_a_headless_file_starting_at_rest_gets_the_names_hint(tmp_path):
    """A first row with repeated values ("0,0,1", a record at rest) said only "duplicate
    column names ['0', '0', '1']": it gets the no-header hint as other numeric rows do."""
    path = _csv(tmp_path, "rest.csv", "0,0,1\n1,0.5,1\n2,0.8,1\n")
    with pytest.raises(ValueError, match=r"duplicate column names \['0', '0', '1'\]; the first "
                                         "line holds numbers, so the file has no header: give "
                                         r"the column names \(names="):
        Signals.from_csv(path, output="y", inputs=["u"], time="t")
    s = Signals.from_csv(path, output="y", inputs=["u"], time="t", names=["t", "y", "u"])
    assert s.n_samples == 3
    # a trailing separator (an empty last name, as the DaISy exchanger file's first line)
    # hid the hint: "unknown column 'theta'; available: ['1.0', '0.3', '98.6', '']"
    path = _csv(tmp_path, "trail.csv", "1.0,0.3,98.6,\n2.0,0.3,98.7,\n3.0,0.4,98.9,\n")
    with pytest.raises(ValueError, match=r"unknown column 'theta' for output; available: .*; "
                                         r"the first line holds numbers, so the file has no "
                                         r"header"):
        Signals.from_csv(path, output="theta", inputs=["q"], time="t")


@pytest.mark.parametrize("end", ["\n", "\r\n", "\r"])
def test_csv_line_ends_of_every_system_read_the_same(tmp_path, end):
    """Old-Mac line ends (CR alone) made the whole file one header line: `read_csv` raised
    the csv module's "new-line character seen in unquoted field", and the CLI called it a bug
    in mfmjax. LF, CRLF and CR read the same numbers now, with a BOM too, through the C
    path (all numbers) and the line parser (an empty cell)."""
    t = np.arange(50) * 0.1
    rows = [f"{float(a)!r},{float(np.sin(a))!r},{float(np.cos(a))!r}" for a in t]
    for body, nan_at in ((rows, None), (rows[:7] + [f"{float(t[7])!r},,1.0"] + rows[8:], 7)):
        path = tmp_path / f"r{nan_at}.csv"
        path.write_bytes(("\ufeff" + end.join(["t,y,u", *body]) + end).encode("utf-8"))
        cols = read_csv(path)
        assert list(cols) == ["t", "y", "u"] and cols["t"].size == 50
        np.testing.assert_array_equal(cols["t"], t)
        y = np.sin(t)
        if nan_at is not None:
            y[nan_at] = np.nan
        np.testing.assert_array_equal(cols["y"], y)


def test_concatenate_says_when_one_offset_term_cannot_serve_records_at_other_levels():
    """Records of one plant at output levels 50 and 80 (inputs alike), each with an offset
    term, joined: one offset term cannot fit both, and estimate returned a static gain of 650
    for 1, unsaid, under record 0's note "the output sits at 50.1". Warned now, the joined
    note names every record's decision; records at one level join silently. Epoch-stamped
    records at one step join (dt 0.10000000031895462 against 0.1 was refused, both printed
    as 0.1); a step that differs is refused with its full digits."""
    rng = np.random.default_rng(0)
    u = rng.standard_normal((2, 400))
    y = 0.5 * rng.standard_normal((2, 400))
    at = [Signals(y[i] + lvl, u[i], dt=0.05, offset=True) for i, lvl in enumerate((50.0, 80.0))]
    with pytest.warns(UserWarning, match=r"concatenate\(\): the records' outputs sit at 49.98, "
                                         r"80.03, further apart than any record's own spread "
                                         r"\(0.505\), while their inputs sit at the same "
                                         r"levels, and one offset term serves them all"):
        joined, _ = Signals.concatenate(at)
    assert joined.offset and joined.offset_note == at[0].offset_note  # both given: one note
    auto = [Signals(y[i] + 50.0 + 0.1 * i, u[i], dt=0.05) for i in range(2)]
    assert auto[0].offset and auto[0].offset_note != auto[1].offset_note
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the same level: nothing to say
        joined, _ = Signals.concatenate(auto)
    assert joined.offset_note.startswith("one offset term for the 2 joined records (their own "
                                         f"notes: record 0: {auto[0].offset_note}; record 1: ")
    epoch = [Signals(np.sin(np.arange(T)), np.cos(np.arange(T)),
                     t=1.7e9 + 0.1 * np.arange(T), offset=False) for T in (300, 101)]
    assert epoch[0].dt != epoch[1].dt and abs(epoch[0].dt - epoch[1].dt) < 1e-9
    joined, windows = Signals.concatenate(epoch)
    assert joined.n_samples == 401 and joined.dt == epoch[0].dt
    # records on one equilibrium line (the input's level moves the output's): no warning
    line = [Signals(2.0 * lvl + 3.0 + y[i], lvl + u[i], dt=0.05, offset=True)
            for i, lvl in enumerate((0.0, 5.0))]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        Signals.concatenate(line)
    other = Signals(np.zeros(50), np.zeros(50), dt=0.1000001, offset=False)
    with pytest.raises(ValueError, match=r"record 1 has dt=0.1000001, record 0 has "
                                         r"0.100000000318955; experiments must match"):
        Signals.concatenate([epoch[0], other])


def test_long_rounded_grids_and_names_as_strings():
    """A 99.99 Hz logger writing ms (its step 0.0100010 s, within 1 % of 10 quanta, so its
    stamps slip one quantum over the record) is a rounded grid (a rule refusing whole-quantum
    slips of whole-quanta steps refused it); `Signals` keeps its input names as strings (a
    record named 1, 2 made `estimate` fail in `Model.labelled`)."""
    t = np.round(np.arange(1000) / 99.99, 3)
    sig = Signals(y=np.zeros(1000), t=t)
    # the stamps fix the step to their quantum over the record, q / (T - 1)
    assert abs(sig.dt - 1 / 99.99) <= 1e-3 / 999
    assert Signals(np.zeros(50), np.ones((50, 2)), dt=1.0, input_names=[1, 2]).input_names \
        == ("1", "2")
    from mfmjax._signals import nearly_dependent_inputs

    # independent +-1 inputs about a level of 20, no offset term: the shared level is no
    # collinearity (they were called nearly collinear, 0.036)
    rng = np.random.default_rng(2)
    u = 20.0 + np.sign(rng.standard_normal((400, 2)))
    assert nearly_dependent_inputs(Signals(np.zeros(400), u, dt=1.0, offset=False)) == ((), 1.0)
    close = np.column_stack([u[:, 0], u[:, 0] + 0.01 * rng.standard_normal(400)])
    names, ratio = nearly_dependent_inputs(Signals(np.zeros(400), close, dt=1.0, offset=False))
    assert names == ("u1", "u2") and ratio < 0.05


def test_an_input_named_twice_is_refused():
    """One column given twice as an input (`from_columns(inputs=["a", "a"])`) was accepted,
    and `estimate` then raised numpy's LinAlgError from inside its stages."""
    y, u = np.zeros(40), np.ones((40, 2))
    for build in (lambda: Signals(y, u, dt=1.0, input_names=["a", "a"]),
                  lambda: Signals.from_columns({"y": y, "a": u[:, 0]}, output="y",
                                               inputs=["a", "a"], dt=1.0)):
        with pytest.raises(ValueError, match=r"input_names has \['a'\] more than once; name "
                                             "each input once"):
            build()


def test_held_inputs_read_as_foh_are_named_and_sensors_are_not():
    """`held_inputs_note` (estimate's notes): a PRBS held over runs, and one clocked every
    sample (two levels, half its steps repeat), read as foh; not a quantised smooth sensor
    (runs, but jumps of one quantum), a smooth input, one read as zoh, or a single step."""
    from mfmjax._signals import held_inputs_note

    rng = np.random.default_rng(0)
    t = np.arange(2000) * 0.05
    runs = np.repeat(rng.choice([-1.0, 1.0], 250), 8)
    clocked = rng.choice([-1.0, 1.0], 2000)
    sensor = np.round(np.sin(0.3 * t), 1)  # 0.1 resolution: runs of equal samples
    coarse = np.round(4 * np.sin(0.1 * t)) / 4  # 0.25 of a range of 2 (9 levels, a review)
    step = (t > 10).astype(float)
    y = np.sin(t) + 0.1 * rng.standard_normal(2000)
    multi = np.repeat(rng.normal(size=250), 8)  # a held multi-level signal
    sig = Signals(y, np.column_stack([runs, clocked, sensor, step, coarse, multi]), dt=0.05,
                  input_names=["prbs", "fast", "sensor", "step", "coarse", "multi"])
    note, = held_inputs_note(sig)
    assert note.startswith("the input(s) ['prbs', 'fast', 'multi'] switch between levels"), note
    assert held_inputs_note(Signals(y, np.column_stack([runs, clocked]), dt=0.05,
                                    intersample="zoh")) == ()
    assert held_inputs_note(Signals(y, runs, dt=0.05, smooth=True)) == ()
