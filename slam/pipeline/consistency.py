"""The front end's chains of a finished pose graph, and the run's own closures as their reference.

``slam eval nees`` tests the chains of odometry edges (each step's registration and wheel edges fused) against
ground-truth relations or, where a log has none, against the closures the run kept. Every 2D run reports the
latter in ``summary.json``: ``closure_nees``, a consistency table of its covariance as the edges state it, and
``chain_model``, that covariance split into the walk and jitter its long closures call for, with the table under it
(:mod:`evaluation.chain_model`; docs/LOOP_CLOSURE.md, "Against the run's own closures" and "A chain model
calibrated by the run's closures").
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from evaluation.chain_model import calibrate
from evaluation.nees import bin_by_length, closure_sample, fuse_steps
from slam.graph.posegraph import KINDS, PoseGraph

Array = NDArray[np.float64]

__all__ = ["graph_chain", "graph_closures", "closure_consistency"]


def graph_chain(graph: PoseGraph) -> tuple[Array, Array]:
    """:func:`evaluation.nees.fuse_steps` of the planar *graph*'s odometry edges (ValueError when a step has none)."""
    a = graph.edge_arrays()
    odo = np.flatnonzero(a.kinds == KINDS.index("odometry"))
    return fuse_steps(graph.num_nodes, [(int(a.ii[e]), int(a.jj[e]), a.measurements[e], np.linalg.inv(a.information[e]))
                                        for e in odo])


def graph_closures(graph: PoseGraph) -> list[tuple[int, int, Array, Array]]:
    """The *graph*'s loop edges as ``(i, j, i_T_j, covariance)`` (node indices)."""
    a = graph.edge_arrays()
    return [(int(a.ii[e]), int(a.jj[e]), a.measurements[e], np.linalg.inv(a.information[e]))
            for e in np.flatnonzero(a.kinds == KINDS.index("loop"))]


def closure_consistency(graph: PoseGraph, drift_rad_per_m: float) -> tuple[list[dict] | None, dict | None]:
    """NEES/dof of the chains against the closures per chain length (:class:`evaluation.nees.NeesBin` as dicts),
    under the edges as stated with the loop closer's heading rate *drift_rad_per_m*; and the chain model the long
    closures calibrate (:func:`evaluation.chain_model.calibrate`, with its own table under ``closure_nees``).
    (None, None) for a 3D graph, a graph without closures, or one whose chain has a step without an edge; the
    model is None with too few long closures."""
    if graph.dim != 2:
        return None, None
    closures = graph_closures(graph)
    if not closures:
        return None, None
    try:
        mu, cov = graph_chain(graph)
    except ValueError:
        return None, None
    as_stated = [b.as_dict() for b in bin_by_length(closure_sample(mu, cov, closures, drift_rad_per_m).rows())]
    sample = closure_sample(mu, cov, closures)  # the walk takes the heading rate's place
    model = calibrate(sample)
    if model is None:
        return as_stated, None
    return as_stated, model.as_dict() | {
        "closure_nees": [b.as_dict() for b in bin_by_length(sample.rows(model.walk, model.jitter))]}
