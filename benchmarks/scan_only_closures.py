"""Closures of a scan-only run checked against a run of the same scans with wheels: the precision the final
solution cannot hide.

The development set's precision column counts the closures the final solution gave up (Hess et al. 2016's
criterion on real data: violated by more than 0.2 m or 1° after optimisation). A wrong closure that the
solution agrees with is not counted. The GMapping-corrected intel and csail logs keep a subset of the
Kümmerle Intel and MIT CSAIL scans, and ``slam2d_devset/gmapping-reference/`` names each kept scan's index
in the original log (identical ranges). So this benchmark runs, with the default configuration:

- ``slam run`` on the original log, with its wheels; its relation error says how good it is (1–3 cm);
- ``slam run`` on the GMapping-corrected log, scan-only, as ``examples/devset.yaml`` does (its odometry fields
  are GMapping's corrected poses, not raw odometry).

Every closure the scan-only run kept (``graph.g2o``; the pruned ones are not in it, and the table counts
them as wrong) is then scored against the relative pose of the same two scans in the wheel run, with the
same 0.2 m / 1° criterion. The benchmark also counts the scan-only run's
steps between consecutive scans that are off by more than 0.3 m or 3°, for its front end alone
(``odometry.tum``) and for the final trajectory. It prints one JSON summary.

    .venv/bin/python benchmarks/scan_only_closures.py [--dir DIR] [--out FILE] [--data ../shared/data]

Four ``slam run`` in a row, ~4 min on two cores. Needs ``../shared/data`` (licences: its SOURCE.md).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from cli_runs import REPO, run_and_report, slam  # noqa: E402

from core import geometry as G  # noqa: E402
from evaluation.loops import loop_edges_from_graph, score_loops  # noqa: E402
from slam.graph.g2o import read_g2o  # noqa: E402

PAIRS = (  # (name, original log, GMapping-corrected log, reference file)
    ("intel", "slam2d_kummerle_benchmark/intel.clf.bz2", "slam2d_devset/gmapping-corrected/intel-corrected.log.gz",
     "slam2d_devset/gmapping-reference/intel_gfs_reference.txt"),
    ("csail", "slam2d_kummerle_benchmark/mit-csail.clf.bz2", "slam2d_devset/gmapping-corrected/csail-corrected.log.gz",
     "slam2d_devset/gmapping-reference/mit-csail_gfs_reference.txt"),
)
SCAN_ONLY = "odometry:\n  use_wheel_odometry: false\n  wheel_edges: false\n"
STEP_TOL = (0.3, 3.0)  # m, degrees: a step of the front end gone wrong (docs/LOOP_CLOSURE.md)


def tum_rows(path: Path) -> np.ndarray:
    """``(N, 4, 4)`` planar poses of a TUM file in the order written (scan order: some logs' stamps are
    rounded or run backwards, so they must not be sorted)."""
    a = np.loadtxt(path, comments="#", ndmin=2)
    yaw = 2.0 * np.arctan2(a[:, 6], a[:, 7])
    return np.array([G.xytheta_to_matrix(x, y, t) for x, y, t in zip(a[:, 1], a[:, 2], yaw)])


def node_scans(node_poses: np.ndarray, scan_poses: np.ndarray) -> np.ndarray:
    """The scan index of every graph node: a keyframe's scan carries the node's optimised pose exactly."""
    xy = scan_poses[:, :2, 3]
    idx = np.array([int(np.argmin(np.linalg.norm(xy - p[:2, 3], axis=1))) for p in node_poses])
    off = np.linalg.norm(xy[idx] - node_poses[:, :2, 3], axis=1)
    if np.any(off > 1e-6):
        sys.exit(f"{int(np.sum(off > 1e-6))} graph nodes match no scan of trajectory.tum")
    return idx


def wrong_steps(poses: np.ndarray, reference: np.ndarray) -> int:
    """Steps between consecutive scans off the reference's by more than STEP_TOL."""
    e = G.relative(G.relative(reference[:-1], reference[1:]), G.relative(poses[:-1], poses[1:]))
    return int(np.sum((np.linalg.norm(e[:, :2, 3], axis=1) > STEP_TOL[0])
                      | (np.degrees(np.abs(np.arctan2(e[:, 1, 0], e[:, 0, 0]))) > STEP_TOL[1])))


def pair(name: str, original: Path, corrected: Path, reference: Path, folder: Path, config: Path) -> dict:
    """Both runs of one log (unless *folder* holds them) and the scores of the scan-only one; *config* the
    scan-only configuration file."""
    wheel_run, scan_run = folder / f"{name}_wheels", folder / f"{name}_scan_only"
    if not (wheel_run / "summary.json").exists():
        slam("run", str(original), "--out", str(wheel_run), "--quiet", "--map", "none")
    if not (scan_run / "summary.json").exists():
        slam("run", str(corrected), "--out", str(scan_run), "--config", str(config), "--quiet", "--map", "none")
    kept = np.loadtxt(reference, comments="#", ndmin=2)[:, 0].astype(int)  # original scan index of each kept scan
    truth = tum_rows(wheel_run / "trajectory.tum")[kept]  # the wheel run's pose of every scan the scan-only log has
    final, front = tum_rows(scan_run / "trajectory.tum"), tum_rows(scan_run / "odometry.tum")
    if len(final) != len(truth):
        sys.exit(f"{corrected.name}: {len(final)} scans, but {reference.name} lists {len(truth)}")
    graph = read_g2o(scan_run / "graph.g2o")
    loops = loop_edges_from_graph(graph)
    score = score_loops(loops, truth[node_scans(graph.poses, final)])
    summary = json.loads((scan_run / "summary.json").read_text())
    pruned = int(summary["loop_stats"].get("pruned", 0))
    wrong = score.n_loops - score.n_correct
    return {"log": name, "closures_kept": score.n_loops, "closures_pruned": pruned, "wrong_kept": wrong,
            "precision_kept_against_wheel_run": score.precision,
            "precision_in_table": (1.0 - pruned / (score.n_loops + pruned)) if score.n_loops + pruned else None,
            "gross_wrong_5m_or_45deg": int(np.sum((score.trans_violation > 5.0) | (score.rot_violation_deg > 45.0))),
            "front_end_wrong_steps": wrong_steps(front, truth), "final_wrong_steps": wrong_steps(final, truth),
            "self_check": summary["self_check"]["verdict"], "scans": len(truth)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data", help="the shared data folder")
    ap.add_argument("--dir", type=Path, default=None, help="keep the runs here (runs already there are reused)")
    ap.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    args = ap.parse_args()

    def collect(folder: Path) -> list[dict]:
        config = folder / "scan_only.yaml"
        config.write_text(SCAN_ONLY)
        return [pair(n, args.data / o, args.data / c, args.data / r, folder, config) for n, o, c, r in PAIRS]

    def summarise(rows: list[dict]) -> dict:
        return {r["log"]: {"precision_kept_against_wheel_run": r["precision_kept_against_wheel_run"],
                           "precision_in_table": r["precision_in_table"]} for r in rows}

    run_and_report(args.dir, args.out, collect, summarise, "logs")


if __name__ == "__main__":
    main()
