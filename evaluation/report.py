"""``slam eval report``: metrics and a self-contained HTML report for one result folder.

Reads whatever of the pipeline outputs exist in the folder (DESIGN.md "Outputs of slam run"):
``trajectory.tum`` (optimised pose of every scan), ``odometry.tum``, ``graph.g2o`` (loop edges
marked; the caller reads it, :mod:`slam.cli.report_io`), ``map.npz`` (``mean``, ``variance``, ``probability``, ``resolution``, ``origin``) and
``summary.json`` (stage timings under ``stage_times_s``, seconds, as ``slam run`` writes them).
Optional inputs: a ground-truth trajectory (APE after SE(2)/SE(3) Umeyama alignment, RPE over one
frame, loop precision/recall), Kümmerle relations (with the published numbers) and a ground-truth
map (map ROC/AUC, after moving the map into the ground-truth frame with the trajectory alignment).

Writes ``report.html`` (every figure inline as a base64 PNG, no external files) and
``metrics.json`` (nested; the console prints the same numbers flattened as ``a.b.c: value``).
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from core import geometry as geo
from core.atomic import atomic_open
from core.errors import GpslamError, InputFileError, MapFormatError
from core.trajectory import Trajectory

from .report_figures import Figure, closing_figures, trajectory_figures
from .report_html import page

Array = NDArray[np.float64]

__all__ = ["Figure", "Report", "build_report", "write_report", "flatten_metrics", "resample_classes", "RUN_FILES"]

#: The files of a ``slam run`` folder the report reads; a folder with none of them is not a run's.
RUN_FILES = ("trajectory.tum", "odometry.tum", "graph.g2o", "map.npz", "summary.json")


@dataclass
class Report:
    """Everything a report holds: nested metrics, figures and notes on inputs that were missing."""

    metrics: dict[str, Any] = field(default_factory=dict)
    figures: list[Figure] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)


def flatten_metrics(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """``{"a": {"b": 1}}`` → ``{"a.b": 1}`` (lists and None are left out; they are not printed)."""
    out: dict[str, Any] = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(flatten_metrics(v, key + "."))
        elif isinstance(v, (bool, int, float, str)) and v is not None:
            out[key] = v
    return out


def _clean(obj: Any) -> Any:
    """JSON-safe copy: numpy scalars to Python, NaN/inf to None."""
    if isinstance(obj, dict):
        return {str(k): _clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_clean(v) for v in obj]
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def _timings(summary: dict[str, Any]) -> dict[str, float]:
    """Stage → seconds from ``summary.json``: its ``stage_times_s`` (``{"odometry_s": …}``, what ``slam run``
    writes), under the stage names (``odometry``)."""
    val = summary.get("stage_times_s")
    if not isinstance(val, dict):
        return {}
    return {str(k).removesuffix("_s"): float(v) for k, v in val.items()
            if isinstance(v, (int, float)) and not isinstance(v, bool)}


def resample_classes(gt_classes: NDArray[np.int8], gt_resolution: float, gt_origin: Array, shape: tuple[int, int],
                     resolution: float, origin: Array, gt_T_map: Array | None = None) -> NDArray[np.int8]:
    """Ground-truth classes at the cell centres of a map grid (nearest cell; −1 outside the ground truth).

    Cell centre ``(iy, ix)`` = origin + ((ix + ½)·res, (iy + ½)·res) in the map frame, moved into
    the ground-truth frame by *gt_T_map* (4×4, default identity) and then into the ground-truth
    grid (whose origin may carry a yaw, as map_server allows).
    """
    h, w = shape
    iy, ix = np.mgrid[0:h, 0:w]
    pts = np.column_stack([origin[0] + (ix.ravel() + 0.5) * resolution, origin[1] + (iy.ravel() + 0.5) * resolution])
    if gt_T_map is not None:
        pts = geo.transform_points(gt_T_map, pts)
    g_origin = np.asarray(gt_origin, float)
    yaw = float(g_origin[2]) if g_origin.size > 2 else 0.0
    local = (pts - g_origin[:2]) @ geo.rot2(yaw)  # rotate by −yaw: row-vector form of R(yaw)ᵀ p
    gx = np.floor(local[:, 0] / gt_resolution).astype(np.int64)
    gy = np.floor(local[:, 1] / gt_resolution).astype(np.int64)
    H, W = gt_classes.shape
    ok = (gx >= 0) & (gx < W) & (gy >= 0) & (gy < H)
    out = np.full(h * w, -1, np.int8)
    out[ok] = gt_classes[gy[ok], gx[ok]]
    return out.reshape(h, w)


def _load_map(path: Path) -> dict[str, Any]:
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except (OSError, ValueError) as exc:
        raise MapFormatError(path, None, f"cannot read npz: {exc}") from None
    for k in ("probability", "resolution", "origin"):
        if k not in data:
            raise MapFormatError(path, None, f"missing array {k!r} (expected mean, variance, probability, resolution, origin)")
    return data


def _node_stamps(result_dir: Path, graph: Any, traj: Any) -> Array | None:
    """Scan stamps of the graph nodes: ``node_stamps.txt`` ('id stamp'), else nodes whose optimised pose
    equals a pose of ``trajectory.tum`` (within 1e-6 m / 1e-6) — the pipeline writes both from one solution."""
    f = result_dir / "node_stamps.txt"
    ids = graph.node_ids
    if f.exists():
        rows = [r.split() for r in f.read_text().splitlines() if r.strip() and not r.startswith("#")]
        table = {int(float(a)): float(b) for a, b in rows}
        if all(int(i) in table for i in ids):
            return np.array([table[int(i)] for i in ids])
        return None
    if traj is None:
        return None
    from scipy.spatial import cKDTree

    P = graph.poses
    if not np.all(np.isfinite(P)):
        return None
    d, k = cKDTree(traj.positions).query(P[:, :3, 3])
    same_rot = np.abs(traj.poses[k, :3, :3] - P[:, :3, :3]).max(axis=(1, 2)) <= 1e-6
    if np.all(d <= 1e-6) and np.all(same_rot):
        return traj.stamps[k]
    return None


def build_report(
    result_dir: str | os.PathLike[str],
    gt: Trajectory | None = None,
    relations: str | os.PathLike[str] | None = None,
    gt_map: str | os.PathLike[str] | None = None,
    max_diff: float = 0.01,
    result_label: str | None = None,
    graph=None,  # type: ignore[no-untyped-def]
) -> Report:
    """Compute the metrics and figures for *result_dir* (see the module docstring).

    *gt* is the ground-truth trajectory and *graph* the run's pose graph (its ``graph.g2o``), both read by
    the caller (a robot log's ground truth and the g2o format are the ``slam`` package's to read).
    *result_label* is how the report names the result folder (default: *result_dir*), e.g. the
    final folder when the report is written into a temporary one that is moved there afterwards.
    """
    rd = Path(result_dir)
    if not rd.is_dir():
        raise InputFileError(rd, None, "result folder does not exist")
    if not any((rd / name).is_file() for name in RUN_FILES):
        raise InputFileError(rd, None, f"has none of the files of a run ({', '.join(RUN_FILES)}): nothing to report")
    rep = Report()
    rep.metrics["result_dir"] = str(rd) if result_label is None else result_label
    trajs = _trajectories(rd, rep)
    truth = _against_ground_truth(trajs, gt, max_diff, rep)
    rel_series = _against_relations(trajs, relations, rep)
    loops_xy = _graph_and_loops(rd, graph, trajs, gt, max_diff, rep)
    mp, gt_bg = _map_and_roc(rd, gt_map, truth.gt_T_map, rep)
    _summary(rd, rep)
    rep.figures = (trajectory_figures(trajs, gt, truth.aligned_paths, truth.ape_series, rel_series, loops_xy, mp, gt_bg)
                   + rep.figures + closing_figures(mp, rep.metrics.get("timings_s")))
    rep.metrics = _clean(rep.metrics)
    return rep


def _trajectories(rd: Path, rep: Report) -> dict[str, Trajectory]:
    """The run's estimate and odometry (``trajectory.tum``, ``odometry.tum``) with their sizes."""
    from core.trajectory import read_tum

    trajs: dict[str, Any] = {}
    for label, name in (("estimate", "trajectory.tum"), ("odometry", "odometry.tum")):
        if (rd / name).exists():
            t = read_tum(rd / name)
            trajs[label] = t
            rep.metrics.setdefault("trajectories", {})[label] = {
                "poses": len(t), "duration_s": float(t.stamps[-1] - t.stamps[0]) if len(t) else 0.0,
                "path_length_m": t.path_length(),
            }
        else:
            rep.notes.append(f"{name} not found")
    return trajs


@dataclass
class _Truth:
    """What the comparison with the ground-truth trajectory leaves for the figures and the map."""

    aligned_paths: dict[str, Array]  # positions in the ground-truth frame (or the map frame without one)
    gt_T_map: Array | None  # the estimate's alignment onto the ground truth
    ape_series: dict[str, tuple[Array, Array]]  # stamps, APE per trajectory


def _against_ground_truth(trajs: dict[str, Trajectory], gt: Trajectory | None, max_diff: float, rep: Report) -> _Truth:
    """APE (SE(d)-aligned) and RPE over one frame of every trajectory against *gt*."""
    from .ape_rpe import evaluate_ape, evaluate_rpe

    m = rep.metrics
    out = _Truth({}, None, {})
    if gt is None:
        rep.notes.append("no ground-truth trajectory (--gt): APE/RPE not computed")
        out.aligned_paths = {k: v.positions for k, v in trajs.items()}
        return out
    out.aligned_paths["ground truth"] = gt.positions
    for label, t in trajs.items():
        try:
            a = evaluate_ape(t, gt, align="se3", max_diff=max_diff)
            r = evaluate_rpe(t, gt, delta=1, delta_unit="frames", max_diff=max_diff)
        except GpslamError as exc:  # e.g. no common stamps: report it, keep the rest of the report
            rep.notes.append(f"{label}: APE/RPE not computed: {exc}")
            continue
        m.setdefault("ape_trans_m", {})[label] = {k: a.stats[k] for k in ("rmse", "mean", "median", "max")} | {"pairs": a.n_matched}
        m.setdefault("rpe_trans_m", {})[label] = {k: r.stats[k] for k in ("rmse", "mean", "median", "max")} | {"pairs": len(r.errors)}
        out.ape_series[label] = (a.stamps, a.errors)
        if a.est_aligned is None or a.alignment is None:
            continue
        out.aligned_paths[label] = a.est_aligned.positions
        if label == "estimate":
            out.gt_T_map = a.alignment.transform
    return out


def _against_relations(trajs: dict[str, Trajectory], relations: str | os.PathLike[str] | None,
                       rep: Report) -> dict[str, tuple[Array, Array]]:
    """The Kümmerle relation error of every trajectory, the published figures beside it; the error series."""
    rel_series: dict[str, tuple[Array, Array]] = {}
    if relations is None:
        return rel_series
    from .published import LOOP_PRECISION, PUBLISHED, recognise_dataset
    from .relations import evaluate_relations, read_relations

    m = rep.metrics
    rel = read_relations(relations)
    ds = recognise_dataset(relations)
    m["relations"] = {"file": str(relations), "dataset": ds or "unknown"}
    for label, t in trajs.items():
        res = evaluate_relations(t, rel)
        m["relations"][label] = res.to_dict()
        if res.n_used:
            rel_series[label] = (rel.t2[res.used], res.trans_errors)
        else:  # e.g. a run over the first scans of a log only
            rep.notes.append(f"{label}: none of the {len(rel)} relations joins two scans of the trajectory")
    if ds:
        m["relations"]["published"] = {
            meth: {k: {"mean": v[0], "std": v[1]} for k, v in vals.items()} for meth, vals in PUBLISHED[ds].items()
        }
        n_c, prec = LOOP_PRECISION[ds]
        m["relations"]["published"]["cartographer_loop_precision"] = prec
        m["relations"]["published"]["cartographer_loop_constraints"] = n_c
    return rel_series


def _graph_and_loops(rd: Path, graph, trajs: dict[str, Trajectory], gt: Trajectory | None,  # type: ignore[no-untyped-def]
                     max_diff: float, rep: Report) -> Array | None:
    """Graph sizes, loop-closure precision (and, with ground truth, recall); the loop edges' end points."""
    if graph is None:
        rep.notes.append("graph.g2o not found" if not (rd / "graph.g2o").exists() else "graph.g2o not read")
        return None
    from .loops import loop_edges_from_graph, score_against_truth, score_loops

    m = rep.metrics
    kinds = graph.edge_kinds
    m["graph"] = {"nodes": graph.num_nodes, "edges": graph.num_edges,
                  "odometry_edges": kinds.count("odometry"), "loop_edges": kinds.count("loop")}
    loops = loop_edges_from_graph(graph)
    if not graph.has_initial_guess:
        rep.notes.append("graph.g2o has no vertex poses: loop precision not computed")
        return None
    m["loops"] = score_loops(loops, graph.poses).to_dict()
    P = graph.poses
    loops_xy = np.stack([P[loops.ii, :2, 3], P[loops.jj, :2, 3]], axis=1) if len(loops) else None
    if gt is not None:
        st = _node_stamps(rd, graph, trajs.get("estimate"))
        if st is None:
            rep.notes.append("graph nodes could not be tied to scan stamps (no node_stamps.txt and vertex poses "
                             "not found in trajectory.tum): loop recall not computed")
        else:
            from .trajectory import nearest_indices

            a_idx, b_idx = nearest_indices(st, gt.stamps, max_diff)
            if len(a_idx) == len(st):
                m["loops_vs_truth"] = score_against_truth(loops, gt.poses[b_idx]).to_dict()
            else:
                rep.notes.append("some graph nodes have no ground-truth pose: loop recall not computed")
    return loops_xy


def _map_and_roc(rd: Path, gt_map: str | os.PathLike[str] | None, gt_T_map: Array | None,
                 rep: Report) -> tuple[dict[str, Any] | None, tuple[Array, float, Array] | None]:
    """The map's size and, against a ground-truth map, its ROC/AUC; the map and the ground truth's image."""
    from . import plots

    m = rep.metrics
    mp = None
    gt_bg: tuple[Array, float, Array] | None = None
    if gt_map is not None:
        from mapping.mapserver import read_map_server

        gmap = read_map_server(gt_map)
        gcls = np.asarray(gmap.classes)
        gt_bg = (np.where(gcls == -1, np.nan, np.clip(gcls, 0, 100) / 100.0), float(gmap.resolution),
                 np.asarray(gmap.origin, float))
    if not (rd / "map.npz").exists():
        rep.notes.append("map.npz not found")
        if gt_map is not None:
            rep.notes.append("--gt-map given but there is no map.npz: ROC not computed")
        return mp, gt_bg
    mp = _load_map(rd / "map.npz")
    prob = np.asarray(mp["probability"], float)
    res_m = float(np.asarray(mp["resolution"]).reshape(-1)[0])
    origin = np.asarray(mp["origin"], float).reshape(-1)
    m["map"] = {"rows": int(prob.shape[0]), "cols": int(prob.shape[1]), "resolution_m": res_m}
    if gt_map is not None:
        from mapping.roc import map_roc

        cls = resample_classes(gmap.classes, gmap.resolution, gmap.origin, prob.shape, res_m, origin, gt_T_map)
        try:
            fpr, tpr, auc = map_roc(prob, cls)
            m["map"]["auc"] = auc
            m["map"]["gt_cells_compared"] = int(np.sum((cls != -1) & np.isfinite(prob)))
            m["map"]["gt_frame"] = "aligned by the trajectory's SE(d) Umeyama fit" if gt_T_map is not None else "map frame"
            rep.figures.append(Figure("Map ROC", plots.roc_png({"map": (fpr, tpr, auc)}),
                                      "Occupancy probability of each map cell scored against the ground-truth map "
                                      "(unknown ground-truth cells ignored)."))
        except GpslamError as exc:
            rep.notes.append(f"map ROC not computed: {exc}")
    return mp, gt_bg


def _summary(rd: Path, rep: Report) -> None:
    """Counts and stage timings of ``summary.json``; the closures the back end pruned count against precision."""
    from core.run_summary import read_run_summary

    m = rep.metrics
    if not (rd / "summary.json").exists():
        rep.notes.append("summary.json not found")
        return
    try:
        summary = read_run_summary(rd / "summary.json").model_dump()
    except MapFormatError as exc:  # another version's folder: the rest of the report stands
        rep.notes.append(f"{' '.join(str(exc).split())}: counts and timings not reported")
        return
    tm = _timings(summary)
    counts = {k: v for k, v in summary.items() if isinstance(v, (int, float)) and not isinstance(v, bool)
              and not k.endswith("_time_s")}
    if counts:
        m["summary"] = counts  # top-level numbers of summary.json (scan, keyframe, loop counts ...)
    pruned = summary["loop_stats"].get("pruned")
    if "loops" in m and isinstance(pruned, int) and pruned >= 0:
        # graph.g2o holds only the closures the back end kept; the ones it pruned (violated by more
        # than its thresholds, by default Cartographer's 20 cm / 1°) count against the verifier.
        lp = m["loops"]
        lp["pruned_by_back_end"] = pruned
        total = lp["n_loops"] + pruned
        lp["precision_counting_pruned"] = lp["n_correct"] / total if total else float("nan")
    if tm:
        m["timings_s"] = tm
    else:
        rep.notes.append("summary.json has no stage timings")


def write_report(
    result_dir: str | os.PathLike[str],
    gt: Trajectory | None = None,
    relations: str | os.PathLike[str] | None = None,
    gt_map: str | os.PathLike[str] | None = None,
    out_dir: str | os.PathLike[str] | None = None,
    result_label: str | None = None,
    graph=None,  # type: ignore[no-untyped-def]
) -> Report:
    """Build the report (:func:`build_report`) and write ``report.html`` and ``metrics.json`` into *out_dir*
    (default *result_dir*)."""
    rep = build_report(result_dir, gt, relations, gt_map, result_label=result_label, graph=graph)
    od = Path(out_dir) if out_dir is not None else Path(result_dir)
    with atomic_open(od / "metrics.json", "w", encoding="utf-8") as fh:
        json.dump(rep.metrics, fh, indent=2)
        fh.write("\n")
    with atomic_open(od / "report.html", "w", encoding="utf-8") as fh:
        fh.write(page(rep.metrics, flatten_metrics(rep.metrics), rep.figures, rep.notes))
    return rep
