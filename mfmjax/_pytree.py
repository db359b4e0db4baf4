"""Small pytree utilities shared by the containers (no numerics here)."""

from __future__ import annotations

import dataclasses


def build(cls, **fields):
    """An equinox Module of class `cls` from all its fields, without running `__init__` (as
    unflattening a pytree does): for containers assembled around a compiled call's outputs,
    whose values the program already checked."""
    new = object.__new__(cls)
    for f in dataclasses.fields(cls):
        object.__setattr__(new, f.name, fields.pop(f.name))
    if fields:
        raise TypeError(f"build(): {cls.__name__} has no fields {list(fields)}")
    return new


def replace_fields(module, **changes):
    """A copy of an equinox Module with some fields replaced, without re-running `__init__`.

    Used for static fields (labels, t0), which `eqx.tree_at` cannot reach: they are stripped
    before a jitted call, so that a new label or t0 never compiles a new program, and put back
    on the result.
    """
    new = object.__new__(type(module))
    for f in dataclasses.fields(module):
        object.__setattr__(new, f.name, changes.pop(f.name, getattr(module, f.name)))
    if changes:
        raise TypeError(f"replace_fields(): {type(module).__name__} has no fields {list(changes)}")
    return new
