"""Reading optimistix results: the solver codes that refinement and output error report."""

from __future__ import annotations

USABLE = ("successful", "max_steps_reached", "nonlinear_max_steps_reached")  # codes kept


def solver_code(result) -> str:
    """The name of an optimistix `RESULTS` value ("failed" for any other error)."""
    import optimistix as optx  # imported by the caller's solver already

    for name in ("successful", "max_steps_reached", "nonlinear_divergence",
                 "nonlinear_max_steps_reached"):
        if hasattr(optx.RESULTS, name) and result == getattr(optx.RESULTS, name):
            return name
    return "failed"
