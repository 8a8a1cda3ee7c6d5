"""Loop closure on simulated rings of corridors: the held-out log's shape, with ground truth, any machine.

The development set has no log shaped like the one that started the loop-closure rework (a square ring of
corridors crossed by two central ones, a 180° laser, returns only after long loops). The simulator draws
such a floor (``slam simulate ring``, docs/SIMULATION.md), a new one per seed, with the true pose of every
scan. This benchmark simulates each seed (or reuses the logs already in ``--dir``), runs ``slam run LOG
--eval`` on it with the default configuration, scores the closures against the truth (``slam eval loops
--gt``: a closure is wrong when the true poses violate it by more than 0.2 m or 1°, Hess et al. 2016; gross
when by more than the 1 m revisit radius or 5°, i.e. it measured another place) and prints one JSON
summary: per ring the APE of the estimate and of the front end alone (SE(2)-aligned, every scan), the
closures, the wrong and the gross ones and the spread of their heading errors, recall of the true
revisits, the self-check's verdict; and the sums over the rings, the figures a change to loop closure
must not make worse.

    .venv/bin/python benchmarks/rings.py [--seeds 1 2 3] [--sensor sick_lms] [--dir DIR] [--out FILE]

Every command is the CLI's, one after another (each ``slam run`` uses its own stage processes); a ring of
~7,500 scans takes ~30 s on two cores.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from cli_runs import run_and_report, slam  # noqa: E402


def ring(seed: int, sensor: str, folder: Path) -> dict:
    """Simulate ring *seed* (unless its log is in *folder*), run SLAM on it, score it against the truth."""
    log = folder / f"ring_{sensor}_{seed}.mcap"
    if not log.exists():
        slam("simulate", "ring", "--sensor", sensor, "--seed", str(seed), "--out", str(log))
    out = folder / f"run_{sensor}_{seed}"
    t0 = time.perf_counter()
    slam("run", str(log), "--eval", "--out", str(out))
    wall = time.perf_counter() - t0
    scored = folder / f"loops_{sensor}_{seed}.json"
    slam("eval", "loops", str(out / "graph.g2o"), "--gt", str(out / "ground_truth.tum"),
          "--node-stamps", str(out / "node_stamps.txt"), "--json", str(scored))
    metrics = json.loads((out / "metrics.json").read_text())
    summary = json.loads((out / "summary.json").read_text())
    truth = json.loads(scored.read_text())["truth"]
    check = summary["self_check"]
    return {"seed": seed, "sensor": sensor, "scans": summary["scans"], "keyframes": summary["keyframes"],
            "ape_rmse_m": metrics["ape_trans_m"]["estimate"]["rmse"],
            "front_end_ape_rmse_m": metrics["ape_trans_m"]["odometry"]["rmse"],
            "closures": truth["n_loops"], "wrong_closures": truth["n_loops"] - truth["n_true_positive"],
            "gross_wrong_closures": truth["n_gross"], "closure_rot_error_deg": truth["rot_error_deg"],
            "revisit_recall": truth["recall"], "verdict": check["verdict"],
            "contradicting": check["keyframes_contradicting"], "checked": check["keyframes_checked"],
            "wall_s": wall}


def summarise(rows: list[dict]) -> dict:
    """The sums and counts over the rings that a change must not make worse."""
    return {"rings": len(rows),
            "sum_ape_rmse_m": sum(r["ape_rmse_m"] for r in rows),
            "max_ape_rmse_m": max(r["ape_rmse_m"] for r in rows),
            "sum_wrong_closures": sum(r["wrong_closures"] for r in rows),
            "sum_gross_wrong_closures": sum(r["gross_wrong_closures"] for r in rows),
            "sum_closures": sum(r["closures"] for r in rows),
            "suspect": sum(r["verdict"] == "suspect" for r in rows),
            "rings_over_0_5_m": sum(r["ape_rmse_m"] > 0.5 for r in rows)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=list(range(1, 15)))
    ap.add_argument("--sensor", default="sick_lms", help="laser preset of `slam simulate` (the held-out log's: sick_lms)")
    ap.add_argument("--dir", type=Path, default=None, help="keep the logs and runs here (reused logs are not simulated again)")
    ap.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    args = ap.parse_args()
    run_and_report(args.dir, args.out, lambda folder: [ring(seed, args.sensor, folder) for seed in args.seeds],
                   summarise, "rings")


if __name__ == "__main__":
    main()
