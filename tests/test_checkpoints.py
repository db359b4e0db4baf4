"""Durable files: on-line checkpoints (format v2: leaves by pytree path, SHA-256, atomic write)
and model JSON files (atomic write, coefficients checked on load)."""

import json
import os
import subprocess
import sys
import zipfile

import numpy as np
import pytest

import mfmjax
from mfmjax import OnlineConfig, OnlineIdentifier, _online, _persist
from mfmjax.datasets import switching_experiment

CUT = 2345  # mid-interval, after the first model (interval 8 closes at 2000 s)
END = 3000


def _run(ident, t, y, u, chunk=97):
    for c0 in range(0, len(t), chunk):
        ident.update(t[c0 : c0 + chunk], y[c0 : c0 + chunk], u[c0 : c0 + chunk])
    return ident


@pytest.fixture(scope="module")
def record():
    t, y, u, _ = switching_experiment(n_intervals=20)
    cfg = OnlineConfig(dt=1.0, n_inputs=2, n=(2,), intersample=("foh", "zoh"))
    full = _run(OnlineIdentifier(cfg), t[:END], y[:END], u[:END])
    part = _run(OnlineIdentifier(cfg), t[:CUT], y[:CUT], u[:CUT])
    assert part.models, "the first model must exist before the cut"
    return t[:END], y[:END], u[:END], full, part


def _resume(path, t, y, u):
    ident = OnlineIdentifier.load(path)
    return _run(ident, t[CUT:], y[CUT:], u[CUT:], chunk=131)


def _assert_continues(resumed, part, full):
    a, b, r = full.series(), part.series(), resumed.series()
    for key in ("t", "y", "y_pred", "model_number"):
        np.testing.assert_array_equal(np.concatenate([b[key], r[key]]), a[key])  # exact
    assert resumed.models == full.models


def test_leaves_stored_by_path(record, tmp_path):
    *_, part = record
    path = tmp_path / "ck.npz"
    part.save(path)
    with zipfile.ZipFile(path) as z:
        names = set(z.namelist())
    assert {"header.npy", "sha256.npy", "state.buf_y.npy", "state.model['a'].npy"} <= names
    with np.load(path) as f:
        header = json.loads(str(f["header"]))
        np.testing.assert_array_equal(f["state.buf_y"], part.state.buf_y)
    assert header["version"] == _online.CHECKPOINT_VERSION == 2
    assert header["leaves"]["state.model['a']"] == ["<f8", [3]]
    back = mfmjax.online.load(path)
    import jax

    for x, z in zip(jax.tree_util.tree_leaves(part.state), jax.tree_util.tree_leaves(back)):
        assert x.dtype == z.dtype and np.array_equal(x, z, equal_nan=True)


def test_crash_mid_save_keeps_previous_checkpoint(record, tmp_path, monkeypatch):
    t, y, u, full, part = record
    path = tmp_path / "ck.npz"
    part.save(path)
    before = path.read_bytes()
    later = _resume(path, t, y, u)  # a later state, whose save will crash half-way

    def half_then_fail(fh, data):
        fh.write(data[: len(data) // 2])
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(_persist, "_write_all", half_then_fail)
    with pytest.raises(OSError, match="No space left"):
        later.save(path)
    monkeypatch.undo()
    assert path.read_bytes() == before
    assert os.listdir(tmp_path) == ["ck.npz"]  # the temporary file was removed
    _assert_continues(_resume(path, t, y, u), part, full)


def test_killed_process_mid_save_keeps_previous_checkpoint(record, tmp_path):
    """A real kill (os._exit half-way through the write, no cleanup): the old file survives."""
    t, y, u, full, part = record
    path = tmp_path / "ck.npz"
    part.save(path)
    code = (
        "import os, sys\n"
        "from mfmjax import _online, _persist\n"
        "state = _online.load(sys.argv[1])\n"
        "def die(fh, data):\n"
        "    fh.write(data[: len(data) // 2]); fh.flush(); os._exit(137)\n"
        "_persist._write_all = die\n"
        "_online.save(sys.argv[1], state)\n"
    )
    r = subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True, text=True)
    assert r.returncode == 137, r.stderr
    leftovers = [p for p in os.listdir(tmp_path) if p != "ck.npz"]
    assert len(leftovers) == 1 and leftovers[0].endswith(".tmp")  # never read by load
    _assert_continues(_resume(path, t, y, u), part, full)


@pytest.fixture(scope="module")
def good_bytes(record, tmp_path_factory):
    path = tmp_path_factory.mktemp("ck") / "good.npz"
    record[4].save(path)
    return path.read_bytes()


def _flip(data: bytes, at: int) -> bytes:
    return data[:at] + bytes([data[at] ^ 0xFF]) + data[at + 1 :]


@pytest.mark.parametrize(
    "damage, match",
    [
        (lambda b: b"", "is empty"),
        (lambda b: b[: len(b) // 2], "truncated or corrupted"),
        (lambda b: b[:100], "truncated or corrupted"),
        (lambda b: b"not a zip file at all", "truncated or corrupted"),
        (lambda b: _flip(b, len(b) // 3), "truncated or corrupted|checksum"),
        (lambda b: _flip(b, len(b) - 30), "truncated or corrupted|checksum"),
    ],
)
def test_damaged_checkpoint_refused(good_bytes, tmp_path, damage, match):
    path = tmp_path / "bad.npz"
    path.write_bytes(damage(good_bytes))
    with pytest.raises(ValueError, match=match):
        mfmjax.online.load(path)
    with pytest.raises(ValueError, match=match):
        OnlineIdentifier.load(path)


def _repack(path, good_bytes, edit, digest=None):
    """Rewrite a good checkpoint with edited leaves; a fresh checksum unless `digest` given."""
    src = path.parent / "src.npz"
    src.write_bytes(good_bytes)
    with np.load(src) as f:
        header = json.loads(str(f["header"]))
        arrays = {k: f[k] for k in f.files if k not in ("header", "sha256")}
        old_digest = str(f["sha256"])
    edit(arrays)
    data = _online._pack(header["config"], header["extra"], arrays)
    if digest == "old":
        import io

        with np.load(io.BytesIO(data)) as f:
            members = {k: f[k] for k in f.files}
        members["sha256"] = np.asarray(old_digest)
        with open(path, "wb") as fh:
            np.savez(fh, **members)
    else:
        path.write_bytes(data)


def test_checksum_catches_a_changed_value(good_bytes, tmp_path):
    path = tmp_path / "edited.npz"

    def bump(a):
        a["state.buf_y"] = a["state.buf_y"] + 1.0

    _repack(path, good_bytes, bump, digest="old")  # a valid zip whose payload changed
    with pytest.raises(ValueError, match="SHA-256 checksum"):
        mfmjax.online.load(path)


@pytest.mark.parametrize(
    "edit, match",
    [
        (lambda a: a.pop("state.op_count"), r"missing leaves \['state.op_count'\]"),
        (lambda a: a.update({"state.new_leaf": np.zeros(3)}),
         r"unknown leaves \['state.new_leaf'\]"),
        (lambda a: a.update({"state.buf_y": a["state.buf_y"][:-1]}), "leaf state.buf_y has"),
        (lambda a: a.update({"state.n_closed": np.asarray(1.5)}), "leaf state.n_closed has"),
    ],
)
def test_layout_change_refused(good_bytes, tmp_path, edit, match):
    path = tmp_path / "layout.npz"
    _repack(path, good_bytes, edit)
    with pytest.raises(ValueError, match=match):
        mfmjax.online.load(path)


def test_other_version_or_format_refused(tmp_path):
    path = tmp_path / "v1.npz"
    with open(path, "wb") as fh:  # version 1 stored leaves by position
        np.savez(fh, header=np.asarray('{"format": "mfmjax-online", "version": 1}'),
                 leaf0=np.zeros(1))
    with pytest.raises(ValueError, match="format version 1; this mfmjax reads version 2"):
        mfmjax.online.load(path)
    with open(path, "wb") as fh:
        np.savez(fh, x=np.zeros(2))
    with pytest.raises(ValueError, match="not an mfmjax on-line checkpoint"):
        mfmjax.online.load(path)
    with open(path, "wb") as fh:  # a bare .npy, not an archive
        np.save(fh, np.zeros(2))
    with pytest.raises(ValueError, match="truncated or corrupted"):
        mfmjax.online.load(path)
    with pytest.raises(ValueError, match="cannot read"):
        mfmjax.online.load(tmp_path / "missing.npz")


def test_save_refuses_non_state_and_non_json_extra(record, tmp_path):
    with pytest.raises(TypeError, match="state must be an OnlineState"):
        _online.save(tmp_path / "x.npz", {"t0": 1})
    with pytest.raises(ValueError, match="extra must be JSON data"):
        _online.save(tmp_path / "x.npz", record[4].state, extra={"f": object()})
    assert not os.listdir(tmp_path)


# -- model files --------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def model_doc(tmp_path_factory):
    from mfmjax.datasets import simulated_experiment, third_order_two_input

    sig = simulated_experiment(third_order_two_input(), dt=0.01, n_samples=2000)
    model = mfmjax.identify(sig, mfmjax.Structure(3, [1, 0]), mfmjax.ModulatingFunction(4, 5, 2.0))
    path = tmp_path_factory.mktemp("model") / "m.json"
    mfmjax.save_model(model, path)
    return model, json.loads(path.read_text())


def test_model_roundtrip(model_doc, tmp_path):
    model, doc = model_doc
    path = tmp_path / "m.json"
    mfmjax.save_model(model, path)
    back = mfmjax.load_model(path)
    np.testing.assert_array_equal(np.asarray(back.theta), np.asarray(model.theta))
    np.testing.assert_array_equal(np.asarray(back.a), np.asarray(model.a))
    assert int(back.status) == int(model.status)


def test_load_model_status_says_unstable_when_a_is(model_doc, tmp_path):
    """A hand-edited a with a right-half-plane root kept the file's `ok`; the unstable bit
    follows a (and leaves when a is stable again)."""
    doc = json.loads(json.dumps(model_doc[1]))
    assert doc["status"] == "ok"
    doc["a"][0] = -abs(doc["a"][0])  # a_0 < 0 < a_n: a real root in the right half plane
    path = tmp_path / "edited.json"
    path.write_text(json.dumps(doc))
    assert int(mfmjax.load_model(path).status) == int(mfmjax.Status.UNSTABLE)
    doc["a"][0], doc["status"] = abs(doc["a"][0]), "unstable"
    path.write_text(json.dumps(doc))
    assert int(mfmjax.load_model(path).status) == 0


@pytest.mark.parametrize(
    "change, match",
    [
        (lambda d: d.update(theta=d["theta"][:-1]), "theta has 6 values but n=3, m=.1, 0. need 7"),
        (lambda d: d.update(theta=d["theta"] + [0.1]), "theta has 8 values"),
        (lambda d: d["theta"].__setitem__(0, float("nan")), "theta contains NaN or inf"),
        (lambda d: d["a"].__setitem__(1, float("inf")), "a contains NaN or inf"),
        (lambda d: d["b"][0].__setitem__(0, float("nan")), r"b\[0\] contains NaN or inf"),
        (lambda d: d.update(offset=float("nan")), "offset must be a finite number"),
        (lambda d: d.update(status="wobbly"), "unknown flag 'wobbly'"),
        (lambda d: d.pop("delays"), "has no field 'delays'"),
        (lambda d: d.update(a="x"), "has a bad field"),
        # edited by hand: orders that disagree with the coefficients, N below n (eq. 5)
        (lambda d: d.update(n=2), r"n=2 but the coefficients a and b give n=3"),
        (lambda d: d.update(m=[1, 1]), r"m=\[1, 1\] but the coefficients a and b give m=\[1, 0\]"),
        (lambda d: d.update(N=2), "N=2 is below n=3; N must be >= n"),
        # h removed or null: loaded as a model without MF settings, J NaN, unsaid (an audit)
        (lambda d: d.pop("h"), "it has N, M but no h: a model identified by MFM stores N, M"),
        (lambda d: d.update(h=None), "it has N, M but no h"),
        (lambda d: d.update(M=None), "it has N, h but no M"),
        # a record save_model would refuse: accepted at load, then ignored or failing later
        (lambda d: d.update(record="abc"), "record must be what save_model writes"),
        (lambda d: d.update(record={"dt": -1.0}), "record must be what save_model writes"),
        (lambda d: d.update(record={"detrend": "quadratic"}), "record must be"),
        (lambda d: d.update(record={"columns": ["y"]}), "record must be"),
        (lambda d: d.update(record={"detrend": "linear", "trend": {"kind": "linear"}}),
         "record must be"),
    ],
)
def test_load_model_refuses_bad_coefficients(model_doc, tmp_path, change, match):
    doc = json.loads(json.dumps(model_doc[1]))
    change(doc)
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(doc))  # json writes NaN / Infinity literals, as a hand edit might
    with pytest.raises(ValueError, match=match):
        mfmjax.load_model(path)


def test_load_model_truncated_or_binary(model_doc, tmp_path):
    path = tmp_path / "m.json"
    mfmjax.save_model(model_doc[0], path)
    text = path.read_text()
    path.write_text(text[: len(text) // 2])
    with pytest.raises(ValueError, match="not valid JSON .*truncated or corrupted"):
        mfmjax.load_model(path)
    path.write_bytes(b"\x89PNG\r\n\x1a\n\xff\xfe")
    with pytest.raises(ValueError, match="not a text"):
        mfmjax.load_model(path)


def test_save_model_crash_keeps_previous(model_doc, tmp_path, monkeypatch):
    path = tmp_path / "m.json"
    mfmjax.save_model(model_doc[0], path)
    before = path.read_bytes()

    def half_then_fail(fh, data):
        fh.write(data[: len(data) // 2])
        raise KeyboardInterrupt  # a Ctrl-C mid-write

    monkeypatch.setattr(_persist, "_write_all", half_then_fail)
    with pytest.raises(KeyboardInterrupt):
        mfmjax.save_model(model_doc[0], path)
    assert path.read_bytes() == before and os.listdir(tmp_path) == ["m.json"]
