"""Mapping benchmark: classic GPOM vs Fast-GPOM vs log-odds on every STDR map_server world.

Usage: ``.venv/bin/python benchmarks/mapping.py [--scans auto] [--every 20] [--out result.json]``

For each map_server world in ../shared/data/stdr_maps (GPL, read in place, never copied; among them
the Fast-GPOM paper's three: sparse_obstacles with the Fast-GPOM fork's origin, simple_rooms and
robocup), at its own resolution, the simulator drives one coverage tour (``slam simulate --scans
auto``) with the paper's laser preset (667 beams over 240°, 0.06–4.09 m) and seed 7, for the default
0.2 m robot or, where that robot cannot reach 95 % of the plan's free space, the largest of 0.1 and
0.05 m that can (the radius is reported); every ``--every``-th scan, with its ground-truth pose, is
fed to all three mappers in this one process. Classic GPOM runs where its projected time (from its
first scans) fits ``--gpom-budget-s``.
Reported per world and method: median / p95 per-scan update time (wall clock and this thread's CPU
time — the machine is shared, so both are given), total time, hyperparameter-fit time, and the AUC
of the map against the ground truth (cells unknown in the ground truth ignored; never-observed
cells score p = 0.5), plus the AUC over observed cells only and the coverage. On simple_rooms the
Fast-GPOM run is repeated with one exact GP per scan (no locality) to measure what locality costs.
Finally 100 submaps are built and all anchors moved to time the recomposition. Each timed mapper is
preceded by two scans on a throw-away instance (warm-up).

BLAS is pinned to one thread: batched small inversions under multi-threaded OpenBLAS on a loaded
2-core machine ran ~30× slower (measured while developing).
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from core.geometry import matrix_to_xytheta, xytheta_to_matrix  # noqa: E402
from evaluation.sim import LASER_PRESETS, PROCEDURAL_WORLDS, load_world  # noqa: E402
from evaluation.sim.coverage import plan_space, scan_coverage, unreachable_space  # noqa: E402
from evaluation.sim.simulate import simulate  # noqa: E402
from mapping.beams import beam_samples  # noqa: E402
from mapping.config import MappingConfig  # noqa: E402
from mapping.fastgpom import FastGPOM, ring_training_set  # noqa: E402
from mapping.gaussian_grid import initial_hyperparameters  # noqa: E402
from mapping.gpom import ClassicGPOM  # noqa: E402
from mapping.grid import GridGeometry  # noqa: E402
from mapping.logodds import LogOddsGrid  # noqa: E402
from mapping.roc import map_roc  # noqa: E402
from mapping.submaps import SubmapFuser  # noqa: E402

STDR = REPO.parent / "shared" / "data" / "stdr_maps"
PAPER_AUC = {"sparse_obstacles.kuanghaofei_fork": 0.93, "simple_rooms": 0.93, "robocup": 0.87}
SEED = 7
ROBOT_RADII_M = (0.2, 0.1, 0.05)  # the default robot first
MIN_REACHABLE = 0.95  # of the plan's free space


def stdr_worlds() -> list[tuple[str, Path]]:
    """Every map_server map (a yaml with an ``image:`` key) in the STDR folder, by name."""
    out = []
    for p in sorted(STDR.glob("*.yaml")):
        if any(line.startswith("image:") for line in p.read_text().splitlines()):
            out.append((p.stem, p))
    if not out:
        raise SystemExit(f"no map_server worlds in {STDR}")
    return out


def robot_radius_for(world) -> tuple[float, float]:
    """The first of ROBOT_RADII_M whose robot reaches MIN_REACHABLE of the plan's space, and that fraction."""
    space_m2 = plan_space(world)[0].sum() * world.resolution**2
    for r in ROBOT_RADII_M:
        reach = 1.0 - sum(g.area_m2 for g in unreachable_space(world, r)) / space_m2
        if reach >= MIN_REACHABLE:
            break
    return r, float(reach)


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def run_mapper(mapper, frames, warmup=None) -> dict:
    if warmup is not None:  # a throw-away instance first: imports, allocator and caches warmed up
        for f in frames[:2]:
            warmup.update(f, f.ground_truth)
    wall, cpu = [], []
    for f in frames:
        t0, c0 = time.perf_counter(), time.thread_time()
        mapper.update(f, f.ground_truth)
        wall.append(time.perf_counter() - t0)
        cpu.append(time.thread_time() - c0)
    w, c = np.array(wall) * 1e3, np.array(cpu) * 1e3
    return {"median_ms": float(np.median(w)), "p95_ms": float(np.percentile(w, 95)), "total_s": float(w.sum() / 1e3),
            "cpu_median_ms": float(np.median(c)), "cpu_p95_ms": float(np.percentile(c, 95)),
            "cpu_total_s": float(c.sum() / 1e3)}


def score(m, gt) -> dict:
    _, _, auc = map_roc(m.probability, gt)
    known = gt != -1
    obs = m.observed & known
    _, _, auc_obs = map_roc(np.where(obs, m.probability, np.nan), gt)
    return {"auc": float(auc), "auc_observed_cells": float(auc_obs), "coverage": float(obs.sum() / known.sum())}


def fit_time(cfg: MappingConfig, X, y, beams):
    t0 = time.perf_counter()
    hyp = initial_hyperparameters(cfg.gp, X, y, beams)
    return hyp, time.perf_counter() - t0


def bench_world(name: str, world, n_scans: int | None, every: int, exact: bool,
                gpom_budget_s: float) -> tuple[dict, list]:
    res = world.resolution
    radius, reach = robot_radius_for(world)
    t0 = time.perf_counter()
    spec = LASER_PRESETS["fastgpom"]
    slog = simulate(world, n_scans=n_scans, spec=spec, seed=SEED, robot_radius=radius)
    t_sim = time.perf_counter() - t0
    tour_coverage = scan_coverage(world, matrix_to_xytheta(slog.sensor_poses()), spec)
    frames = list(slog.frames())[::every]
    gt_xy = slog.ground_truth[:, :2, 3]
    length = float(np.linalg.norm(np.diff(gt_xy, axis=0), axis=1).sum())
    log(f"{name}: simulated {len(slog)} scans ({length:.0f} m, robot radius {radius} m, coverage {tour_coverage:.4f}) "
        f"in {t_sim:.1f} s, mapping {len(frames)}")
    geom = GridGeometry((float(world.origin_xy[0]), float(world.origin_xy[1])), world.resolution, world.shape)
    gt = world.classes()
    cfg = MappingConfig(resolution_m=res)
    out: dict = {"resolution": res, "grid": list(world.shape), "scans_simulated": len(slog), "scans_mapped": len(frames),
                 "seed": SEED, "robot_radius_m": radius, "reachable_fraction": reach, "tour_length_m": length,
                 "tour_coverage": tour_coverage, "simulate_s": t_sim, "paper_auc_fastgpom": PAPER_AUC.get(name)}
    # hyperparameters: LML fit on the first frame (Yuan et al. §IV), timed separately
    f0 = frames[0]
    fast_hyp, t_fast = fit_time(cfg, *ring_training_set(beam_samples(f0, res, cfg.fastgpom.stop_before_hit),
                                                         cfg.fastgpom.train_beam_stride))
    X, y, _, beams = ClassicGPOM(geom, cfg).training_set(f0)
    gpom_hyp, t_gpom = fit_time(cfg, X, y, beams)
    cx = cfg.model_copy(deep=True)
    cx.fastgpom.exact_gp = True
    make = {
        "fastgpom": (lambda: FastGPOM(geom, cfg, fast_hyp), fast_hyp, t_fast),
        "gpom": (lambda: ClassicGPOM(geom, cfg, gpom_hyp), gpom_hyp, t_gpom),
        "logodds": (lambda: LogOddsGrid(geom, cfg), None, 0.0),
        "fastgpom_exact_gp": (lambda: FastGPOM(geom, cx, fast_hyp), fast_hyp, t_fast),
    }
    if not exact:
        del make["fastgpom_exact_gp"]
    maps = {}
    for key, (factory, hyp, tfit) in make.items():
        mapper = factory()
        if key == "gpom":  # where it fits in time: project from its first three scans
            probe = factory()
            t_probe = time.perf_counter()
            for f in frames[:3]:
                probe.update(f, f.ground_truth)
            projected = (time.perf_counter() - t_probe) / min(3, len(frames)) * len(frames)
            if projected > gpom_budget_s:
                out[key] = {"skipped": f"projected {projected:.0f} s > --gpom-budget-s {gpom_budget_s:.0f}"}
                log(f"  {key}: {out[key]['skipped']}")
                continue
        r = run_mapper(mapper, frames, warmup=factory())
        m = mapper.to_map()
        maps[key] = m
        r.update(score(m, gt))
        if hyp is not None:
            r["hyperparameter_fit_s"] = tfit
            r["hyperparameters"] = {"nu": hyp.nu, "length_scale": hyp.length_scale, "sigma_f": hyp.sigma_f,
                                    "sigma_n": hyp.sigma_n}
        out[key] = r
        log(f"  {key}: median {r['median_ms']:.2f} ms (cpu {r['cpu_median_ms']:.2f}) total {r['total_s']:.1f} s "
            f"auc {r['auc']:.4f} (observed {r['auc_observed_cells']:.4f}, coverage {r['coverage']:.3f})")
    if "total_s" in out["gpom"]:
        out["speedup_fastgpom_vs_gpom"] = out["gpom"]["total_s"] / out["fastgpom"]["total_s"]
        out["speedup_fastgpom_vs_gpom_cpu"] = out["gpom"]["cpu_total_s"] / out["fastgpom"]["cpu_total_s"]
    if exact:
        a, b = maps["fastgpom"], maps["fastgpom_exact_gp"]
        both = a.observed & b.observed
        out["locality"] = {
            "auc_block_minus_exact": out["fastgpom"]["auc"] - out["fastgpom_exact_gp"]["auc"],
            "max_abs_probability_difference": float(np.abs(a.probability - b.probability)[both].max()),
            "mean_abs_probability_difference": float(np.abs(a.probability - b.probability)[both].mean()),
            "class_agreement": float(np.mean((a.probability[both] > 0.5) == (b.probability[both] > 0.5))),
            "per_scan_speedup": out["fastgpom_exact_gp"]["median_ms"] / out["fastgpom"]["median_ms"],
        }
    out["_figure"] = (world, slog, maps["fastgpom"])  # for --figure; dropped before the JSON
    return out, frames


def bench_recompose(frames, res: float, n_submaps: int = 100, seed: int = 5) -> dict:
    """100 submaps (one keyframe scan each) on a shared world grid; time moving every anchor."""
    poses = np.array([f.ground_truth for f in frames])
    xy = poses[:, :2, 3]
    geom = GridGeometry.covering(xy.min(0), xy.max(0), res, margin=6.0)
    fuser = SubmapFuser(geom, MappingConfig(resolution_m=res), submap_half_size=5.0)
    reps = (n_submaps + len(frames) - 1) // len(frames)
    k = 0
    for _ in range(reps):
        for f in frames:
            if k == n_submaps:
                break
            fuser.add_submap(k, f.ground_truth)
            fuser.add_scan(k, f, f.ground_truth)
            k += 1
    t0 = time.perf_counter()
    fuser.to_map()
    first = time.perf_counter() - t0
    rng = np.random.default_rng(seed)
    anchors = {key: xytheta_to_matrix(*rng.normal(0.0, [0.05, 0.05, 0.01])) @ sm.world_T_anchor
               for key, sm in fuser.submaps.items()}
    t0, c0 = time.perf_counter(), time.thread_time()
    moved = fuser.update_poses(anchors)
    m = fuser.to_map()
    wall, cpu = time.perf_counter() - t0, time.thread_time() - c0
    return {"submaps": len(fuser.submaps), "moved": moved, "recompose_s": wall, "recompose_cpu_s": cpu,
            "initial_placement_s": first, "grid": list(geom.shape), "observed_cells": int(m.observed.sum())}


def figure(path: Path, name: str, world, slog, fast_map) -> None:
    """Plan, coverage tour and Fast-GPOM map of one world side by side (the README picture)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from core.atomic import atomic_open

    ext = world.extent
    gt = world.classes().astype(float)
    plan = np.where(gt < 0, 0.5, 1.0 - gt / 100.0)
    fig, ax = plt.subplots(1, 3, figsize=(15, 5.4), constrained_layout=True)
    ax[0].imshow(plan, origin="lower", extent=ext, cmap="gray", vmin=0, vmax=1, interpolation="nearest")
    ax[0].set_title(f"plan: {name}")
    ax[1].imshow(plan, origin="lower", extent=ext, cmap="gray", vmin=0, vmax=1, interpolation="nearest")
    xy = slog.ground_truth[:, :2, 3]
    ax[1].plot(xy[:, 0], xy[:, 1], "-", color="tab:blue", lw=0.8)
    ax[1].plot(xy[0, 0], xy[0, 1], "o", color="tab:red")
    ax[1].set_title(f"coverage tour: {len(slog)} scans, {np.linalg.norm(np.diff(xy, axis=0), axis=1).sum():.0f} m")
    from mapping.occupancy_map import max_pool

    block = max(1, int(np.ceil(max(world.shape) / 300)))  # ≤ 300 cells a panel (~430 px): one-cell walls survive
    p, seen = max_pool(fast_map.probability, fast_map.observed, block)
    p = np.where(seen, p, 0.5)
    occ_plan, _ = max_pool(np.where(gt < 0, 0.5, gt / 100.0), None, block)
    plan = 1.0 - occ_plan
    ax[0].images[0].set_data(plan)
    ax[1].images[0].set_data(plan)
    ax[2].imshow(1.0 - p, origin="lower", extent=ext, cmap="gray", vmin=0, vmax=1, interpolation="nearest")
    ax[2].set_title("Fast-GPOM map (occupancy probability)")
    for a in ax:
        a.set_xlabel("x (m)")
        a.set_aspect("equal")
    ax[0].set_ylabel("y (m)")
    with atomic_open(path, "wb") as fh:
        fig.savefig(fh, format="png", dpi=100)
    plt.close(fig)


def reference_maps() -> dict:
    """AUC (our map_roc) of the Fast-GPOM authors' own simple_rooms output maps (GPL data, read in place),
    registered to the ground truth by the shift in ../shared/data/fastgpom/SOURCE.md."""
    from scipy.io import loadmat

    from mapping.mapserver import read_map_server

    base = REPO.parent / "shared" / "data" / "fastgpom" / "data_set" / "map"
    gt = read_map_server(STDR / "simple_rooms.yaml")
    h, w = gt.shape
    out = {}
    for key, rel in (("fastgpom", "fast_gpom/stdr_simple_rooms.map.mat"), ("gpom", "gpom/simple_rooms.map.mat")):
        if (base / rel).exists():
            prob = loadmat(base / rel)["prob_map"][149 : 149 + h, 100 : 100 + w]
            out[key] = float(map_roc(prob, gt.classes)[2])
    return {"simple_rooms_auc": out, "paper_auc_fastgpom": PAPER_AUC["simple_rooms"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scans", default="auto", help="scans simulated per world: auto (one coverage tour) or a number")
    ap.add_argument("--every", type=int, default=20, help="map every n-th scan (2 s of a 10 Hz tour)")
    ap.add_argument("--worlds", default=None, help="comma-separated world names (default: every world)")
    ap.add_argument("--gpom-budget-s", type=float, default=900.0, help="skip classic GPOM on a world projected slower")
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--figure", type=Path, default=None,
                    help="PNG: plan, tour and Fast-GPOM map of --figure-world, one of our own (MIT) procedural worlds: "
                         "a picture of an STDR world would carry its GPL into the project")
    ap.add_argument("--figure-world", default="rooms", choices=PROCEDURAL_WORLDS)
    args = ap.parse_args()
    t_all = time.perf_counter()
    result: dict = {"benchmark": "mapping", "laser": "fastgpom (667 beams, 240°, 0.06–4.09 m)",
                    "blas_threads": os.environ.get("OPENBLAS_NUM_THREADS"), "load_avg_start": list(os.getloadavg()),
                    "worlds": {}}
    frames_005 = None
    n_scans = None if args.scans == "auto" else int(args.scans)
    for name, yaml in stdr_worlds():
        if args.worlds is not None and name not in args.worlds.split(","):
            continue
        r, frames = bench_world(name, load_world(str(yaml)), n_scans, args.every, exact=(name == "simple_rooms"),
                                gpom_budget_s=args.gpom_budget_s)
        r.pop("_figure")
        result["worlds"][name] = r
        if name == "simple_rooms":
            frames_005 = frames
    if args.figure is not None:  # Fast-GPOM only (classic GPOM's budget 0): the map of the picture
        r, _ = bench_world(args.figure_world, load_world(args.figure_world, seed=SEED), n_scans, args.every,
                           exact=False, gpom_budget_s=0.0)
        figure(args.figure, args.figure_world, *r.pop("_figure"))
    result["reference_code_maps"] = reference_maps()
    if frames_005 is not None:
        result["recompose"] = bench_recompose(frames_005, 0.05)
        log(f"recompose: {result['recompose']}")
    W = result["worlds"]
    G = {k: v for k, v in W.items() if "auc" in v["gpom"]}  # worlds where classic GPOM ran
    summary = {
        "fastgpom_auc": {k: v["fastgpom"]["auc"] for k, v in W.items()},
        "gpom_auc": {k: v["gpom"]["auc"] for k, v in G.items()},
        "logodds_auc": {k: v["logodds"]["auc"] for k, v in W.items()},
        "coverage": {k: v["tour_coverage"] for k, v in W.items()},
        "robot_radius_m": {k: v["robot_radius_m"] for k, v in W.items()},
        "min_fastgpom_auc_all_worlds": min(v["fastgpom"]["auc"] for v in W.values()),
        "min_coverage_all_worlds": min(v["tour_coverage"] for v in W.values()),
        "fastgpom_median_ms_at_005": W["simple_rooms"]["fastgpom"]["median_ms"] if "simple_rooms" in W else None,
        "fastgpom_cpu_median_ms_at_005": W["simple_rooms"]["fastgpom"]["cpu_median_ms"] if "simple_rooms" in W else None,
        # the smallest per-world ratio of total update times (conservative)
        "speedup_fastgpom_vs_gpom": min(v["speedup_fastgpom_vs_gpom"] for v in G.values()) if G else None,
        "speedup_fastgpom_vs_gpom_per_world": {k: v["speedup_fastgpom_vs_gpom"] for k, v in G.items()},
        "recompose_100_submaps_s": result.get("recompose", {}).get("recompose_s"),
    }
    fa, ga = summary["fastgpom_auc"], summary["gpom_auc"]
    summary["targets"] = {
        "fastgpom_auc_ge_0.95": all(a >= 0.95 for a in fa.values()),
        "coverage_ge_0.95": summary["min_coverage_all_worlds"] >= 0.95,
        "fastgpom_auc_not_below_gpom_by_0.01": all(fa[k] >= ga[k] - 0.01 for k in ga),
        "fastgpom_median_le_5ms_at_005": summary["fastgpom_median_ms_at_005"] is not None
        and summary["fastgpom_median_ms_at_005"] <= 5.0,
        "speedup_ge_20": summary["speedup_fastgpom_vs_gpom"] is not None and summary["speedup_fastgpom_vs_gpom"] >= 20.0,
        "recompose_le_0.5s": summary["recompose_100_submaps_s"] is not None and summary["recompose_100_submaps_s"] <= 0.5,
    }
    result["summary"] = summary
    result["load_avg_end"] = list(os.getloadavg())
    result["total_s"] = time.perf_counter() - t_all
    text = json.dumps(result, indent=2)
    if args.out:
        from core.atomic import atomic_open

        with atomic_open(args.out) as fh:
            fh.write(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
