"""Peer benchmark (issue 7): KISS-SLAM beside our pipeline on the same log, in one process.

Both systems read the same CARMEN log (default the bundled Intel Research Lab log) and are
scored with the Kümmerle et al. 2009 relation metric (:mod:`evaluation.relations`) against the
same relations file; the raw wheel odometry of the processed scans is scored too, as the floor.

* **ours**: exactly what ``slam run`` does (``slam.cli.run_cmd.run_log`` with the default
  ``SlamConfig``, mapping on) into a temporary folder, so the wall time includes reading the
  log, odometry, loop closure, the pose graph, the Fast-GPOM map and writing every output.
* **kiss_slam**: KISS-SLAM 0.0.2 (:mod:`evaluation.peers`), each scan's returns as a z = 0
  cloud in the sensor frame, with :class:`evaluation.peers.KissSlamPlanarParams` (2D-laser
  settings, documented there; change any with ``--peer-param key=value``). Its wall time
  includes reading the log, every ``process_scan`` and the final per-scan optimisation; it
  builds no occupancy map and writes nothing.

KISS-SLAM is optional (``make peers``; its map-closures dependency caps numpy, pydantic and typer
below our pins, so it is installed without its dependency metadata — see pyproject.toml).
Without it the script stops with a one-line error unless ``--skip-peer`` is given.

Prints one JSON object: ``summary`` (the keys the issue fixes; null for a skipped system) and
``details``. Usage::

    python benchmarks/peers.py [--log data/intel.clf.bz2] [--relations data/intel.relations]
        [--max-scans N] [--skip-ours] [--skip-peer] [--peer-param extrude_height=0.05] [--out f.json]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import time
from importlib import metadata
from pathlib import Path
from typing import Iterator

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from core.errors import GpslamError  # noqa: E402

INTEL = REPO / "data" / "intel.clf.bz2"
INTEL_REL = REPO / "data" / "intel.relations"


def _clean(x):  # type: ignore[no-untyped-def]
    """JSON-ready copy: numpy scalars → Python, NaN/inf → None (strict JSON has no NaN)."""
    if isinstance(x, dict):
        return {k: _clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_clean(v) for v in x]
    if isinstance(x, np.generic):
        x = x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def _relations(traj, relations) -> dict:  # type: ignore[no-untyped-def]
    from evaluation.relations import evaluate_relations

    return evaluate_relations(traj, relations).to_dict()


def _version(dist: str) -> str | None:
    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return None


class _OdometryTap:
    """Wraps a frame stream and keeps (stamp, wheel-odometry pose) of every frame it passes on."""

    def __init__(self, frames) -> None:  # type: ignore[no-untyped-def]
        self._frames = frames
        self.stamps: list[float] = []
        self.odom: list[np.ndarray] = []

    def __iter__(self) -> Iterator:
        for f in self._frames:
            if f.odom is not None:
                self.stamps.append(f.stamp)
                self.odom.append(f.odom)
            yield f

    def trajectory(self):  # type: ignore[no-untyped-def]
        from core.trajectory import Trajectory

        if not self.stamps:
            return None
        return Trajectory(np.asarray(self.stamps), np.asarray(self.odom).reshape(-1, 4, 4))


def run_ours(log: Path, relations, max_scans: int | None) -> dict:  # type: ignore[no-untyped-def]
    """``slam run`` (default config, mapping on) into a temporary folder; relation error and wall time."""
    from core.trajectory import read_tum
    from evaluation.peers import stdout_to_stderr
    from slam.cli.run_cmd import load_config, run_log

    cfg = load_config(None, {"max_scans": max_scans})
    with tempfile.TemporaryDirectory(prefix="peers-ours-") as tmp:
        out = Path(tmp) / "run"
        with stdout_to_stderr():
            t0 = time.perf_counter()
            s = run_log(log, out, cfg, None, quiet=True)
            wall = time.perf_counter() - t0
        traj = read_tum(out / "trajectory.tum")
    return {"wall_s": wall, "relations": _relations(traj, relations),
            "run": {k: s[k] for k in ("scans", "keyframes", "loop_closures", "wall_time_s", "scans_per_second",
                                      "peak_memory_mb", "stage_times_s")},
            "config": {"odometry": cfg.odometry.method, "backend": cfg.backend.kind,
                       "mapping": cfg.mapping.enabled}}


def run_peer(log: Path, relations, max_scans: int | None,  # type: ignore[no-untyped-def]
             params) -> tuple[dict, _OdometryTap]:
    """KISS-SLAM over the log (streamed); relation error, wall time, closures."""
    from evaluation.peers import run_kiss_slam
    from slam.logs import open_log

    tap = _OdometryTap(open_log(log).frames())
    r = run_kiss_slam(tap, params, max_scans)
    X = r.trajectory.poses
    return {"wall_s": r.wall_s, "relations": _relations(r.trajectory, relations), "scans": len(r.trajectory),
            "local_maps": r.local_maps, "closures_accepted": len(r.closures),
            "closure_candidates_singular_icp": r.closures_singular,
            "max_abs_z_m": float(np.abs(X[:, 2, 3]).max()),
            "max_tilt_deg": float(np.degrees(np.arcsin(np.clip(np.abs(X[:, 2, :2]).max(), 0, 1)))),
            "params": r.params}, tap


def wheel_odometry(log: Path, relations, max_scans: int | None,  # type: ignore[no-untyped-def]
                   tap: _OdometryTap | None) -> dict | None:
    """Relation error of the raw wheel odometry of the same scans (from *tap*, else one more read)."""
    if tap is None:
        from slam.logs import open_log

        tap = _OdometryTap(open_log(log).frames())
        for i, _ in enumerate(tap, start=1):
            if max_scans is not None and i >= max_scans:
                break
    traj = tap.trajectory()
    return None if traj is None else {"scans": len(traj), "relations": _relations(traj, relations)}


def _peer_params(pairs: list[str]):  # type: ignore[no-untyped-def]
    from pydantic import ValidationError

    from evaluation.peers import KissSlamPlanarParams

    upd: dict[str, object] = {}
    for item in pairs:
        key, sep, value = item.partition("=")
        if not sep:
            raise GpslamError(f"--peer-param {item!r}: expected key=value")
        upd[key.strip()] = value.strip()
    try:
        return KissSlamPlanarParams.model_validate(upd)
    except ValidationError as exc:
        first = exc.errors()[0]
        raise GpslamError(f"--peer-param {'.'.join(map(str, first['loc']))}: {first['msg']}") from None


def benchmark(args: argparse.Namespace) -> dict:
    from evaluation.peers import INSTALL_HINT, PeerUnavailableError, kiss_slam_available
    from evaluation.published import PUBLISHED, recognise_dataset
    from evaluation.relations import read_relations

    params = None if args.skip_peer else _peer_params(args.peer_param)
    if not args.skip_peer and not kiss_slam_available():
        raise PeerUnavailableError(f"{INSTALL_HINT}, or pass --skip-peer")
    if args.max_scans is not None and args.max_scans < 1:
        raise GpslamError(f"--max-scans must be ≥ 1, got {args.max_scans}")
    relations = read_relations(args.relations)
    dataset = recognise_dataset(args.relations) or recognise_dataset(args.log)
    published = PUBLISHED.get(dataset) if dataset else None

    ours = None if args.skip_ours else run_ours(args.log, relations, args.max_scans)
    peer, tap = (None, None) if args.skip_peer else run_peer(args.log, relations, args.max_scans, params)
    wheel = wheel_odometry(args.log, relations, args.max_scans, tap)

    def rel(d: dict | None, key: str):  # type: ignore[no-untyped-def]
        return None if d is None else d["relations"][key]

    ratio = (ours["wall_s"] / peer["wall_s"]) if ours and peer and peer["wall_s"] > 0 else None
    summary = {
        "ours_translation_mean_m": rel(ours, "trans_mean"),
        "ours_rotation_mean_deg": rel(ours, "rot_mean_deg"),
        "ours_wall_s": ours["wall_s"] if ours else None,
        "kiss_slam_translation_mean_m": rel(peer, "trans_mean"),
        "kiss_slam_rotation_mean_deg": rel(peer, "rot_mean_deg"),
        "kiss_slam_wall_s": peer["wall_s"] if peer else None,
        "ratio_wall_ours_vs_kiss_slam": ratio,
        "cartographer_translation_mean_m": published["cartographer"]["trans"][0] if published else None,
    }
    details = {
        "log": str(args.log), "relations_file": str(args.relations), "dataset": dataset,
        "max_scans": args.max_scans, "relations_total": len(relations),
        "ours": ours, "kiss_slam": peer, "wheel_odometry": wheel,
        "published": published,
        "versions": {d: _version(d)
                     for d in ("gpslam", "kiss-slam", "map-closures", "kiss-icp", "open3d", "numpy")},
        "notes": [
            "relation error: Kümmerle et al. 2009, mean/std over the relations whose both stamps were processed "
            "(n_used; n_missing lie outside the processed scans)",
            "ours_wall_s: slam run end to end (read, odometry, loops, pose graph, Fast-GPOM map, all outputs); "
            "kiss_slam_wall_s: read + process_scan + final fine-grained optimisation, no map, no outputs",
            "kiss_slam input: each scan's returns as z = 0 points in the sensor frame (no-return beams dropped); "
            "its point-to-plane closure check is singular on such clouds (all normals ±z), counted in "
            "closure_candidates_singular_icp and treated as rejected",
        ],
    }
    return {"summary": summary, "details": details}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--log", type=Path, default=INTEL, help="CARMEN/MCAP/ROS 1 log (default: bundled Intel)")
    ap.add_argument("--relations", type=Path, default=INTEL_REL, help="ground-truth relations of the log")
    ap.add_argument("--max-scans", type=int, default=None, help="process only the first N scans (quick run)")
    ap.add_argument("--skip-ours", action="store_true", help="do not run our pipeline")
    ap.add_argument("--skip-peer", action="store_true", help="do not run KISS-SLAM")
    ap.add_argument("--peer-param", action="append", default=[], metavar="KEY=VALUE",
                    help="override a KissSlamPlanarParams field, e.g. extrude_height=0.05 (repeatable)")
    ap.add_argument("--out", type=Path, default=None, help="also write the JSON here (atomically)")
    args = ap.parse_args(argv)
    try:
        result = _clean(benchmark(args))
    except GpslamError as exc:
        print(f"error: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2
    text = json.dumps(result, indent=2, allow_nan=False)
    if args.out is not None:
        from core.atomic import atomic_open

        with atomic_open(args.out) as fh:
            fh.write(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
