"""``slam eval ape|rpe|relations|loops|crosscheck|report``: evaluation on result files.

Every command prints ``key: value`` lines (numbers with 10 significant digits) and can save the
full result as JSON with ``--json PATH``.
"""

from __future__ import annotations

import json
from enum import Enum
from pathlib import Path
from typing import Any

import typer

from .options import real


class _Align(str, Enum):
    none = "none"
    se3 = "se3"
    sim3 = "sim3"


class _Relation(str, Enum):
    trans = "trans"
    rot_deg = "rot_deg"
    rot_rad = "rot_rad"
    rot_part = "rot_part"
    full = "full"


class _DeltaUnit(str, Enum):
    frames = "frames"
    m = "m"


class _Fmt(str, Enum):
    auto = "auto"
    tum = "tum"
    kitti = "kitti"
    g2o = "g2o"
    log_gt = "log_gt"
    log_odom = "log_odom"


def fmt_num(v: Any) -> str:
    """How numbers are printed: 10 significant digits (ints as ints)."""
    if isinstance(v, (bool, str)) or v is None:
        return str(v)
    if isinstance(v, int):
        return str(v)
    return f"{float(v):.10g}"


def _echo_pairs(pairs: dict[str, Any]) -> None:
    for k, v in pairs.items():
        typer.echo(f"{k}: {fmt_num(v)}")


def _check_json(path: Path | None) -> None:
    """Before any work: the --json path can be written."""
    if path is not None:
        from core.atomic import check_output_file

        check_output_file(path)


def _save_json(path: Path | None, obj: Any) -> None:
    if path is None:
        return
    from core.atomic import atomic_open

    with atomic_open(path, "w", encoding="utf-8") as fh:
        json.dump(obj, fh, indent=2, default=float)
        fh.write("\n")


_JSON = typer.Option(None, "--json", help="Also write the full result as JSON to this path.")
_STAMPS_HELP = "Stamps for a KITTI or g2o file: one per pose, or 'id stamp' lines."
_EST_STAMPS = typer.Option(None, "--est-stamps", help=_STAMPS_HELP)
_REF_STAMPS = typer.Option(None, "--ref-stamps", help=_STAMPS_HELP)


def ape_cmd(
    est: Path = typer.Argument(..., help="Estimated trajectory (TUM, KITTI or g2o vertices)."),
    ref: Path = typer.Argument(..., help="Reference trajectory."),
    align: _Align = typer.Option(_Align.none, "--align", help="Umeyama alignment of EST onto REF (evo_ape default: none)."),
    relation: _Relation = typer.Option(_Relation.trans, "--relation", help="Error part: trans (m), rot_deg, rot_rad, rot_part, full."),
    max_diff: float = typer.Option(0.01, "--max-diff", parser=real(0.0), help="Largest stamp difference for association (s)."),
    est_format: _Fmt = typer.Option(_Fmt.auto, "--est-format"),
    ref_format: _Fmt = typer.Option(_Fmt.auto, "--ref-format"),
    est_stamps: Path | None = _EST_STAMPS,
    ref_stamps: Path | None = _REF_STAMPS,
    json_out: Path | None = _JSON,
) -> None:
    """Absolute pose error (evo's definition): prints rmse, mean, median, max, std, min, sse."""
    _check_json(json_out)
    from evaluation.ape_rpe import evaluate_ape
    from slam.trajectory_io import read_trajectory

    res = evaluate_ape(read_trajectory(est, est_format.value, est_stamps), read_trajectory(ref, ref_format.value, ref_stamps),
                       align=align.value, relation=relation.value, max_diff=max_diff)
    typer.echo(f"metric: APE {res.relation} [{res.unit or 'unitless'}]")
    _echo_pairs({k: res.stats[k] for k in ("rmse", "mean", "median", "max", "std", "min", "sse")})
    typer.echo(f"pairs: {res.n_matched}")
    _save_json(json_out, res.to_dict())


def rpe_cmd(
    est: Path = typer.Argument(..., help="Estimated trajectory (TUM, KITTI or g2o vertices)."),
    ref: Path = typer.Argument(..., help="Reference trajectory."),
    delta: float = typer.Option(1.0, "--delta", parser=real(0.0, above=True), help="Pair distance (frames or metres)."),
    delta_unit: _DeltaUnit = typer.Option(_DeltaUnit.frames, "--delta-unit", help="frames, or m of travelled path."),
    relation: _Relation = typer.Option(_Relation.trans, "--relation"),
    align: _Align = typer.Option(_Align.none, "--align"),
    all_pairs: bool = typer.Option(False, "--all-pairs", help="Every start pose instead of consecutive pairs."),
    pairs_from_reference: bool = typer.Option(False, "--pairs-from-reference", help="Metric pairs from REF's path (default: EST's, as evo)."),
    max_diff: float = typer.Option(0.01, "--max-diff", parser=real(0.0), help="Largest stamp difference for association (s)."),
    est_format: _Fmt = typer.Option(_Fmt.auto, "--est-format"),
    ref_format: _Fmt = typer.Option(_Fmt.auto, "--ref-format"),
    est_stamps: Path | None = _EST_STAMPS,
    ref_stamps: Path | None = _REF_STAMPS,
    json_out: Path | None = _JSON,
) -> None:
    """Relative pose error (evo's definition): prints rmse, mean, median, max, std, min, sse."""
    _check_json(json_out)
    from evaluation.ape_rpe import evaluate_rpe
    from slam.trajectory_io import read_trajectory

    d: float = int(delta) if delta_unit is _DeltaUnit.frames and float(delta).is_integer() else delta
    res = evaluate_rpe(read_trajectory(est, est_format.value, est_stamps), read_trajectory(ref, ref_format.value, ref_stamps), delta=d,
                       delta_unit=delta_unit.value, relation=relation.value, align=align.value, all_pairs=all_pairs,
                       max_diff=max_diff, pairs_from_reference=pairs_from_reference)
    if not len(res.errors):
        from core.errors import InputFileError

        raise InputFileError(est, None, f"no two of the {res.n_matched} poses associated with {ref} are --delta "
                             f"{fmt_num(d)} {delta_unit.value} apart: nothing to measure (give a smaller --delta)")
    typer.echo(f"metric: RPE {res.relation} [{res.unit or 'unitless'}] delta {fmt_num(d)} {delta_unit.value}")
    _echo_pairs({k: res.stats[k] for k in ("rmse", "mean", "median", "max", "std", "min", "sse")})
    typer.echo(f"pairs: {len(res.errors)}")
    _save_json(json_out, res.to_dict())


def relations_table(result: Any, dataset: str | None) -> list[str]:
    """Lines comparing our relation metric with the published numbers for *dataset*."""
    from evaluation.published import DATASET_NAMES, METRIC_KEYS, PUBLISHED

    pub = PUBLISHED.get(dataset) if dataset else None
    units = {"trans": "[m]", "trans_sq": "[m^2]", "rot": "[deg]", "rot_sq": "[deg^2]"}
    head = f"{'metric':<22}{'ours':>24}"
    if pub:
        head += f"{'Cartographer':>24}{'Graph Mapping':>24}"
    lines = [f"dataset: {DATASET_NAMES[dataset]}" if pub else "dataset: not recognised (no published numbers)", head]
    for key, (label, m_attr, s_attr) in METRIC_KEYS.items():
        row = f"{label + ' ' + units[key]:<22}{f'{getattr(result, m_attr):.4g} ± {getattr(result, s_attr):.4g}':>24}"
        if pub:
            for meth in ("cartographer", "graph_mapping"):
                m, s = pub[meth][key]
                row += f"{f'{m:g} ± {s:g}':>24}"
        lines.append(row)
    return lines


def relations_cmd(
    traj: Path = typer.Argument(..., help="Estimated trajectory with scan stamps (TUM, or KITTI/g2o with --stamps)."),
    relations: Path = typer.Argument(..., help="Relations file 't1 t2 x y z roll pitch yaw' (Kümmerle et al. 2009)."),
    stamp_tol: float = typer.Option(1e-3, "--stamp-tol", parser=real(0.0), help="Stamp matching tolerance (s)."),
    traj_format: _Fmt = typer.Option(_Fmt.auto, "--format"),
    stamps: Path | None = typer.Option(None, "--stamps", help=_STAMPS_HELP),
    dataset: str | None = typer.Option(None, "--dataset", help="Dataset key for published numbers (default: from the file name)."),
    json_out: Path | None = _JSON,
) -> None:
    """Kümmerle relation metric: trans/rot mean ± std (abs and squared), missing-stamp count, published numbers."""
    _check_json(json_out)
    from evaluation.published import PUBLISHED, recognise_dataset
    from evaluation.relations import evaluate_relations, read_relations
    from slam.trajectory_io import read_trajectory

    res = evaluate_relations(read_trajectory(traj, traj_format.value, stamps), read_relations(relations), stamp_tol)
    if res.n_used == 0:
        from core.errors import InputFileError

        raise InputFileError(traj, None, f"no relation of {relations} has both stamps in this trajectory (within "
                             f"--stamp-tol {stamp_tol} s): was it written from the same log?")
    ds = dataset or recognise_dataset(relations) or recognise_dataset(traj)
    out = res.to_dict()
    _echo_pairs(out)
    for line in relations_table(res, ds):
        typer.echo(line)
    _save_json(json_out, {**out, "dataset": ds, "published": PUBLISHED.get(ds) if ds else None})


def nees_cmd(
    run: Path = typer.Argument(..., help="A slam run folder (graph.g2o, node_stamps.txt, odometry.tum)."),
    relations: Path = typer.Argument(..., help="Ground-truth relations 't1 t2 x y z roll pitch yaw' (Kümmerle et al. 2009)."),
    stamp_tol: float = typer.Option(1e-3, "--stamp-tol", parser=real(0.0), help="Stamp matching tolerance (s)."),
    heading_drift: float | None = typer.Option(None, "--heading-drift", parser=real(0.0), help="σ of the loop closer's heading rate (° per m) added to the chain's covariance; default: the run's config.yaml (loops.heading_drift_deg_per_m); 0: the edges' covariances alone."),
    reference: bool = typer.Option(True, "--reference-noise/--no-reference-noise", help="Add the relations' own error, estimated from the triangles they close among themselves (a → b, b → c, a → c), to each chain's covariance."),
    json_out: Path | None = _JSON,
) -> None:
    """Consistency of the front end's covariance: NEES/dof of its keyframe chains against the relations, per chain
    length (1 = consistent; above, overconfident; below, conservative)."""
    _check_json(json_out)
    import numpy as np

    from core.errors import InputFileError
    from core.trajectory import read_node_stamps
    from evaluation.nees import bin_by_length, chain_nees, fuse_steps, heading_by_path
    from evaluation.relations import read_relations, reference_noise
    from evaluation.trajectory import nearest_indices
    from slam.graph import read_graph
    from slam.graph.posegraph import KINDS
    from slam.trajectory_io import read_trajectory

    graph = read_graph(run / "graph.g2o")
    if graph.dim != 2:
        raise InputFileError(run / "graph.g2o", None, "is not a planar graph; the NEES table is for 2D runs")
    a = graph.edge_arrays()
    odo = np.flatnonzero(a.kinds == KINDS.index("odometry"))
    edges = [(int(a.ii[e]), int(a.jj[e]), a.measurements[e], np.linalg.inv(a.information[e])) for e in odo]
    try:
        mu, cov = fuse_steps(graph.num_nodes, edges)
    except ValueError as err:
        raise InputFileError(run / "graph.g2o", None, str(err)) from None
    node_t = read_node_stamps(run / "node_stamps.txt", graph.node_ids)
    scans = read_trajectory(run / "odometry.tum")
    kf_scan = np.searchsorted(node_t, scans.stamps + stamp_tol, side="right") - 1
    ia, sa = nearest_indices(node_t, scans.stamps, stamp_tol)
    if len(ia) != len(node_t):
        raise InputFileError(run / "node_stamps.txt", None, "a keyframe stamp has no scan in odometry.tum")
    kf_odom = scans.poses[sa]
    rel = read_relations(relations)
    i1, s1 = nearest_indices(rel.t1, scans.stamps, stamp_tol)
    i2, s2 = nearest_indices(rel.t2, scans.stamps, stamp_tol)
    both = np.intersect1d(i1, i2)
    m1, m2 = dict(zip(i1, s1)), dict(zip(i2, s2))
    keep = [r for r in both if kf_scan[m1[r]] >= 0 and kf_scan[m2[r]] >= 0]
    if not keep:
        raise InputFileError(relations, None, f"no relation has both stamps among the scans of {run} (within --stamp-tol {stamp_tol} s)")
    pairs = np.array([(m1[r], m2[r]) for r in keep], dtype=np.int64)
    if heading_drift is None:
        heading_drift = _run_heading_drift(run)
    noise = reference_noise(rel) if reference else None
    rows = chain_nees(mu, cov, kf_scan, scans.poses, kf_odom, pairs, rel.deltas[keep], float(np.radians(heading_drift)),
                      None if noise is None else noise.covariance())
    bins = bin_by_length(rows)
    typer.echo(f"relations: {len(rows)} (of {len(rel)}; within one keyframe interval or unmatched: {len(rel) - len(rows)}); "
               f"heading rate σ {heading_drift:g} °/m")
    if noise is not None:
        typer.echo(f"relations' own error, from {noise.triangles} triangles: σ {noise.sigma_translation_m:.4f} m per axis, "
                   f"{np.degrees(noise.sigma_rotation_rad):.3f}° (added to every chain)")
    elif reference:
        typer.echo("relations' own error: not estimated (fewer than 20 triangles among the relations)")
    typer.echo(f"{'keyframes':>12} {'n':>6} {'NEES/dof':>9} {'median':>8} {'rms_m':>8} {'σ_m':>8} {'rms_deg':>8} {'σ_deg':>8}")
    for b in bins:
        span = f'{b.lo}+' if b.hi >= 10**8 else f'{b.lo}-{b.hi}'
        typer.echo(f"{span:>12} {b.n:>6} {b.nees_mean:>9.3f} {b.nees_median:>8.3f} {b.rms_translation_m:>8.4f} "
                   f"{b.sigma_translation_m:>8.4f} {b.rms_rotation_deg:>8.3f} {b.sigma_rotation_deg:>8.3f}")
    by_path = heading_by_path(rows)
    if by_path:
        typer.echo("heading error by odometry path between the keyframes:")
        typer.echo(f"{'path_m':>12} {'n':>6} {'med_deg':>8} {'p95_deg':>8} {'med_°/m':>8} {'p95_°/m':>8} {'σ_deg':>8}")
        for h in by_path:
            span = f"{h.lo_m:.0f}+" if not np.isfinite(h.hi_m) else f"{h.lo_m:.0f}-{h.hi_m:.0f}"
            typer.echo(f"{span:>12} {h.n:>6} {h.error_median_deg:>8.2f} {h.error_p95_deg:>8.2f} {h.rate_median_deg_per_m:>8.4f} "
                       f"{h.rate_p95_deg_per_m:>8.4f} {h.sigma_median_deg:>8.2f}")
    _save_json(json_out, {"relations": len(rows), "heading_drift_deg_per_m": heading_drift, "bins": [b.as_dict() for b in bins],
                          "heading_by_path": [h.as_dict() for h in by_path],
                          "reference_noise": None if noise is None else {
                              "sigma_translation_m": noise.sigma_translation_m,
                              "sigma_rotation_deg": float(np.degrees(noise.sigma_rotation_rad)), "triangles": noise.triangles}})


def _run_heading_drift(run: Path) -> float:
    """The heading-rate σ (°/m) of the run's own configuration (``config.yaml``), or the default one."""
    from core.errors import ConfigError
    from core.yaml_config import load_yaml
    from slam.pipeline.config import SlamConfig

    try:
        return load_yaml(SlamConfig, run / "config.yaml").loops.heading_drift_deg_per_m
    except ConfigError:
        return SlamConfig().loops.heading_drift_deg_per_m


def _node_gt_poses(graph: Any, gt: Path, node_stamps: Path | None, max_diff: float) -> Any:
    """True poses of the graph nodes: by stamp (``--node-stamps`` file of 'id stamp' or one stamp per node)
    or, without it, node id = row of the ground-truth trajectory."""
    from core.errors import LogFormatError
    from core.trajectory import read_node_stamps
    from evaluation.trajectory import nearest_indices
    from slam.trajectory_io import read_trajectory

    ref = read_trajectory(gt)
    ids = graph.node_ids
    if node_stamps is None:
        if ids.max(initial=-1) >= len(ref):
            raise LogFormatError(gt, None, f"has {len(ref)} poses but the graph has node id {int(ids.max())}; give --node-stamps")
        return ref.poses[ids]
    st = read_node_stamps(node_stamps, ids)
    a, b = nearest_indices(st, ref.stamps, max_diff)
    if len(a) != len(st):
        raise LogFormatError(gt, None, f"{len(st) - len(a)} node stamps have no ground-truth pose within {max_diff} s")
    return ref.poses[b]


def loops_cmd(
    graph_path: Path = typer.Argument(..., help="g2o graph with loop edges marked (gpslam edge tags)."),
    poses: Path | None = typer.Option(None, "--poses", help="Optimised poses (g2o/TUM); default: the graph's vertices."),
    gt: Path | None = typer.Option(None, "--gt", help="Ground-truth trajectory (TUM) for precision/recall."),
    node_stamps: Path | None = typer.Option(None, "--node-stamps", help="'id stamp' per node, to find the nodes in --gt."),
    trans_tol: float = typer.Option(0.20, "--trans-tol", parser=real(0.0), help="Allowed violation in m (Hess et al. 2016: 0.20)."),
    rot_tol: float = typer.Option(1.0, "--rot-tol", parser=real(0.0), help="Allowed violation in degrees (Hess et al. 2016: 1.0)."),
    revisit_radius: float = typer.Option(1.0, "--revisit-radius", parser=real(0.0, above=True),
                                         help="True revisit distance in m (with --gt)."),
    min_separation: int = typer.Option(30, "--min-separation", min=1, help="Smallest node-index gap of a revisit (with --gt)."),
    max_diff: float = typer.Option(0.01, "--max-diff", parser=real(0.0), help="Stamp tolerance for --node-stamps (s)."),
    json_out: Path | None = _JSON,
) -> None:
    """Loop-closure precision (violated by ≤ 20 cm and ≤ 1° after optimisation); with --gt, precision and recall."""
    _check_json(json_out)
    from evaluation.loops import loop_edges_from_graph, score_against_truth, score_loops
    from slam.backends.crosscheck import load_solution
    from slam.graph import read_graph

    graph = read_graph(graph_path)
    if poses is None and not graph.has_initial_guess:
        from core.errors import GraphFormatError

        raise GraphFormatError(graph_path, None, "has no VERTEX pose for every node; give the optimised poses with --poses")
    P = load_solution(poses, graph) if poses is not None else graph.poses
    loops = loop_edges_from_graph(graph)
    if not len(loops):
        from core.errors import GraphFormatError

        raise GraphFormatError(graph_path, None, "has no loop closure (no edge tagged kind=loop or between "
                               "non-consecutive nodes): nothing to score")
    s = score_loops(loops, P, trans_tol, rot_tol)
    out: dict[str, Any] = {"self": s.to_dict()}
    _echo_pairs({"loops": s.n_loops, "correct": s.n_correct, "precision": s.precision})
    if gt is not None:
        t = score_against_truth(loops, _node_gt_poses(graph, gt, node_stamps, max_diff), revisit_radius, min_separation,
                                trans_tol, rot_tol)
        if not t.n_revisit_nodes:
            from core.errors import InputFileError

            raise InputFileError(gt, None, f"no node comes back within --revisit-radius {revisit_radius} m of one at "
                                 f"least --min-separation {min_separation} nodes earlier: recall is undefined")
        out["truth"] = t.to_dict()
        _echo_pairs({"gt_true_positive": t.n_true_positive, "gt_precision": t.precision,
                     "gt_revisit_nodes": t.n_revisit_nodes, "gt_recall": t.recall})
    _save_json(json_out, out)


def crosscheck_cmd(
    graph_path: Path = typer.Argument(..., help="Pose graph (g2o or TORO)."),
    sol_a: Path = typer.Argument(..., help="First solution (g2o vertices by id, or TUM/KITTI in node order)."),
    sol_b: Path = typer.Argument(..., help="Second solution."),
    names: str = typer.Option("a,b", "--names", help="Labels of the two solutions, comma-separated."),
    json_out: Path | None = _JSON,
) -> None:
    """Both objectives (SE-Sync, GTSAM χ²) of two solutions and their pose differences, printed as JSON."""
    _check_json(json_out)
    from slam.backends.crosscheck import crosscheck, load_solution
    from slam.graph import read_graph

    graph = read_graph(graph_path)
    na, nb = (names.split(",") + ["b"])[:2]
    out = crosscheck(graph, load_solution(sol_a, graph), load_solution(sol_b, graph), (na.strip(), nb.strip()))
    typer.echo(json.dumps(out["graph"] | {k: out[k] for k in (na.strip(), nb.strip())} | {
        "objective_rel_diff": out["objective_rel_diff"], "raw": out["raw"], "aligned": out["aligned"],
        "bbox_diagonal_m": out["bbox_diagonal_m"],
        "max_position_diff_percent_of_diagonal": out["max_position_diff_percent_of_diagonal"]}, default=float))
    _save_json(json_out, out)


def report_cmd(
    result_dir: Path = typer.Argument(..., help="Folder written by 'slam run' (trajectory.tum, graph.g2o, map.npz, summary.json ...)."),
    gt: Path | None = typer.Option(None, "--gt", help="Ground-truth trajectory (TUM)."),
    relations: Path | None = typer.Option(None, "--relations", help="Kümmerle relations file."),
    gt_map: Path | None = typer.Option(None, "--gt-map", help="Ground-truth map (map_server YAML)."),
    out: Path | None = typer.Option(None, "--out", help="Output folder (default: RESULT_DIR)."),
) -> None:
    """Write report.html (figures inline) and metrics.json; print the metrics as 'key: value' lines."""
    from evaluation.report import flatten_metrics

    from .report_io import write_run_report

    od = out if out is not None else result_dir
    for name in ("report.html", "metrics.json"):
        _check_json(od / name)

    rep = write_run_report(result_dir, gt, relations, gt_map, out)
    for k, v in flatten_metrics(rep.metrics).items():
        typer.echo(f"{k}: {fmt_num(v)}")
    for n in rep.notes:
        typer.echo(f"note: {n}")
    typer.echo(f"report: {od / 'report.html'}")
    typer.echo(f"metrics: {od / 'metrics.json'}")


def register(app: typer.Typer, eval_app: typer.Typer) -> None:
    eval_app.command("ape")(ape_cmd)
    eval_app.command("rpe")(rpe_cmd)
    eval_app.command("relations")(relations_cmd)
    eval_app.command("loops")(loops_cmd)
    eval_app.command("nees")(nees_cmd)
    eval_app.command("crosscheck")(crosscheck_cmd)
    eval_app.command("report")(report_cmd)
