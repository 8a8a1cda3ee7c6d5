"""Deskewing slow lasers on simulated tours with ground truth: read first (the default), not at all, trusted.

A rotating laser takes its beams one after the other; a robot turning meanwhile draws a skewed scan, and
scan matching comes short of (or, for a clockwise mirror, past) every turn (docs/ODOMETRY.md, "A scan
taken while turning"). This benchmark simulates tours of the ``rooms`` and ``obstacles`` worlds with two
slow lasers — a Hokuyo URG-04LX, whose log lists its beams in the order taken, and an RPLIDAR A2, which
turns clockwise while its log lists the beams by increasing angle, as the rplidar_ros and ydlidar drivers
publish — and runs ``slam run LOG --eval`` three ways on each: the default (the beam times' order read
from the log's first scans, then deskewed), ``odometry.deskew: false``, and ``odometry.beam_time_order:
listed`` (the log's times trusted). One JSON: per log and setting the APE RMSE of the SLAM estimate and
of the front end alone, what the check read and from how many scans; sums per laser and setting.

    .venv/bin/python benchmarks/deskew.py [--seeds 1 2 3] [--worlds rooms obstacles] [--dir DIR] [--out FILE]

Every command is the CLI's; a tour of ~1,500–2,000 scans runs in ~20–30 s on two cores, the whole
benchmark (36 runs) in ~15 min.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from cli_runs import run_and_report, slam  # noqa: E402

SENSORS = ("hokuyo_urg04lx", "rplidar_a2")
SETTINGS = {"read_first": None, "not_deskewed": "odometry:\n  deskew: false\n",
            "trusted": "odometry:\n  beam_time_order: listed\n"}


def tour(world: str, sensor: str, seed: int, setting: str, folder: Path) -> dict:
    """Simulate the tour (unless its log is in *folder*), run SLAM on it with *setting*, read the result."""
    log = folder / f"{world}_{sensor}_{seed}.mcap"
    if not log.exists():
        slam("simulate", world, "--sensor", sensor, "--seed", str(seed), "--out", str(log))
    out = folder / f"run_{world}_{sensor}_{seed}_{setting}"
    args = ["run", str(log), "--eval", "--out", str(out)]
    if SETTINGS[setting] is not None:
        cfg = folder / f"{setting}.yaml"
        cfg.write_text(SETTINGS[setting])
        args += ["--config", str(cfg)]
    slam(*args)
    metrics = json.loads((out / "metrics.json").read_text())
    summary = json.loads((out / "summary.json").read_text())
    stats = summary["odometry_stats"]
    return {"world": world, "sensor": sensor, "seed": seed, "setting": setting, "scans": summary["scans"],
            "ape_rmse_m": metrics["ape_trans_m"]["estimate"]["rmse"],
            "front_end_ape_rmse_m": metrics["ape_trans_m"]["odometry"]["rmse"],
            "closures": summary["loop_closures"], "verdict": summary["self_check"]["verdict"],
            "beam_times": stats.get("beam_times"), "beam_time_scans_read": stats.get("beam_time_scans_read")}


def summarise(rows: list[dict]) -> dict:
    """Per laser and setting: the summed APE of the estimate and of the front end, the runs read right."""
    out: dict = {}
    for sensor in SENSORS:
        for setting in SETTINGS:
            sel = [r for r in rows if r["sensor"] == sensor and r["setting"] == setting]
            if sel:
                out[f"{sensor}/{setting}"] = {
                    "runs": len(sel), "sum_ape_rmse_m": sum(r["ape_rmse_m"] for r in sel),
                    "sum_front_end_ape_rmse_m": sum(r["front_end_ape_rmse_m"] for r in sel),
                    "suspect": sum(r["verdict"] == "suspect" for r in sel)}
    right = {"hokuyo_urg04lx": "listed", "rplidar_a2": "reversed"}
    read = [r for r in rows if r["setting"] == "read_first"]
    out["read_right"] = f"{sum(r['beam_times'] == right[r['sensor']] for r in read)} of {len(read)}"
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--worlds", nargs="+", default=["rooms", "obstacles"])
    ap.add_argument("--dir", type=Path, default=None, help="keep the logs and runs here (reused logs are not simulated again)")
    ap.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    args = ap.parse_args()
    run_and_report(args.dir, args.out,
                   lambda folder: [tour(world, sensor, seed, setting, folder) for seed in args.seeds
                                   for world in args.worlds for sensor in SENSORS for setting in SETTINGS],
                   summarise, "runs")


if __name__ == "__main__":
    main()
