"""Solver cross-validation: our chordal Gauss-Newton and GTSAM Levenberg-Marquardt on the same
pose graph from the same chordal initialisation, against the published SE-Sync optimum.

Usage:  python examples/solver_crossvalidation.py [GRAPH.g2o]
Default: ../shared/data/pose_graphs/sesync/intel.g2o (SE-Sync f* = 52.35, Rosen et al. 2019, Table 1).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

DEFAULT = Path(__file__).resolve().parents[2] / "shared" / "data" / "pose_graphs" / "sesync" / "intel.g2o"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("graph", nargs="?", default=DEFAULT, type=Path)
    args = ap.parse_args()

    from slam.backends.chordal import solve_chordal
    from slam.backends.crosscheck import crosscheck
    from slam.backends.gtsam_backend import optimize
    from slam.graph.costs import sesync_objective
    from slam.graph.g2o import read_g2o
    from slam.graph.init import chordal_initialisation

    # 1. Read the graph (g2o: VERTEX_SE2/EDGE_SE2 or VERTEX_SE3:QUAT/EDGE_SE3:QUAT).
    graph = read_g2o(args.graph)
    print(f"1. {args.graph.name}: {graph.num_nodes} poses, {graph.num_edges} edges, {graph.dim}D")

    # 2. Chordal initialisation (Carlone et al., ICRA 2015): rotations first, then translations.
    init = chordal_initialisation(graph)
    print(f"2. chordal initialisation: SE-Sync objective {sesync_objective(graph, init):.4f}")

    # 3. Both solvers from the same start.
    ours = solve_chordal(graph, init)
    ref = optimize(graph, init, method="lm")
    print(f"3. chordal GN: f = {sesync_objective(graph, ours.poses):.4f} in {ours.time_s:.3f} s; "
          f"GTSAM LM: f = {sesync_objective(graph, ref.poses):.4f} in {ref.time_s:.3f} s")

    # 4. How far apart are the two solutions (after removing the gauge)?
    report = crosscheck(graph, ours.poses, ref.poses, ("chordal", "gtsam_lm"))
    print("4.", json.dumps({k: report[k] for k in ("bbox_diagonal_m", "max_position_diff_percent_of_diagonal")}))


if __name__ == "__main__":
    main()
