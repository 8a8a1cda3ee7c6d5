"""Map quality: Fast-GPOM, classic GPOM and a log-odds grid from the same simulated scans, scored by
ROC AUC against the ground-truth world (Yuan, Kuang & Schwertfeger 2018, §IV).

Usage:  python examples/map_quality.py [--world rooms] [--scans 200]
"""

from __future__ import annotations

import argparse
import time


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--world", default="rooms", help="rooms, corridor, obstacles or a map_server yaml")
    ap.add_argument("--scans", type=int, default=200)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()

    import numpy as np

    from evaluation.sim import LASER_PRESETS, load_world, simulate
    from mapping.config import MappingConfig
    from mapping.fastgpom import FastGPOM
    from mapping.gpom import ClassicGPOM
    from mapping.grid import GridGeometry
    from mapping.logodds import LogOddsGrid
    from mapping.roc import map_roc

    # 1. A world and a log with ground-truth poses, recorded with the Fast-GPOM paper's laser.
    world = load_world(args.world)
    sim = simulate(world, n_scans=args.scans, spec=LASER_PRESETS["fastgpom"], seed=args.seed)
    frames = list(sim.frames())
    print(f"1. {len(frames)} scans in '{args.world}' ({world.occupied.shape[1]}×{world.occupied.shape[0]} cells)")

    # 2. The ground-truth classes on the world's own grid (unknown cells are ignored by the ROC).
    gt = world.classes()
    geometry = GridGeometry((float(world.origin_xy[0]), float(world.origin_xy[1])), world.resolution, world.shape)

    # 3. Build the three maps from the same scans at the true poses, and score them.
    for name, cls in (("fastgpom", FastGPOM), ("gpom", ClassicGPOM), ("logodds", LogOddsGrid)):
        mapper = cls(geometry, MappingConfig(method=name, resolution_m=world.resolution))
        t0 = time.perf_counter()
        for f in frames:
            mapper.update(f, f.ground_truth)
        dt = (time.perf_counter() - t0) / len(frames)
        m = mapper.to_map()
        _, _, auc = map_roc(m.probability, gt)  # never-observed cells keep p = 0.5
        _, _, auc_seen = map_roc(np.where(m.observed, m.probability, np.nan), gt)
        print(f"3. {name:9s} AUC {auc:.3f} (observed cells {auc_seen:.3f})   {1000 * dt:.1f} ms per scan")


if __name__ == "__main__":
    main()
