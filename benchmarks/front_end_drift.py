"""Front-end drift: the odometry alone against the relations, for two local maps side by side.

The held-out log that started the loop-closure work came back to its start with ~10° of heading drift; loop
closure has to find that return, but the drift itself comes from the front end. This benchmark runs the 2D
odometry alone (our scan-to-map ICP with the wheel guess, no keyframes, no loop closure, no graph) over each
log twice in one process — with the default local map (thirty scans spaced along the path: one joins when
the sensor moved 0.5 m or turned 0.2 rad since the last that did) and with the map of the last ten scans
(every scan joins it; the default before 2026-11-26) — and measures every scan pose against the Kümmerle et
al. 2009 relations, binned by the odometry path between the relation's two poses (a relation spans a
corridor or a whole loop):

* per bin: relations, median translation error (m), median and 95th percentile of the heading error (°);
* per log: CPU seconds of the odometry.

Prints one JSON object (``summary``: per log and map, the median heading error of the relations over
≥ 200 m of path; ``bins``: everything).

    .venv/bin/python benchmarks/front_end_drift.py [LOG:RELATIONS ...]

Without arguments: the bundled Intel and MIT CSAIL logs (``data/``).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from core.trajectory import Trajectory  # noqa: E402
from evaluation.relations import errors_by_path, read_relations  # noqa: E402
from registration.config import IcpOdometryConfig  # noqa: E402
from registration.odometry import IcpOdometry  # noqa: E402
from slam.logs import open_log  # noqa: E402
from slam.pipeline.config import PLANAR_ICP  # noqa: E402

#: the local map before 2026-11-26: every scan joined it, the last ten formed it (~0.5 m of path at walking pace)
LAST_TEN_SCANS = PLANAR_ICP.model_copy(update={"map_scans": 10, "unguided_map_scans": None, "map_step_m": 0.0,
                                               "map_step_rad": 0.1})
PATH_BINS_M = ((0.0, 2.0), (2.0, 10.0), (10.0, 50.0), (50.0, 200.0), (200.0, 800.0), (800.0, np.inf))
FAR_M = 200.0  # relations over at least this much odometry path make the summary


def odometry_alone(log: str, config: IcpOdometryConfig) -> tuple[Trajectory, float]:
    """Every scan's base pose from the odometry alone, and its CPU time (s)."""
    odo = IcpOdometry(config)
    t0 = time.process_time()
    for frame in open_log(log).frames():
        odo.update(frame)
    return Trajectory(odo.stamps(), odo.poses(base=True)), time.process_time() - t0


def drift(traj: Trajectory, relations_path: str) -> dict:
    """Relation errors of *traj*, binned by the odometry path between each relation's poses."""
    length, err_m, err_deg = errors_by_path(traj, read_relations(relations_path))
    bins = {}
    for lo, hi in PATH_BINS_M:
        m = (length >= lo) & (length < hi)
        if m.sum() >= 3:
            bins[f"{lo:g}-{hi:g} m"] = {"relations": int(m.sum()), "median_err_m": float(np.median(err_m[m])),
                                        "median_err_deg": float(np.median(err_deg[m])),
                                        "p95_err_deg": float(np.percentile(err_deg[m], 95))}
    far = length >= FAR_M
    return {"bins": bins, "far_relations": int(far.sum()),
            "far_median_err_deg": float(np.median(err_deg[far])) if far.any() else None,
            "far_median_err_m": float(np.median(err_m[far])) if far.any() else None}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="*", help="LOG:RELATIONS")
    args = ap.parse_args()
    pairs = args.runs or [f"{REPO}/data/intel.clf.bz2:{REPO}/data/intel.relations",
                          f"{REPO}/data/mit-csail.clf.bz2:{REPO}/data/mit-csail.relations"]
    maps = {"default": PLANAR_ICP, "last_ten_scans": LAST_TEN_SCANS}
    out: dict = {"maps": {k: {f: getattr(c, f) for f in ("map_scans", "unguided_map_scans", "map_step_m", "map_step_rad")} for k, c in maps.items()},
                 "summary": {}, "bins": {}}
    t0 = time.perf_counter()
    for pair in pairs:
        log, relations = pair.rsplit(":", 1)
        name = Path(log).name.split(".")[0]
        out["summary"][name], out["bins"][name] = {}, {}
        for key, config in maps.items():
            traj, cpu = odometry_alone(log, config)
            d = drift(traj, relations)
            out["bins"][name][key] = d["bins"]
            out["summary"][name][key] = {"far_median_err_deg": d["far_median_err_deg"],
                                         "far_median_err_m": d["far_median_err_m"],
                                         "far_relations": d["far_relations"], "cpu_s": round(cpu, 2)}
    out["runtime_s"] = time.perf_counter() - t0
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
