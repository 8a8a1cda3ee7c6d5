"""2D laser simulator on ground-truth worlds: worlds, sensors, ray casting, paths, logs.

``load_world`` → ``simulate``; :func:`slam.logs.simulated.write_simulated_log` writes the run as a log (MCAP +
ground-truth map_server map).

Note: the function :func:`simulate` shadows its module ``evaluation.sim.simulate`` as an attribute
of this package (both are importable: ``from evaluation.sim.simulate import ...`` still works).
"""

from __future__ import annotations

from .path import plan_path
from .raycast import cast_rays, raycast_distances
from .sensors import LASER_PRESETS, LaserSpec
from .simulate import SimulatedLog, simulate
from .world import PROCEDURAL_WORLDS, World, load_world

__all__ = ["World", "load_world", "PROCEDURAL_WORLDS", "LaserSpec", "LASER_PRESETS", "cast_rays",
           "raycast_distances", "plan_path", "SimulatedLog", "simulate"]
