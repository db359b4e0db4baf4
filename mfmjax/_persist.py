"""Save / load a model as JSON (coefficients, structure, MF settings, delays, modes, version),
and the durable write that every mfmjax file goes through (`atomic_write`)."""

from __future__ import annotations

import contextlib
import json
import math
import os
import tempfile

import jax
import numpy as np

from ._boundary import eager_only, require_x64
from ._model import Model, is_stable
from ._modulating import ModulatingFunction, as_values
from ._pytree import replace_fields
from ._status import Status

FORMAT = "mfmjax-model"
VERSION = 1


def _write_all(fh, data: bytes) -> None:  # one place to fail in tests (a crash mid-write)
    fh.write(data)


def json_safe(x):
    """Strict JSON data: NaN / inf floats as None, tuples as lists, numpy values as Python ones
    (the text output next to the JSON says what a None meant)."""
    if isinstance(x, dict):
        return {str(k): json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [json_safe(v) for v in x]
    if isinstance(x, np.ndarray):
        return json_safe(x.tolist())
    if isinstance(x, np.generic):
        x = x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def atomic_write(path, data: bytes) -> None:
    """Write `data` to `path` so that `path` always holds either its old or its new content.

    The bytes go to a temporary file in the same folder, which is flushed to disk (fsync) and
    then renamed over `path` (`os.replace`, atomic on POSIX and Windows). A crash or an error
    half-way leaves the previous file untouched (an error also removes the temporary file; a
    killed process may leave a `.<name>.*.tmp` file behind, which is never read).
    """
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):  # else the error names the temporary file, not `path`
        raise FileNotFoundError(f"cannot write {path}: the folder {folder} does not exist; "
                                "create it first")
    if os.path.isdir(path):  # (the rename's error named the temporary file)
        raise IsADirectoryError(f"cannot write {path}: it is a folder; give a file name, e.g. "
                                f"{os.path.join(path, 'model.json')}")
    try:
        mode = os.stat(path).st_mode & 0o777
    except OSError:
        mask = os.umask(0)
        os.umask(mask)
        mode = 0o666 & ~mask
    fd, tmp = tempfile.mkstemp(prefix=f".{os.path.basename(path)}.", suffix=".tmp", dir=folder)
    try:
        with os.fdopen(fd, "wb") as fh:
            _write_all(fh, data)
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, mode)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    with contextlib.suppress(OSError):  # make the rename itself durable (POSIX)
        dfd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)


# how the identification data were read (`save_model`); with a trend, the clock its lines are
# on: the file, its time column (None: a step, times from 0) and first time (the CLI's)
RECORD_KEYS = ("dt", "detrend", "trend", "columns", "file", "time", "start")
FIELDS = ("format", "version", "n", "m", "a", "b", "delays", "intersample", "offset", "theta", "J",
          "J_rel", "cond", "status", "output_name", "input_names", "N", "M", "h", "record",
          "covariance", "joint_covariance")  # what `save_model` writes (`Model.to_dict` and
# its own entries)


def save_model(model: Model, path, *, covariance=None, joint_covariance=None,
               record=None) -> None:
    """Write `model` (concrete) to a JSON file (atomically: see `atomic_write`).

    `covariance` (optional): of the free parameters (`Estimate.covariance`,
    `OutputErrorFit.covariance`), stored with their names for `mfmjax report`'s bands;
    `load_model` ignores it, and files without it stay valid. `joint_covariance` (optional):
    a fit's covariance of the free parameters and each input's delay (`joint_covariance` of
    `OutputErrorFit` or `Estimate`, whose delays were fitted), stored beside it so that the
    bands of the loaded model hold the delays' uncertainty (`load_covariance(path,
    joint=True)`); a delay fitted down to its bound 0 counts as known. `record` (optional): how the
    identification data were read, `{"dt": step, "detrend": None | "linear" | "constant"}`
    (the CLI stores it; `mfmjax validate` and `report` compare it with their data's and say
    where it differs: a model of detrended data on raw data gave fit -23434 %), and with
    --detrend `"trend"`: the removed lines (`Trend.to_dict`), which validate and report then
    remove from their data instead of fitting lines of their own."""
    require_x64("save_model")
    if not isinstance(model, Model):
        raise TypeError(f"save_model(): model must be a Model (e.g. from identify or "
                        f"estimate(...).model), got {type(model).__name__}")
    eager_only("save_model", model, covariance)
    doc = {"format": FORMAT, "version": VERSION, **model.to_dict()}
    if covariance is not None:
        from ._output_error import free_parameters

        names = free_parameters(model)[0]
        cov = np.asarray(covariance, dtype=np.float64)
        if cov.shape != (len(names), len(names)):
            raise ValueError(f"save_model(): covariance must be a finite ({len(names)}, "
                             f"{len(names)}) matrix ordered as {list(names)} (got shape "
                             f"{cov.shape})")
        if not np.all(np.isfinite(cov)):  # (it named the shape, which was right)
            raise ValueError("save_model(): covariance has non-finite entries (NaN or inf): a "
                             "model without standard errors (an estimate whose method is "
                             "'mfm') or with a parameter the data do not determine has no "
                             "usable covariance; save the model without it (covariance=None)")
        doc["covariance"] = {"names": list(names), "matrix": cov.tolist()}
    if joint_covariance is not None:
        from ._analysis import usable_joint

        names = joint_names(model)
        joint = usable_joint(model, joint_covariance)
        if joint is None:
            raise ValueError(f"save_model(): joint_covariance must be a ({len(names)}, "
                             f"{len(names)}) matrix ordered as {names}, finite but for a "
                             "delay's rows (a delay fitted down to its bound 0); save the model "
                             "without it where a parameter is undetermined")
        doc["joint_covariance"] = {"names": names, "matrix": joint.tolist()}
    if record is not None:
        if not _record_ok(record, model):
            raise ValueError(f"save_model(): record must be a dict with keys from {RECORD_KEYS}: "
                             "dt a finite step > 0, detrend None, 'linear' or 'constant', "
                             f"trend Trend.to_dict() of that kind and the model's inputs, "
                             "columns the output's and inputs' names, file a path, time a "
                             f"column name or None, start a finite time (got {record!r})")
        doc["record"] = {k: (float(v) if k == "dt" else v) for k, v in record.items()}
    atomic_write(path, (json.dumps(doc, indent=2, allow_nan=False) + "\n").encode())


def joint_names(model: Model) -> list:
    """The rows of a joint covariance: the free parameters, then "delay <input>" per input."""
    from ._output_error import free_parameters

    return [*free_parameters(model)[0], *(f"delay {n}" for n in model.input_names)]


def _record_ok(record, model: Model) -> bool:
    """`record` is what `save_model` accepts (and writes)."""
    dt = record.get("dt") if isinstance(record, dict) else None
    return not (not isinstance(record, dict) or set(record) - set(RECORD_KEYS)
                or ("dt" in record and not (isinstance(dt, (int, float)) and not isinstance(
                    dt, bool) and math.isfinite(dt) and dt > 0))
                or record.get("detrend") not in (None, "linear", "constant")
                or not _trend_ok(record.get("trend"), record.get("detrend"),
                                 model.n_inputs)
                or ("columns" in record and not (
                    isinstance(record["columns"], list)
                    and len(record["columns"]) == model.n_inputs + 1
                    and all(isinstance(c, str) for c in record["columns"])))
                or ("file" in record and not isinstance(record["file"], str))
                or ("time" in record and not isinstance(record["time"], str | None))
                or ("start" in record and not (
                    isinstance(record["start"], int | float)
                    and not isinstance(record["start"], bool)
                    and math.isfinite(record["start"]))))


def _trend_ok(trend, kind, n_inputs: int) -> bool:
    if trend is None:
        return True
    from ._prepare import Trend

    try:
        lines = Trend.from_dict(trend)
        return lines.kind == kind and lines.n_inputs == n_inputs
    except (ValueError, TypeError, AttributeError):
        return False


def load_covariance(path, model: Model | None = None, *, joint: bool = False):
    """The covariance `save_model(..., covariance=...)` stored in a model file (of
    `free_parameters(model)`, `model` default `load_model(path)`), checked against the model's
    free parameters; None when the file holds none. With `joint=True`, the joint covariance
    of the parameters and each input's delay (`save_model(..., joint_covariance=...)`; None
    when the file holds none: its delays count as known). For the bands of `step_response`
    and `frequency_response` on a loaded model (`mfmjax report` reads it the same way)."""
    from ._analysis import PSD_TOL, _least_correlation_eigenvalue
    from ._output_error import free_parameters

    model = load_model(path) if model is None else model
    with open(path, "rb") as fh:  # load_model has read and checked it
        doc = json.loads(fh.read().decode("utf-8"))
    key = "joint_covariance" if joint else "covariance"
    entry = doc.get(key) if isinstance(doc, dict) else None
    if entry is None:
        return None
    free = joint_names(model) if joint else list(free_parameters(model)[0])
    try:
        names, cov = list(entry["names"]), np.asarray(entry["matrix"], dtype=np.float64)
    except (KeyError, TypeError, ValueError):
        raise ValueError(f"load_covariance(): {path}: the {key} entry needs 'names' and a "
                         "numeric 'matrix'") from None
    if names != free or cov.shape != (len(free), len(free)) or not np.all(np.isfinite(cov)):
        raise ValueError(f"load_covariance(): {path}: the {key} is not a finite matrix "
                         f"over the model's {'parameters and delays' if joint else 'free parameters'}"
                         f" {free} (got names {names}, shape {cov.shape})")
    if not (np.allclose(cov, cov.T, rtol=1e-12, atol=0.0) and np.all(np.diag(cov) >= 0)):
        raise ValueError(f"load_covariance(): {path}: the {key} must be symmetric with a "
                         "non-negative diagonal (edited by hand?); save it again with "
                         f"save_model(..., {key}=...)")
    worst = _least_correlation_eigenvalue(cov)
    if worst < -PSD_TOL:  # (it reached step_response, whose error named neither file nor field)
        raise ValueError(f"load_covariance(): {path}: the {key} is not positive semidefinite "
                         f"(its correlation matrix has the eigenvalue {worst:.3g}; edited by "
                         f"hand?); save it again with save_model(..., {key}=...)")
    return cov


def load_model(path) -> Model:
    """Read a model written by `save_model`; clear errors for malformed or foreign files.

    Refuses non-finite or mis-sized coefficients (a, b, offset, theta), an unknown status and
    a theta whose length does not match the structure (n + 1 + sum(m_k + 1) [+ 1 offset], or
    one less: a fitted model's free parameters, which it keeps as its theta).
    """
    require_x64("load_model")
    if not isinstance(path, (str, bytes, os.PathLike)):
        raise TypeError(f"load_model(): path must be a file name, got {type(path).__name__}")
    try:
        with open(path, "rb") as fh:
            raw = fh.read()
    except OSError as err:
        raise ValueError(f"load_model(): cannot read {path}: {err.strerror}") from None
    try:
        doc = json.loads(raw.decode("utf-8"))
    except UnicodeDecodeError:
        raise ValueError(f"load_model(): {path} is not a text (JSON) file") from None
    except json.JSONDecodeError as err:
        raise ValueError(f"load_model(): {path} is not valid JSON ({err.msg}; truncated or "
                         "corrupted?)") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise ValueError(f"load_model(): {path} is not an mfmjax model file")
    version = doc.get("version")
    if type(version) is not int or version != VERSION:  # (True == 1 in Python)
        raise ValueError(
            f"load_model(): {path} has format version {version!r}, this mfmjax reads "
            f"version {VERSION}; re-save it with a matching mfmjax"
        )
    try:
        _check_kinds(doc)
        model = Model.from_coefficients(
            doc["a"],
            doc["b"],
            offset=_finite_or_none(doc.get("offset"), "offset"),
            delays=doc["delays"],
            intersample=doc["intersample"],
            output_name=doc.get("output_name", "y"),
            input_names=doc.get("input_names"),
        )
        for key, own in (("n", model.n), ("m", list(model.m))):  # edited by hand: agree
            if key in doc and doc[key] != own:
                raise ValueError(f"{key}={doc[key]!r} but the coefficients a and b give "
                                 f"{key}={own}")
        given = [k for k in ("N", "M", "h") if doc.get(k) is not None]
        if given and len(given) < 3:  # (a null h loaded N, M and J as a model without them)
            missing = [k for k in ("N", "M", "h") if k not in given]
            raise ValueError(f"it has {', '.join(given)} but no {', '.join(missing)}: a model "
                             "identified by MFM stores N, M and h (save it again), one of "
                             "another method none of them")
        if given:
            model = _with_mf(model, doc)
        else:  # a model without MF settings (output error, SRIVC, estimate) keeps its status
            model = replace_fields(model, status=np.int32(_status(doc.get("status"))),
                                   **_free_theta(model, doc.get("theta")), **{
                                       k: jax.device_put(np.float64(doc[k])) for k in
                                       ("J", "J_rel", "cond") if doc.get(k) is not None})
        if "record" in doc and not _record_ok(doc["record"], model):
            raise ValueError(f"record must be what save_model writes: a dict with keys from "
                             f"{RECORD_KEYS}, dt a finite step > 0, detrend null, 'linear' or "
                             "'constant', trend its lines for the model's inputs, columns the "
                             "output's and inputs' names, file a path, time a column name or "
                             f"null, start a finite time (got {doc['record']!r})")
        # the unstable bit follows a (a hand-edited a kept `ok`)
        unstable = not is_stable(np.asarray(model.a))
        status = (int(model.status) & ~int(Status.UNSTABLE)) | (int(Status.UNSTABLE) * unstable)
        model = replace_fields(model, status=jax.device_put(np.int32(status)))
    except KeyError as err:
        raise ValueError(f"load_model(): {path} is missing or has a bad field: it has no field {err}") from None
    except (TypeError, ValueError) as err:
        msg = str(err).splitlines()[0] if str(err) else type(err).__name__
        raise ValueError(f"load_model(): {path} is missing or has a bad field: {msg}") from None
    return model


def _check_kinds(doc: dict) -> None:
    """Every field of a model file of the kind `save_model` writes (a hand-edited file took
    strings as coefficients, null delays as zeros, a bool J as 1 and "ab" as two names)."""
    unknown = sorted(set(doc) - set(FIELDS))
    if unknown:  # a hand-edited "offest": 1.2 was ignored and the model loaded without offset
        raise ValueError(f"unknown field(s) {unknown} (a typo?); a model file has the fields "
                         f"{list(FIELDS)}")

    def number(v):
        return isinstance(v, (int, float)) and not isinstance(v, bool)

    def numbers(key, v, depth=1):
        ok = isinstance(v, list) and all(
            number(x) if depth == 1 else isinstance(x, list) and all(number(y) for y in x)
            for x in v)
        if not ok:
            raise ValueError(f"{key} must be a list{' of lists' * (depth - 1)} of numbers "
                             f"(got {v!r})")

    numbers("a", doc["a"])
    numbers("b", doc["b"], depth=2)
    numbers("delays", doc["delays"])
    if "theta" in doc:
        numbers("theta", doc["theta"])
    for key in ("offset", "J", "J_rel", "cond", "N", "M", "h"):
        v = doc.get(key)
        if v is not None and not number(v):
            raise ValueError(f"{key} must be a number or null (got {v!r})")
        if key in ("J", "J_rel", "cond") and v is not None and v < 0:
            raise ValueError(f"{key} must be >= 0 (got {v!r})")
    if not isinstance(doc.get("output_name", "y"), str):
        raise ValueError(f"output_name must be a string (got {doc['output_name']!r})")
    names = doc.get("input_names")
    if names is not None and not (isinstance(names, list)
                                  and all(isinstance(v, str) for v in names)):
        raise ValueError(f"input_names must be a list of strings (got {names!r})")


def _free_theta(model: Model, theta) -> dict:
    """{"theta": ...} where the file's theta is a fitted model's free parameters (output error,
    SRIVC, `estimate`: a_0..a_{n-1}, the b_kj, the offset), which `from_coefficients` would
    replace by its normalised [a; b; offset]; {} for that full-length one (rebuilt the same)
    or none."""
    if theta is None:
        return {}
    theta = np.asarray(theta, dtype=np.float64)
    full = model.structure.n_params + int(model.has_offset)
    if theta.shape == (full,):
        return {}
    if theta.shape != (full - 1,):
        raise ValueError(f"theta has {theta.size} values but n={model.n}, m={list(model.m)}"
                         f"{' and an offset' if model.has_offset else ''} need {full} (or "
                         f"{full - 1} free parameters)")
    if not np.all(np.isfinite(theta)):
        raise ValueError("theta contains NaN or inf")
    return {"theta": jax.device_put(theta)}  # NumPy on the device: no eager program


def _finite_or_none(v, name):
    if v is None:
        return None
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise ValueError(f"{name} must be a finite number or null (got {v!r})")
    return float(v)


def _status(text) -> int:
    if text is None or text == "ok":
        return 0
    names = {f.name.lower(): f.value for f in Status}
    bits = 0
    for part in str(text).split(","):
        if part not in names:
            raise ValueError(f"status has the unknown flag {part!r} (known: {sorted(names)})")
        bits |= names[part]
    return bits


def _with_mf(model: Model, doc: dict) -> Model:
    import equinox as eqx
    import jax

    mf = as_values(ModulatingFunction(doc["N"], doc["M"], doc["h"]))  # as identify's
    for key in ("N", "M"):  # eq. 5: as identify requires
        if float(doc[key]) < model.n:
            raise ValueError(f"{key}={doc[key]} is below n={model.n}; {key} must be >= n")
    theta = np.asarray(doc["theta"], dtype=np.float64)
    size = model.structure.n_params + int(model.has_offset)
    if theta.shape != (size,):
        raise ValueError(
            f"theta has {theta.size} values but n={model.n}, m={list(model.m)}"
            f"{' and an offset' if model.has_offset else ''} need {size}"
        )
    if not np.all(np.isfinite(theta)):
        raise ValueError("theta contains NaN or inf")
    values = dict(theta=theta, status=np.int32(_status(doc.get("status"))))
    for key in ("J", "J_rel", "cond"):
        values[key] = np.float64(np.nan if doc.get(key) is None else float(doc[key]))
    fields = dict(mf=mf, **jax.device_put(values))  # NumPy on the device: no eager programs
    return eqx.tree_at(
        lambda m: [getattr(m, k) for k in fields], model, list(fields.values()),
        is_leaf=lambda x: x is None,
    )
