"""Loop-closure precision and recall on a simulated log with ground truth.

Usage:  python examples/loop_closure_experiment.py [--world corridor] [--scans 1500]
"""

from __future__ import annotations

import argparse


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--world", default="corridor", help="rooms, corridor, obstacles or a map_server yaml")
    ap.add_argument("--scans", type=int, default=1500)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()

    import numpy as np

    from evaluation.loops import loop_edges_from_graph, score_against_truth, score_loops
    from evaluation.sim import LASER_PRESETS, load_world, simulate
    from slam.pipeline.config import SlamConfig
    from slam.pipeline.run import run_slam

    # 1. Simulate a log with ground truth: the robot tours the world and comes back (loops exist).
    sim = simulate(load_world(args.world), n_scans=args.scans, spec=LASER_PRESETS["hokuyo_utm30"], seed=args.seed)
    print(f"1. simulated {len(sim.stamps)} scans in '{args.world}'")

    # 2. Run the pipeline without mapping (only the trajectory and the graph matter here).
    result = run_slam(sim.frames(), SlamConfig.model_validate({"mapping": {"enabled": False}}))
    graph = result.backend.graph
    print(f"2. {graph.num_nodes} keyframes, {len(result.loops)} closures accepted, stats {result.loop_stats}")

    # 3. Score the accepted closures against the true keyframe poses (precision, recall of revisits).
    gt_kf = sim.ground_truth[[kf.scan_index for kf in result.keyframes]]
    truth = score_against_truth(loop_edges_from_graph(graph), gt_kf, revisit_radius=1.0,
                                min_separation=graph.num_nodes // 20 or 1)
    print(f"3. ground truth: precision {truth.precision:.3f}, recall {truth.recall:.3f} "
          f"({truth.n_revisit_nodes_found}/{truth.n_revisit_nodes} revisit keyframes closed)")

    # 4. Cartographer's self-consistency criterion on the final solution (no ground truth needed).
    self_score = score_loops(loop_edges_from_graph(graph), result.keyframe_poses)
    print(f"4. self-consistency precision (20 cm / 1°): {self_score.precision:.3f}")

    # 5. Trajectory error of the SLAM solution vs the wheel odometry.
    A = sim.ground_truth[0] @ np.linalg.inv(result.poses[0])
    err = np.linalg.norm((A @ result.poses)[:, :2, 3] - sim.ground_truth[:, :2, 3], axis=1)
    print(f"5. position error RMS {np.sqrt((err**2).mean()):.3f} m, max {err.max():.3f} m")


if __name__ == "__main__":
    main()
