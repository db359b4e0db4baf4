"""Result codes shared by every computation that can fail on data (bit flags).

Batched paths never raise for one bad candidate: they set bits here and go on.
"""

from __future__ import annotations

import enum


class Status(enum.IntFlag):
    """Bit flags describing the quality of one identified model / candidate."""

    OK = 0
    NONFINITE = 1  # non-finite data or non-finite result
    ILL_CONDITIONED = 2  # reduced Gram matrix (orthogonal to eta) numerically singular
    NO_EXCITATION = 4  # an input is constant / zero on the window: its columns are masked
    A_N_ZERO = 8  # leading coefficient a_n vanished: a, b left un-normalised
    UNSTABLE = 16  # model has a pole with positive real part
    UNOBSERVABLE = 32  # observer Gramian numerically singular (window too short / pair unobservable)
    OVERFLOW = 64  # simulation left the float64 range (unstable model on a long window)
    OUT_OF_BOUNDS = 128  # traced h + delay exceed the static bound (h_max, delay_max) compiled
    # for, or a traced setting is outside its valid range (N, M < n, h < 2 dt, delay < 0, ...)


def describe(status: int) -> str:
    """Readable names of the bits set in `status` ("ok" when none)."""
    status = int(status)
    if status == 0:
        return "ok"
    return ",".join(
        flag.name.lower() for flag in Status if flag.value and status & flag.value
    )
