"""2D laser simulator on ground-truth worlds: worlds, sensors, ray casting, paths, logs.

``load_world`` → ``simulate`` → ``write_simulated_log`` (MCAP + ground-truth map_server map).
"""

from __future__ import annotations

from .raycast import cast_rays, raycast_distances
from .sensors import LASER_PRESETS, LaserSpec
from .world import PROCEDURAL_WORLDS, World, load_world

__all__ = ["World", "load_world", "PROCEDURAL_WORLDS", "LaserSpec", "LASER_PRESETS", "cast_rays",
           "raycast_distances", "plan_path", "SimulatedLog", "simulate", "write_simulated_log"]


def __getattr__(name: str):
    # path planning and log writing pull in scipy.sparse / the MCAP writer: import on first use
    if name == "plan_path":
        from .path import plan_path

        return plan_path
    if name in ("SimulatedLog", "simulate", "write_simulated_log"):
        from . import simulate as _sim

        return getattr(_sim, name)
    raise AttributeError(name)
