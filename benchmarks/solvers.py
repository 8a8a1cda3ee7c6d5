"""Pose-graph solvers: our chordal Gauss-Newton vs GTSAM Levenberg-Marquardt on the SE-Sync benchmark graphs.

For each graph with a published f* (SE-Sync IJRR 2019, Tables 1-2; ../shared/data/PUBLISHED_RESULTS.md §2):
both solvers start from the same chordal initialisation, run ``--repeats`` times interleaved in this one
process (the machine is shared, so the minimum wall time is reported next to all runs), and their final SE-Sync
objective and GTSAM χ² are recorded. GTSAM's time is its optimiser only (factor-graph construction is listed
separately); ours includes all assembly. The sparse linear solvers available without new dependencies are
timed on one Gauss-Newton system of city10000 and sphere2500, and the peak RSS of solving city10000 is measured
in fresh child processes. Prints one JSON object with a top-level ``summary``.

    .venv/bin/python benchmarks/solvers.py [--repeats 3]
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from slam.backends.chordal import _linear_system, _Pattern, solve_chordal  # noqa: E402
from slam.backends.gtsam_backend import optimize  # noqa: E402
from slam.backends.linsolve import SOLVERS, spd_solve  # noqa: E402
from slam.graph import read_g2o  # noqa: E402
from slam.graph.costs import chordal_weights, gtsam_error, sesync_objective  # noqa: E402
from slam.graph.init import chordal_initialisation  # noqa: E402

DATA = REPO.parent / "shared" / "data" / "pose_graphs" / "sesync"
# name: (published f*, PDL-GN time [s]) from SE-Sync IJRR 2019 Tables 1-2
PUBLISHED = {
    "CSAIL": (3.170e1, 0.029),
    "intel": (5.235e1, 0.120),
    "manhattan": (6.432e3, 0.268),
    "city10000": (6.386e2, 1.670),
    "sphere2500": (1.687e3, 0.704),
}


def bench_graph(name: str, repeats: int) -> dict:
    g = read_g2o(DATA / f"{name}.g2o")
    t0 = time.perf_counter()
    P0 = chordal_initialisation(g)
    t_init = time.perf_counter() - t0
    ch_times, gt_times, gt_build = [], [], []
    ch = gt = None
    for _ in range(repeats):
        ch = solve_chordal(g, P0)
        ch_times.append(ch.time_s)
        gt = optimize(g, P0, method="lm")
        gt_times.append(gt.time_s)
        gt_build.append(gt.build_time_s)
    assert ch is not None and gt is not None
    fstar, pdl = PUBLISHED[name]
    d = g.dim
    diag = float(np.linalg.norm(np.ptp(gt.poses[:, :d, 3], axis=0)))
    worst = float(np.linalg.norm(ch.poses[:, :d, 3] - gt.poses[:, :d, 3], axis=1).max())
    return {
        "nodes": g.num_nodes,
        "edges": g.num_edges,
        "initial_sesync_objective": sesync_objective(g, P0),
        "chordal_init_time_s": t_init,
        "chordal": {
            "time_s": min(ch_times), "times_s": ch_times, "iterations": ch.iterations,
            "sesync_objective": ch.cost, "gtsam_error": gtsam_error(g, ch.poses),
        },
        "gtsam_lm": {
            "time_s": min(gt_times), "times_s": gt_times, "build_time_s": min(gt_build), "iterations": gt.iterations,
            "sesync_objective": sesync_objective(g, gt.poses), "gtsam_error": gt.error,
        },
        "published_fstar": fstar,
        "published_pdl_time_s": pdl,
        "chordal_rel_diff_to_fstar": abs(ch.cost - fstar) / fstar,
        "max_position_diff_m": worst,
        "max_position_diff_pct_of_bbox_diag": 100.0 * worst / diag,
    }


def bench_linear_solvers(name: str) -> dict:
    """Time each sparse SPD solver on the first Gauss-Newton system of *name* (min of 3)."""
    g = read_g2o(DATA / f"{name}.g2o")
    P = chordal_initialisation(g)
    a = g.edge_arrays()
    kappa, tau = chordal_weights(g)
    var = np.arange(g.num_nodes) - 1
    pat = _Pattern(a.ii, a.jj, var, g.dof)
    B, bj, _ = _linear_system(P, a.ii, a.jj, a.measurements, kappa, tau, g.dim)
    H, rhs = pat.matrix(B), -pat.gradient(bj)
    out: dict = {"n": H.shape[0], "nnz": int(H.nnz)}
    for method in SOLVERS:
        ts = []
        for _ in range(3):
            t0 = time.perf_counter()
            x = spd_solve(H, rhs, method)
            ts.append(time.perf_counter() - t0)
        out[method] = {"time_s": min(ts), "residual": float(np.abs(H @ x - rhs).max())}
    return out


def memory_child(name: str, which: str) -> None:
    """Run in a fresh process: read, initialise and solve *name* with *which*; print peak RSS in MiB."""
    g = read_g2o(DATA / f"{name}.g2o")
    P0 = chordal_initialisation(g)
    if which == "chordal":
        solve_chordal(g, P0)
    else:
        optimize(g, P0)
    print(peak_rss_mib())


def peak_rss_mib() -> float:
    """Peak resident set size of this process in MiB: VmHWM from /proc (reset by exec, unlike ru_maxrss, which a
    child started by fork + exec inherits from its parent), else ru_maxrss."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return float(line.split()[1]) / 1024.0  # kB
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--memory-child", nargs=2, metavar=("GRAPH", "SOLVER"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.memory_child:
        memory_child(*args.memory_child)
        return
    per = {name: bench_graph(name, args.repeats) for name in PUBLISHED}
    lin = {name: bench_linear_solvers(name) for name in ("city10000", "sphere2500")}
    rss = {}
    for which in ("chordal", "gtsam"):
        p = subprocess.run([sys.executable, __file__, "--memory-child", "city10000", which],
                           capture_output=True, text=True, check=True)
        rss[which] = float(p.stdout.strip().splitlines()[-1])
    summary = {
        "graphs": list(per),
        "max_time_ratio_chordal_vs_gtsam": max(r["chordal"]["time_s"] / r["gtsam_lm"]["time_s"] for r in per.values()),
        "max_time_ratio_chordal_vs_published_pdl": max(r["chordal"]["time_s"] / r["published_pdl_time_s"]
                                                       for r in per.values()),
        "max_rel_diff_to_published_fstar": max(r["chordal_rel_diff_to_fstar"] for r in per.values()),
        "max_position_diff_pct_of_bbox_diag": max(r["max_position_diff_pct_of_bbox_diag"] for r in per.values()),
        "city10000_peak_rss_mib": rss,
        "per_graph": {
            name: {
                "chordal_time_s": r["chordal"]["time_s"],
                "gtsam_time_s": r["gtsam_lm"]["time_s"],
                "chordal_sesync_objective": r["chordal"]["sesync_objective"],
                "gtsam_sesync_objective": r["gtsam_lm"]["sesync_objective"],
                "published_fstar": r["published_fstar"],
                "published_pdl_time_s": r["published_pdl_time_s"],
            }
            for name, r in per.items()
        },
    }
    print(json.dumps({"summary": summary, "graphs": per, "linear_solvers": lin}, indent=1))


if __name__ == "__main__":
    main()
