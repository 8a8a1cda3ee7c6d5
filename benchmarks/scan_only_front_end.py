"""The scan-only front end on the eight GMapping-corrected logs, with and without the free-space test of its
widened searches, side by side: steps off GMapping's.

The GMapping-corrected logs (``../shared/data/slam2d_devset/gmapping-corrected/``) keep only the scans
GMapping processed, 0.5–3 m apart, and no raw odometry, so their front end places each scan by a correlative
search on the local map, widened to every heading when its best scores poorly (``registration/unguided.py``).
Since 2026-11-28 a widened candidate that contradicts the local map's free space is passed over
(``odometry.icp_2d.unguided_max_contradiction``, Olson 2009 §III-B). This runs that front end (the default
configuration without wheels, as ``examples/devset.yaml`` runs these logs) twice on each log, with the test
and without it (``unguided_max_contradiction`` None), and counts the steps between consecutive scans that
are off GMapping's by more than 0.3 m or 3° (gross: 0.5 m or 5°). GMapping's poses are a weak reference (in
long corridors they follow the robot's odometry); the closures against a wheel run of the same scans are
``benchmarks/scan_only_closures.py``. It prints one JSON summary.

    .venv/bin/python benchmarks/scan_only_front_end.py [--out FILE] [--data ../shared/data]

~6 min on two cores. Needs ``../shared/data`` (licences: its SOURCE.md).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from cli_runs import REPO  # noqa: E402

from core import geometry as G  # noqa: E402
from slam.cli.eval_io import check_json, save_json  # noqa: E402
from slam.logs import open_log  # noqa: E402
from slam.pipeline.config import SlamConfig  # noqa: E402
from slam.pipeline.odometry_source import make_odometry  # noqa: E402

LOGS = ("acapulco", "belgioioso", "csail", "fhw", "freiburg-101", "freiburg-campus", "intel", "orebro")
WRONG, GROSS = (0.3, 3.0), (0.5, 5.0)  # m, degrees


def config(test: bool) -> SlamConfig:
    """The default configuration without wheels; *test* False leaves out the free-space test."""
    data = SlamConfig().model_dump()
    data["odometry"] |= {"use_wheel_odometry": False, "wheel_edges": False}
    if not test:
        data["odometry"]["icp_2d"]["unguided_max_contradiction"] = None
    return SlamConfig.model_validate(data)


def front_end(frames: list, cfg: SlamConfig) -> dict:
    """Steps of the front end over *frames* against GMapping's (the frames' odometry fields)."""
    t0 = time.perf_counter()
    odometry = make_odometry(cfg, True)
    poses = np.array([odometry.update(f).world_T_sensor for f in frames])
    seconds = time.perf_counter() - t0
    ref = np.array([f.odom for f in frames])
    e = G.relative(G.relative(ref[:-1], ref[1:]), G.relative(poses[:-1], poses[1:]))
    off_m = np.linalg.norm(e[:, :2, 3], axis=1)
    off_deg = np.degrees(np.abs(np.arctan2(e[:, 1, 0], e[:, 0, 0])))
    return {"wrong_steps": int(np.sum((off_m > WRONG[0]) | (off_deg > WRONG[1]))),
            "gross_steps": int(np.sum((off_m > GROSS[0]) | (off_deg > GROSS[1]))),
            "widened_searches": odometry.unguided_escalations, "best_passed_over": odometry.unguided_contradicted,
            "seconds": round(seconds, 2)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data", help="the shared data folder")
    ap.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    args = ap.parse_args()
    check_json(args.out)
    t0 = time.perf_counter()
    rows = []
    for name in LOGS:
        path = args.data / "slam2d_devset" / "gmapping-corrected" / f"{name}-corrected.log.gz"
        frames = list(open_log(path).frames())
        rows.append({"log": name, "steps": len(frames) - 1, "with_test": front_end(frames, config(True)),
                     "without_test": front_end(frames, config(False))})
    summary = {side: {k: sum(r[side][k] for r in rows) for k in ("wrong_steps", "gross_steps")}
               for side in ("with_test", "without_test")}
    result = {"summary": summary, "logs": rows, "runtime_s": time.perf_counter() - t0}
    save_json(args.out, result)
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
