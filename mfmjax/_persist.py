"""Save / load a model as JSON (coefficients, structure, MF settings, delays, modes, version)."""

from __future__ import annotations

import json

import numpy as np

from ._model import Model
from ._modulating import ModulatingFunction

FORMAT = "mfmjax-model"
VERSION = 1


def save_model(model: Model, path) -> None:
    """Write `model` (concrete) to a JSON file."""
    doc = {"format": FORMAT, "version": VERSION, **model.to_dict()}
    with open(path, "w") as fh:
        json.dump(doc, fh, indent=2)


def load_model(path) -> Model:
    """Read a model written by `save_model`; clear errors for malformed or foreign files."""
    try:
        with open(path) as fh:
            doc = json.load(fh)
    except OSError as err:
        raise ValueError(f"load_model(): cannot read {path}: {err.strerror}") from None
    except json.JSONDecodeError as err:
        raise ValueError(f"load_model(): {path} is not valid JSON ({err.msg})") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise ValueError(f"load_model(): {path} is not an mfmjax model file")
    if doc.get("version") != VERSION:
        raise ValueError(
            f"load_model(): {path} has format version {doc.get('version')}, this mfmjax reads "
            f"version {VERSION}; re-save it with a matching mfmjax"
        )
    try:
        model = Model.from_coefficients(
            doc["a"],
            doc["b"],
            offset=doc.get("offset"),
            delays=doc["delays"],
            intersample=doc["intersample"],
            output_name=doc.get("output_name", "y"),
            input_names=doc.get("input_names"),
        )
        if doc.get("h") is not None:
            model = _with_mf(model, doc)
    except (KeyError, TypeError) as err:
        raise ValueError(f"load_model(): {path} is missing or has a bad field ({err})") from None
    return model


def _with_mf(model: Model, doc: dict) -> Model:
    import equinox as eqx
    import jax.numpy as jnp

    mf = ModulatingFunction(doc["N"], doc["M"], doc["h"])
    fields = dict(mf=mf, theta=jnp.asarray(np.asarray(doc["theta"], dtype=np.float64)))
    for key in ("J", "J_rel", "cond"):
        fields[key] = jnp.asarray(np.nan if doc.get(key) is None else float(doc[key]))
    return eqx.tree_at(
        lambda m: [getattr(m, k) for k in fields], model, list(fields.values()),
        is_leaf=lambda x: x is None,
    )
