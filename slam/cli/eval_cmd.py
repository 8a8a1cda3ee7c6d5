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

from .eval_io import JSON_OPTION, check_json, echo_pairs, fmt_num, save_json
from .eval_nees import nees_cmd
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
    json_out: Path | None = JSON_OPTION,
) -> None:
    """Absolute pose error (evo's definition): prints rmse, mean, median, max, std, min, sse."""
    check_json(json_out)
    from evaluation.ape_rpe import evaluate_ape
    from slam.trajectory_io import read_trajectory

    res = evaluate_ape(read_trajectory(est, est_format.value, est_stamps), read_trajectory(ref, ref_format.value, ref_stamps),
                       align=align.value, relation=relation.value, max_diff=max_diff)
    typer.echo(f"metric: APE {res.relation} [{res.unit or 'unitless'}]")
    echo_pairs({k: res.stats[k] for k in ("rmse", "mean", "median", "max", "std", "min", "sse")})
    typer.echo(f"pairs: {res.n_matched}")
    save_json(json_out, res.to_dict())


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
    json_out: Path | None = JSON_OPTION,
) -> None:
    """Relative pose error (evo's definition): prints rmse, mean, median, max, std, min, sse."""
    check_json(json_out)
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
    echo_pairs({k: res.stats[k] for k in ("rmse", "mean", "median", "max", "std", "min", "sse")})
    typer.echo(f"pairs: {len(res.errors)}")
    save_json(json_out, res.to_dict())


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
    json_out: Path | None = JSON_OPTION,
) -> None:
    """Kümmerle relation metric: trans/rot mean ± std (abs and squared), missing-stamp count, published numbers."""
    check_json(json_out)
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
    echo_pairs(out)
    for line in relations_table(res, ds):
        typer.echo(line)
    save_json(json_out, {**out, "dataset": ds, "published": PUBLISHED.get(ds) if ds else None})


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
    json_out: Path | None = JSON_OPTION,
) -> None:
    """Loop-closure precision (violated by ≤ 20 cm and ≤ 1° after optimisation); with --gt, precision and recall."""
    check_json(json_out)
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
    echo_pairs({"loops": s.n_loops, "correct": s.n_correct, "precision": s.precision})
    if gt is not None:
        t = score_against_truth(loops, _node_gt_poses(graph, gt, node_stamps, max_diff), revisit_radius, min_separation,
                                trans_tol, rot_tol)
        if not t.n_revisit_nodes:
            from core.errors import InputFileError

            raise InputFileError(gt, None, f"no node comes back within --revisit-radius {revisit_radius} m of one at "
                                 f"least --min-separation {min_separation} nodes earlier: recall is undefined")
        out["truth"] = t.to_dict()
        echo_pairs({"gt_true_positive": t.n_true_positive, "gt_precision": t.precision, "gt_gross": int(t.gross.sum()),
                     "gt_revisit_nodes": t.n_revisit_nodes, "gt_recall": t.recall})
    save_json(json_out, out)


def crosscheck_cmd(
    graph_path: Path = typer.Argument(..., help="Pose graph (g2o or TORO)."),
    sol_a: Path = typer.Argument(..., help="First solution (g2o vertices by id, or TUM/KITTI in node order)."),
    sol_b: Path = typer.Argument(..., help="Second solution."),
    names: str = typer.Option("a,b", "--names", help="Labels of the two solutions, comma-separated."),
    json_out: Path | None = JSON_OPTION,
) -> None:
    """Both objectives (SE-Sync, GTSAM χ²) of two solutions and their pose differences, printed as JSON."""
    check_json(json_out)
    from slam.backends.crosscheck import crosscheck, load_solution
    from slam.graph import read_graph

    graph = read_graph(graph_path)
    na, nb = (names.split(",") + ["b"])[:2]
    out = crosscheck(graph, load_solution(sol_a, graph), load_solution(sol_b, graph), (na.strip(), nb.strip()))
    typer.echo(json.dumps(out["graph"] | {k: out[k] for k in (na.strip(), nb.strip())} | {
        "objective_rel_diff": out["objective_rel_diff"], "raw": out["raw"], "aligned": out["aligned"],
        "bbox_diagonal_m": out["bbox_diagonal_m"],
        "max_position_diff_percent_of_diagonal": out["max_position_diff_percent_of_diagonal"]}, default=float))
    save_json(json_out, out)


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
        check_json(od / name)

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
