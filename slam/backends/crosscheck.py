"""Solver cross-check: one pose graph, two solutions (e.g. GTSAM LM and our chordal Gauss-Newton).

For each solution both objectives are evaluated with :mod:`slam.graph.costs` — the SE-Sync
objective (Rosen et al., IJRR 2019, eq. 12) and GTSAM's ``NonlinearFactorGraph.error``
(½ Σ eᵀΩe on the log-map; χ² = twice that) — and the poses are compared node by node, raw and
after removing the gauge freedom by an SE(d) Umeyama fit of B's positions onto A's (Umeyama 1991;
the rotations are carried along). Position differences in metres, rotation differences in degrees.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from core import geometry as geo
from core.errors import GeometryError, GraphFormatError

from evaluation.trajectory import umeyama
from slam.graph.costs import gtsam_error, sesync_objective
from slam.trajectory_io import read_trajectory

Array = NDArray[np.float64]

__all__ = ["pose_differences", "crosscheck", "load_solution"]


def pose_differences(A: Array, B: Array) -> dict[str, float]:
    """Position [m] and rotation [deg] differences of two ``(N, 4, 4)`` pose sets: max and RMS."""
    dp = np.linalg.norm(A[:, :3, 3] - B[:, :3, 3], axis=1)
    dr = np.degrees(np.linalg.norm(geo.so3_log(geo.relative(A, B)[:, :3, :3]), axis=1))
    return {
        "max_position_diff_m": float(dp.max()),
        "rms_position_diff_m": float(np.sqrt(np.mean(dp**2))),
        "max_rotation_diff_deg": float(dr.max()),
        "rms_rotation_diff_deg": float(np.sqrt(np.mean(dr**2))),
    }


def _objectives(graph, P: Array) -> dict[str, float | str]:
    out: dict[str, float | str] = {"sesync_objective": sesync_objective(graph, P)}
    try:
        g = gtsam_error(graph, P)
        out["gtsam_error"] = g
        out["chi2"] = 2.0 * g
    except ImportError as exc:  # the GTSAM back end module is optional at run time
        out["gtsam_error"] = f"unavailable: {exc}"
    return out


def crosscheck(graph, poses_a: Array, poses_b: Array, names: tuple[str, str] = ("a", "b")) -> dict[str, Any]:
    """Objectives of both solutions on *graph* (a :class:`slam.graph.PoseGraph`) and their pose differences.

    Args:
        poses_a, poses_b: ``(N, 4, 4)`` solutions in the graph's node order.
    Returns:
        A JSON-ready dict: ``{names[0]: {...objectives}, names[1]: {...}, "raw": {...}, "aligned": {...},
        "bbox_diagonal_m", "max_position_diff_percent_of_diagonal", "objective_rel_diff"}``.
    """
    A = np.asarray(poses_a, dtype=np.float64)
    B = np.asarray(poses_b, dtype=np.float64)
    n = graph.num_nodes
    if A.shape != (n, 4, 4) or B.shape != (n, 4, 4):
        raise GeometryError(f"solutions must have one pose per graph node ({n}), got {A.shape} and {B.shape}")
    d = graph.dim
    R, t, _ = umeyama(B[:, :d, 3], A[:, :d, 3])
    G = np.eye(4)
    G[:d, :d] = R
    G[:d, 3] = t
    B_al = G @ B
    pa = A[:, :3, 3]
    diag = float(np.linalg.norm(pa.max(0) - pa.min(0)))
    oa, ob = _objectives(graph, A), _objectives(graph, B)
    raw, aligned = pose_differences(A, B), pose_differences(A, B_al)
    fa, fb = float(oa["sesync_objective"]), float(ob["sesync_objective"])
    return {
        "graph": {"dim": d, "nodes": n, "edges": graph.num_edges},
        names[0]: oa,
        names[1]: ob,
        "objective_rel_diff": abs(fa - fb) / max(abs(fa), abs(fb), 1e-300),
        "raw": raw,
        "aligned": aligned,
        "gauge_transform": G.tolist(),
        "bbox_diagonal_m": diag,
        "max_position_diff_percent_of_diagonal": 100.0 * aligned["max_position_diff_m"] / diag if diag > 0 else float("nan"),
    }


def load_solution(path: str | os.PathLike[str], graph) -> Array:
    """Poses of a solution file in *graph*'s node order.

    A g2o file (vertices matched to the graph by id) or a TUM / KITTI file with one pose per node
    in node order (a TUM file's stamps give that order: its lines are read sorted by stamp).
    """
    p = Path(path)
    traj = read_trajectory(p)
    ids = graph.node_ids
    with open(p, encoding="utf-8") as fh:
        is_g2o = p.suffix.lower() == ".g2o" or any(line.startswith("VERTEX") for line in fh)
    if is_g2o:
        index = {int(s): k for k, s in enumerate(traj.stamps)}
        missing = [int(i) for i in ids if int(i) not in index]
        if missing:
            raise GraphFormatError(p, None, f"solution has no vertex {missing[0]} of the graph")
        return traj.poses[[index[int(i)] for i in ids]]
    if len(traj) != len(ids):
        raise GraphFormatError(p, None, f"solution has {len(traj)} poses, the graph {len(ids)} nodes")
    return traj.poses
