"""Scenarios in the plane-strain layout of the NumPy references: the initial material points,
grid and boundaries from a configuration (the engine's own set-up is segmpm.engine.setup)."""

from __future__ import annotations

from ..config import Config
from ..state import State
from .builders import attach_segregation, build_bar, build_box, build_chute, build_collapse

BUILDERS = {
    "chute": build_chute,
    "collapse": build_collapse,
    "bar": build_bar,
    "box": build_box,
}


def build(cfg: Config) -> State:
    """Initial state of the scenario ``cfg.scenario.kind``, with its concentration grid (the
    column model's elements and nodes with ``scenario.solver = "column"``)."""
    if cfg.scenario.solver == "column":
        from ..column import build_column

        return build_column(cfg)
    st = BUILDERS[cfg.scenario.kind](cfg)
    attach_segregation(cfg, st)
    return st


__all__ = ["build", "BUILDERS"]
