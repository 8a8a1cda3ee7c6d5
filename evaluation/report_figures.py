"""The figures of an evaluation report (:mod:`evaluation.report`): trajectories in the ground-truth frame and
over the map, the error along them, the map's variance and the stage timings, as PNG bytes."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from core.trajectory import Trajectory

Array = NDArray[np.float64]

__all__ = ["Figure", "trajectory_figures", "closing_figures"]


@dataclass
class Figure:
    """One report figure: title, PNG bytes and a one-line caption."""

    title: str
    png: bytes
    caption: str = ""


def trajectory_figures(trajs: dict[str, Trajectory], gt: Trajectory | None, aligned_paths: dict[str, Array],
                       ape_series: dict[str, tuple[Array, Array]], rel_series: dict[str, tuple[Array, Array]],
                       loops_xy: Array | None, mp: dict[str, Any] | None,
                       gt_bg: tuple[Array, float, Array] | None) -> list[Figure]:
    """The figures a report opens with: the trajectories (*aligned_paths* in the ground-truth frame, the run's
    own over its map *mp* with the loop edges *loops_xy*) and the error along them (APE, else the relations)."""
    from . import plots

    figs: list[Figure] = []
    if aligned_paths:
        if gt is not None:
            bg = gt_bg if gt_bg is not None else (None, None, None)
            figs.append(Figure(
                "Trajectories in the ground-truth frame",
                plots.trajectory_map_png(aligned_paths, *bg, None, "Trajectories aligned to the ground truth",
                                         bg_label="ground-truth occupancy"),
                "Estimated and odometry trajectories after SE(d) Umeyama alignment to the ground truth"
                + (", over the ground-truth map." if gt_bg is not None else "."),
            ))
        if mp is not None or gt is None:
            figs.append(Figure(
                "Trajectory over the map",
                plots.trajectory_map_png(
                    {k: v.positions for k, v in trajs.items()},
                    None if mp is None else np.asarray(mp["probability"], float),
                    None if mp is None else float(np.asarray(mp["resolution"]).reshape(-1)[0]),
                    None if mp is None else np.asarray(mp["origin"], float).reshape(-1),
                    loops_xy, "Trajectory over the occupancy map" if mp is not None else "Trajectory"),
                "Optimised trajectory, odometry and loop closures (green) in the map frame"
                + (", over the occupancy probability." if mp is not None else "."),
            ))
    if ape_series:
        figs.append(Figure("Error along the trajectory",
                           plots.error_along_png(ape_series, "APE translation [m]", "Absolute position error (SE(d)-aligned)"),
                           "Translational APE of each pose against the ground truth."))
    elif rel_series:
        figs.append(Figure("Relation error along the trajectory",
                           plots.error_along_png(rel_series, "relation translation error [m]", "Kümmerle relation error",
                                                 points=True),
                           "Translational error of each ground-truth relation, at the stamp of its second scan."))
    return figs


def closing_figures(mp: dict[str, Any] | None, timings_s: dict[str, float] | None) -> list[Figure]:
    """The figures a report closes with: the map's variance and the stage timings."""
    from . import plots

    out = []
    if mp is not None and "variance" in mp:
        out.append(Figure("Map variance", plots.map_png(np.asarray(mp["variance"], float),
                                                                float(np.asarray(mp["resolution"]).reshape(-1)[0]),
                                                                np.asarray(mp["origin"], float).reshape(-1),
                                                                "GP predictive variance (unitless)", "Map variance"),
                                  "Predictive variance of the Gaussian-process map (low = confident)."))
    if timings_s:
        out.append(Figure("Stage timings", plots.timings_png(timings_s), "Wall-clock time per pipeline stage."))
    return out
