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


def fmt_num(v: Any) -> str:
    """How numbers are printed: 10 significant digits (ints as ints)."""
    if isinstance(v, bool) or v is None:
        return str(v)
    if isinstance(v, int):
        return str(v)
    return f"{float(v):.10g}"


def _echo_pairs(pairs: dict[str, Any]) -> None:
    for k, v in pairs.items():
        typer.echo(f"{k}: {fmt_num(v)}")


def _save_json(path: Path | None, obj: Any) -> None:
    if path is None:
        return
    from registration.atomic import atomic_open

    with atomic_open(path, "w", encoding="utf-8") as fh:
        json.dump(obj, fh, indent=2, default=float)
        fh.write("\n")


_JSON = typer.Option(None, "--json", help="Also write the full result as JSON to this path.")


def ape_cmd(
    est: Path = typer.Argument(..., help="Estimated trajectory (TUM, KITTI or g2o vertices)."),
    ref: Path = typer.Argument(..., help="Reference trajectory."),
    align: _Align = typer.Option(_Align.none, "--align", help="Umeyama alignment of EST onto REF (evo_ape default: none)."),
    relation: _Relation = typer.Option(_Relation.trans, "--relation", help="Error part: trans [m], rot_deg, rot_rad, rot_part, full."),
    max_diff: float = typer.Option(0.01, "--max-diff", help="Largest stamp difference for association [s]."),
    est_format: _Fmt = typer.Option(_Fmt.auto, "--est-format"),
    ref_format: _Fmt = typer.Option(_Fmt.auto, "--ref-format"),
    json_out: Path | None = _JSON,
) -> None:
    """Absolute pose error (evo's definition): prints rmse, mean, median, max, std, min, sse."""
    from evaluation.ape_rpe import evaluate_ape
    from slam.trajectory_io import read_trajectory

    res = evaluate_ape(read_trajectory(est, est_format.value), read_trajectory(ref, ref_format.value),
                       align=align.value, relation=relation.value, max_diff=max_diff)
    typer.echo(f"metric: APE {res.relation} [{res.unit or 'unitless'}]")
    _echo_pairs({k: res.stats[k] for k in ("rmse", "mean", "median", "max", "std", "min", "sse")})
    typer.echo(f"pairs: {res.n_matched}")
    _save_json(json_out, res.to_dict())


def rpe_cmd(
    est: Path = typer.Argument(..., help="Estimated trajectory (TUM, KITTI or g2o vertices)."),
    ref: Path = typer.Argument(..., help="Reference trajectory."),
    delta: float = typer.Option(1.0, "--delta", help="Pair distance (frames or metres)."),
    delta_unit: _DeltaUnit = typer.Option(_DeltaUnit.frames, "--delta-unit", help="frames, or m of travelled path."),
    relation: _Relation = typer.Option(_Relation.trans, "--relation"),
    align: _Align = typer.Option(_Align.none, "--align"),
    all_pairs: bool = typer.Option(False, "--all-pairs", help="Every start pose instead of consecutive pairs."),
    pairs_from_reference: bool = typer.Option(False, "--pairs-from-reference", help="Metric pairs from REF's path (default: EST's, as evo)."),
    max_diff: float = typer.Option(0.01, "--max-diff", help="Largest stamp difference for association [s]."),
    est_format: _Fmt = typer.Option(_Fmt.auto, "--est-format"),
    ref_format: _Fmt = typer.Option(_Fmt.auto, "--ref-format"),
    json_out: Path | None = _JSON,
) -> None:
    """Relative pose error (evo's definition): prints rmse, mean, median, max, std, min, sse."""
    from evaluation.ape_rpe import evaluate_rpe
    from slam.trajectory_io import read_trajectory

    d: float = int(delta) if delta_unit is _DeltaUnit.frames and float(delta).is_integer() else delta
    res = evaluate_rpe(read_trajectory(est, est_format.value), read_trajectory(ref, ref_format.value), delta=d,
                       delta_unit=delta_unit.value, relation=relation.value, align=align.value, all_pairs=all_pairs,
                       max_diff=max_diff, pairs_from_reference=pairs_from_reference)
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
    stamp_tol: float = typer.Option(1e-3, "--stamp-tol", help="Stamp matching tolerance [s]."),
    traj_format: _Fmt = typer.Option(_Fmt.auto, "--format"),
    dataset: str | None = typer.Option(None, "--dataset", help="Dataset key for published numbers (default: from the file name)."),
    json_out: Path | None = _JSON,
) -> None:
    """Kümmerle relation metric: trans/rot mean ± std (abs and squared), missing-stamp count, published numbers."""
    from evaluation.published import PUBLISHED, recognise_dataset
    from evaluation.relations import evaluate_relations, read_relations
    from slam.trajectory_io import read_trajectory

    res = evaluate_relations(read_trajectory(traj, traj_format.value), read_relations(relations), stamp_tol)
    ds = dataset or recognise_dataset(relations) or recognise_dataset(traj)
    out = res.to_dict()
    _echo_pairs(out)
    for line in relations_table(res, ds):
        typer.echo(line)
    _save_json(json_out, {**out, "dataset": ds, "published": PUBLISHED.get(ds) if ds else None})


def register(app: typer.Typer, eval_app: typer.Typer) -> None:
    eval_app.command("ape")(ape_cmd)
    eval_app.command("rpe")(rpe_cmd)
    eval_app.command("relations")(relations_cmd)
