"""Loop-closure scoring: self-consistency precision (Cartographer's criterion) and, with ground
truth, precision and recall against the true revisits.

* Self-scored precision — W. Hess et al., "Real-Time Loop Closure in 2D LIDAR SLAM", ICRA 2016,
  §VI-B / Table IV: a loop closure (i, j, Z) is counted correct when the final solution violates
  it by at most 20 cm and 1°, i.e. the error ``e = Z⁻¹ (x_i⁻¹ x_j)`` has ‖trans(e)‖ ≤ 0.2 m and
  |angle(e)| ≤ 1°.
* Against ground truth (simulated logs): a closure is a true positive when its measurement agrees
  with the true relative pose ``g_i⁻¹ g_j`` within the same tolerances. A node *j* is a *true
  revisit* when some earlier node *i* with ``j − i ≥ min_separation`` lies within
  ``revisit_radius`` of it (true positions); recall is the fraction of true-revisit nodes that are
  the later end of at least one true-positive closure.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from core import geometry as geo

Array = NDArray[np.float64]

__all__ = ["LoopEdges", "LoopScore", "TruthScore", "loop_edges_from_graph", "loop_edges_from_closures", "constraint_violations", "score_loops",
           "true_revisits", "score_against_truth"]

TRANS_TOL = 0.20  # m, Hess et al. 2016
ROT_TOL_DEG = 1.0  # deg, Hess et al. 2016
GROSS_ROT_DEG = 5.0  # deg: a closure turned this far measured another place (or a mirror of it), not this one imprecisely


@dataclass(frozen=True)
class LoopEdges:
    """Loop-closure constraints: node indices ``ii, jj (M,)`` (into the pose array) and ``Z (M, 4, 4) = i_T_j``."""

    ii: NDArray[np.int64]
    jj: NDArray[np.int64]
    measurements: Array

    def __len__(self) -> int:
        return int(self.ii.shape[0])


@dataclass
class LoopScore:
    """Self-scored precision of the loop closures under the final poses."""

    n_loops: int
    n_correct: int
    precision: float
    trans_violation: Array  # (M,) m
    rot_violation_deg: Array  # (M,) deg
    correct: NDArray[np.bool_]  # (M,)
    trans_tol: float = TRANS_TOL
    rot_tol_deg: float = ROT_TOL_DEG

    def to_dict(self) -> dict[str, float | int]:
        v = self.trans_violation
        return {
            "n_loops": self.n_loops, "n_correct": self.n_correct, "precision": self.precision,
            "trans_tol_m": self.trans_tol, "rot_tol_deg": self.rot_tol_deg,
            "median_trans_violation_m": float(np.median(v)) if v.size else float("nan"),
            "median_rot_violation_deg": float(np.median(self.rot_violation_deg)) if v.size else float("nan"),
        }


@dataclass
class TruthScore:
    """Precision and recall of the loop closures against ground truth."""

    n_loops: int
    n_true_positive: int
    precision: float
    n_revisit_nodes: int
    n_revisit_nodes_found: int
    recall: float
    true_positive: NDArray[np.bool_] = field(default_factory=lambda: np.zeros(0, bool))  # (M,)
    revisit_nodes: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    settings: dict[str, float] = field(default_factory=dict)
    trans_error_m: Array = field(default_factory=lambda: np.zeros(0))  # (M,) each closure against the truth
    rot_error_deg: Array = field(default_factory=lambda: np.zeros(0))

    @property
    def gross(self) -> NDArray[np.bool_]:
        """Closures that measured another place, not this one imprecisely: off the truth by more than the
        revisit radius or ``GROSS_ROT_DEG`` (a closure 1.2° off fails the 1° criterion; one 3 m off is an alias)."""
        return (self.trans_error_m > self.settings.get("revisit_radius_m", np.inf)) | (self.rot_error_deg > GROSS_ROT_DEG)

    def to_dict(self) -> dict[str, object]:
        def spread(v: Array) -> dict[str, float]:
            return {k: float(np.percentile(v, q)) for k, q in (("p50", 50), ("p90", 90), ("max", 100))} if len(v) else {}

        return {
            "n_loops": self.n_loops, "n_true_positive": self.n_true_positive, "precision": self.precision,
            "n_gross": int(self.gross.sum()),
            "n_revisit_nodes": self.n_revisit_nodes, "n_revisit_nodes_found": self.n_revisit_nodes_found,
            "recall": self.recall, "trans_error_m": spread(self.trans_error_m),
            "rot_error_deg": spread(self.rot_error_deg), **self.settings,
        }


def loop_edges_from_graph(graph) -> LoopEdges:  # graph: slam.graph.PoseGraph
    """The edges of kind ``loop`` of a :class:`slam.graph.PoseGraph` (indices into its node order)."""
    a = graph.edge_arrays()
    m = np.array(graph.edge_kinds, dtype=object) == "loop"
    return LoopEdges(a.ii[m].copy(), a.jj[m].copy(), a.measurements[m].copy())


def loop_edges_from_closures(closures) -> LoopEdges:  # closures: slam.loops.types.LoopClosure (i, j, measurement)
    """Closures with keyframe ids ``i``, ``j`` (= node indices) and measurements ``i_T_j`` as :class:`LoopEdges`."""
    return LoopEdges(np.array([lc.i for lc in closures], np.int64), np.array([lc.j for lc in closures], np.int64),
                     np.array([lc.measurement for lc in closures], float).reshape(-1, 4, 4))


def constraint_violations(loops: LoopEdges, poses: Array) -> tuple[Array, Array]:
    """‖trans(e)‖ [m] and |angle(e)| [deg] of ``e = Z⁻¹ (x_i⁻¹ x_j)`` for every loop edge."""
    P = np.asarray(poses, dtype=np.float64)
    if len(loops) == 0:
        return np.zeros(0), np.zeros(0)
    E = geo.relative(loops.measurements, geo.relative(P[loops.ii], P[loops.jj]))
    return np.linalg.norm(E[:, :3, 3], axis=1), np.degrees(np.linalg.norm(geo.so3_log(E[:, :3, :3]), axis=1))


def score_loops(loops: LoopEdges, poses: Array, trans_tol: float = TRANS_TOL, rot_tol_deg: float = ROT_TOL_DEG) -> LoopScore:
    """Hess et al. 2016 precision: fraction of loop closures violated by ≤ *trans_tol* m and ≤ *rot_tol_deg*."""
    tv, rv = constraint_violations(loops, poses)
    ok = (tv <= trans_tol) & (rv <= rot_tol_deg)
    n = len(loops)
    return LoopScore(n, int(ok.sum()), float(ok.mean()) if n else float("nan"), tv, rv, ok, trans_tol, rot_tol_deg)


def true_revisits(gt_poses: Array, revisit_radius: float, min_separation: int) -> NDArray[np.int64]:
    """Node indices j with an earlier node i (j − i ≥ *min_separation*) within *revisit_radius* m (true positions)."""
    p = np.asarray(gt_poses, dtype=np.float64)[:, :3, 3]
    pairs = cKDTree(p).query_pairs(revisit_radius, output_type="ndarray")
    if len(pairs) == 0:
        return np.zeros(0, np.int64)
    lo, hi = pairs.min(1), pairs.max(1)
    return np.unique(hi[hi - lo >= min_separation]).astype(np.int64)


def score_against_truth(
    loops: LoopEdges,
    gt_poses: Array,
    revisit_radius: float = 1.0,
    min_separation: int = 30,
    trans_tol: float = TRANS_TOL,
    rot_tol_deg: float = ROT_TOL_DEG,
) -> TruthScore:
    """Precision (measurement agrees with the true relative pose) and recall over true-revisit nodes.

    Args:
        loops: loop-closure edges, indices into *gt_poses*.
        gt_poses: ``(N, 4, 4)`` true ``world_T_base`` poses of the graph's nodes (metres).
        revisit_radius: true distance [m] below which two nodes see the same place.
        min_separation: smallest index gap for a pair to count as a revisit (not a neighbour).
    """
    tv, rv = constraint_violations(loops, gt_poses)
    tp = (tv <= trans_tol) & (rv <= rot_tol_deg)
    n = len(loops)
    revisit = true_revisits(gt_poses, revisit_radius, min_separation)
    later = np.maximum(loops.ii, loops.jj)[tp] if n else np.zeros(0, np.int64)
    found = np.intersect1d(revisit, later)
    return TruthScore(
        n, int(tp.sum()), float(tp.mean()) if n else float("nan"), int(len(revisit)), int(len(found)),
        float(len(found) / len(revisit)) if len(revisit) else float("nan"), tp, revisit,
        {"revisit_radius_m": revisit_radius, "min_separation": min_separation, "trans_tol_m": trans_tol,
         "rot_tol_deg": rot_tol_deg}, tv, rv,
    )
