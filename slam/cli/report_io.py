"""The report of a run folder with the inputs only the ``slam`` package reads: a ground truth given as a
trajectory file or a robot log (:func:`slam.trajectory_io.read_trajectory`) and the run's ``graph.g2o``
(:func:`slam.graph.read_graph`); :func:`evaluation.report.write_report` computes the rest."""

from __future__ import annotations

import os
from pathlib import Path

from evaluation.report import Report, write_report
from slam.graph import read_graph
from slam.trajectory_io import read_trajectory

__all__ = ["write_run_report"]

PathLike = str | os.PathLike[str]


def write_run_report(result_dir: PathLike, gt: PathLike | None = None, relations: PathLike | None = None,
                     gt_map: PathLike | None = None, out_dir: PathLike | None = None,
                     result_label: str | None = None) -> Report:
    """:func:`evaluation.report.write_report` for *result_dir*, the ground truth read from *gt* (TUM, KITTI,
    g2o or a log's ground-truth poses) and the folder's pose graph when it has one."""
    g2o = Path(result_dir) / "graph.g2o"
    return write_report(result_dir, read_trajectory(gt) if gt is not None else None, relations, gt_map, out_dir,
                        result_label=result_label, graph=read_graph(g2o) if g2o.exists() else None)
