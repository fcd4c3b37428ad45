"""Robot presets (thesis 7.1) and their controllers.

``make_robot(cfg, tag_ids)`` builds the preset named by ``cfg.preset``:
``lru`` (narrow stereo 50.6 deg), ``lru_wide`` (wide stereo 112.8 deg), ``ardea``
(hexacopter, two stereo pairs tilted +-60 deg).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

from sim.robots.ardea import Ardea
from sim.robots.base import Robot, RobotError, WaypointRecord, WheelState
from sim.robots.lru import LRU, LRUWide

if TYPE_CHECKING:  # sim.scenario imports PRESETS to validate robots
    from sim.scenario import RobotConfig

__all__ = ["LRU", "PRESETS", "Ardea", "LRUWide", "Robot", "RobotError", "WaypointRecord", "WheelState", "make_robot"]

PRESETS: dict[str, type[Robot]] = {"lru": LRU, "lru_wide": LRUWide, "ardea": Ardea}


def make_robot(cfg: RobotConfig, tag_ids: Sequence[int]) -> Robot:
    """The robot of preset ``cfg.preset`` carrying AprilTags ``tag_ids`` (``cfg.marker_count`` of them)."""
    if cfg.preset not in PRESETS:
        raise RobotError(f"robot {cfg.name}: unknown preset {cfg.preset!r}; known: {sorted(PRESETS)}")
    return PRESETS[cfg.preset](cfg, tag_ids)
