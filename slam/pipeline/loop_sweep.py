"""Precision/recall of loop closure over a grid of :class:`~slam.pipeline.config.LoopConfig` settings.

The front end runs once (:func:`slam.pipeline.loop_replay.record_front_end`); every grid point replays
loop detection, verification and the pose graph (:func:`slam.pipeline.loop_replay.replay_loops`) and is
scored on the closures the verifier accepted (before the back end's pruning):

* with ground truth (every frame carries ``Frame.ground_truth``, e.g. logs of ``slam simulate``):
  precision and recall against the true revisits, :func:`evaluation.loops.score_against_truth`;
* always: Cartographer's self-consistency criterion on the optimised poses (Hess et al., ICRA 2016,
  §VI-B: violated by ≤ 20 cm and ≤ 1°), :func:`evaluation.loops.score_loops` — the precision of logs
  without ground truth;
* with a Kümmerle relations file: the relation error of the whole trajectory (Kümmerle et al. 2009).

A sweep is written ``NAME=start:stop:count`` (``count`` values evenly spaced from ``start`` to ``stop``,
both included; integer fields are rounded); several sweeps form their cartesian product. ``slam loops``
sweeps :class:`LoopConfig` fields by name; ``slam batch`` uses the same grammar with dotted names into
:class:`SlamConfig` (:func:`numeric_fields`, e.g. ``odometry.icp_2d.icp.tol_translation_m``). Each grid point is scored
by :func:`score_setting`, one call per setting, which a parallel executor may run anywhere.
"""

from __future__ import annotations

import copy
import itertools
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence, TypeVar

import numpy as np
from pydantic import BaseModel, ValidationError

from core.errors import ConfigError
from evaluation.loops import ROT_TOL_DEG, TRANS_TOL, loop_edges_from_closures, score_against_truth, score_loops

from .config import LoopConfig, SlamConfig

M = TypeVar("M", bound=BaseModel)
#: ``map_fn(fn, shared, items, on_done)`` → ``[fn(*shared, *item) for item in items]`` in item order, calling
#: ``on_done(index, result)`` as each finishes; a parallel executor may run the calls anywhere.
MapFn = Callable[[Callable[..., Any], tuple, Sequence[tuple], Callable[[int, Any], None] | None], list]

__all__ = ["Sweep", "SWEEP_MARKER", "SweepResult", "parse_sweep", "numeric_fields", "sweep_grid", "run_loop_sweep", "sweep_recorded",
           "score_setting", "write_sweep", "COLUMNS_TRUTH", "COLUMNS_SELF", "COLUMNS_RELATIONS"]

# Columns after the swept values, by kind of log.
COLUMNS_TRUTH = ("accepted", "pruned", "true_positive", "false_positive", "precision", "revisits_found", "revisits",
                 "recall", "consistent", "time_s")
COLUMNS_SELF = ("accepted", "pruned", "consistent", "precision", "time_s")
COLUMNS_RELATIONS = ("relation_trans_mean_m", "relation_rot_mean_deg")


@dataclass(frozen=True)
class Sweep:
    """One swept :class:`LoopConfig` field and its values (ints for integer fields)."""

    name: str
    values: tuple[float | int, ...]


@dataclass
class SweepResult:
    """Rows (one per grid point, grid order) with their column names, and what the experiment ran on."""

    columns: list[str]
    rows: list[dict[str, object]]
    meta: dict[str, object] = field(default_factory=dict)

    @property
    def has_truth(self) -> bool:
        return bool(self.meta.get("ground_truth"))


def numeric_fields(model: type[BaseModel], prefix: str = "") -> dict[str, type]:
    """Fields of *model* a sweep may vary, by (dotted) name: the int and float ones, optional (None = off)
    or not, also inside nested models (``numeric_fields(SlamConfig)`` has ``"loops.icp_tolerance_m"``)."""
    out: dict[str, type] = {}
    for name, f in model.model_fields.items():
        ann = f.annotation
        if isinstance(ann, type) and issubclass(ann, BaseModel):
            out |= numeric_fields(ann, f"{prefix}{name}.")
            continue
        for kind in (int, float):
            if ann in (kind, kind | None):
                out[f"{prefix}{name}"] = kind
    return out


def parse_sweep(text: str, fields: dict[str, type] | None = None) -> Sweep:
    """``NAME=start:stop:count`` → :class:`Sweep`; ConfigError (one line) for anything malformed.

    *fields*: the names a sweep may vary and their kinds (default: :class:`LoopConfig`'s, see
    :func:`numeric_fields`). Values are checked against the field's constraints by :func:`sweep_grid`.
    """
    loop_names = fields is None
    fields = numeric_fields(LoopConfig) if fields is None else fields
    name, eq, spec = text.partition("=")
    name = name.strip()
    if not eq or not name:
        raise ConfigError(f"--sweep {text!r}: expected NAME=start:stop:count")
    if name not in fields:
        if loop_names:
            kind = "is not a numeric loop setting" if name in LoopConfig.model_fields else "is not a loop setting"
            known = ", ".join(sorted(fields))
        else:
            kind = "is not a numeric setting"
            known = "dotted config names, e.g. loops.icp_tolerance_m, odometry.icp_2d.icp.tol_translation_m, max_scans"
        raise ConfigError(f"--sweep {text!r}: {name!r} {kind}; sweepable: {known}")
    parts = spec.split(":")
    if len(parts) != 3:
        raise ConfigError(f"--sweep {text!r}: expected NAME=start:stop:count")
    try:
        start, stop = float(parts[0]), float(parts[1])
    except ValueError:
        raise ConfigError(f"--sweep {text!r}: start and stop must be numbers") from None
    if not (math.isfinite(start) and math.isfinite(stop)):
        raise ConfigError(f"--sweep {text!r}: start and stop must be finite")
    try:
        count = int(parts[2])
    except ValueError:
        raise ConfigError(f"--sweep {text!r}: count must be a whole number") from None
    if count < 1:
        raise ConfigError(f"--sweep {text!r}: count must be >= 1")
    if count == 1 and start != stop:
        raise ConfigError(f"--sweep {text!r}: count 1 needs start == stop")
    vals = np.linspace(start, stop, count)
    if fields[name] is int:  # integer fields: rounded, repeated values dropped
        values: tuple[float | int, ...] = tuple(dict.fromkeys(int(v) for v in np.rint(vals)))
    else:  # 12 significant digits: 0.4:0.8:3 gives the default 0.6 itself, not 0.6000000000000001
        values = tuple(float(f"{v:.12g}") for v in vals)
    return Sweep(name, values)


def sweep_grid(base: M, sweeps: Iterable[Sweep]) -> list[tuple[dict[str, float | int], M]]:
    """Cartesian product of *sweeps* over *base*: ``(swept values, config)`` per grid point, first sweep slowest.

    *base* is a :class:`LoopConfig` (``slam loops``) or any config model whose fields the sweeps name,
    dotted into nested models (``slam batch``: a :class:`SlamConfig`). Without sweeps: the base setting
    alone. ConfigError for a field swept twice or a value the model rejects.
    """
    sweeps = list(sweeps)
    names = [s.name for s in sweeps]
    dup = {n for n in names if names.count(n) > 1}
    if dup:
        raise ConfigError(f"--sweep given twice for {', '.join(sorted(dup))}")
    data = base.model_dump()
    grid = []
    for combo in itertools.product(*(s.values for s in sweeps)):
        setting = dict(zip(names, combo))
        point = copy.deepcopy(data)
        for name, value in setting.items():
            *path, leaf = name.split(".")
            node = point
            for key in path:
                node = node[key]
            node[leaf] = value
        try:
            cfg = type(base).model_validate(point)
        except ValidationError as exc:
            err = exc.errors()[0]
            where = ".".join(str(p) for p in err["loc"])
            raise ConfigError(f"--sweep {where}={setting.get(where, '?')}: {err['msg']}") from None
        grid.append((setting, cfg))
    return grid


def _nan_to_none(v: object) -> object:
    return None if isinstance(v, float) and not math.isfinite(v) else v


def run_loop_sweep(
    frames: Iterable,
    config: SlamConfig,
    sweeps: Iterable[Sweep] = (),
    *,
    relations=None,  # evaluation.relations.Relations
    revisit_radius: float = 1.0,
    min_separation: int | None = None,
    progress: Callable[[str], None] | None = None,
    map_fn: MapFn | None = None,
) -> SweepResult:
    """Record the front end over *frames* once (``config.max_scans`` honoured), then :func:`sweep_recorded`.

    The grid is validated before the log is read. *progress* is called with a one-line message after
    the front end and after each setting; *map_fn* runs the settings (:func:`sweep_recorded`).
    """
    from .loop_replay import record_front_end

    sweeps = list(sweeps)
    sweep_grid(config.loops, sweeps)
    def scans(n: int, k: int) -> None:
        if progress is not None and n % 500 == 0:
            progress(f"front end: {n} scans, {k} keyframes")

    rec = record_front_end(frames, config, scans)
    if progress is not None:
        progress(f"front end: {len(rec.stamps)} scans, {len(rec.keyframes)} keyframes, {rec.time_s:.1f} s")
    return sweep_recorded(rec, config, sweeps, relations=relations, revisit_radius=revisit_radius,
                          min_separation=min_separation, progress=progress, map_fn=map_fn)


def _sequential_map(fn: Callable[..., Any], shared: tuple, items: Sequence[tuple],
                    on_done: Callable[[int, Any], None] | None = None) -> list:
    """The default :data:`MapFn`: one call after another in this process."""
    out = []
    for i, item in enumerate(items):
        out.append(fn(*shared, *item))
        if on_done is not None:
            on_done(i, out[-1])
    return out


def sweep_recorded(
    rec,  # slam.pipeline.loop_replay.FrontEndRecord
    config: SlamConfig,
    sweeps: Iterable[Sweep] = (),
    *,
    relations=None,  # evaluation.relations.Relations
    revisit_radius: float = 1.0,
    min_separation: int | None = None,
    progress: Callable[[str], None] | None = None,
    map_fn: MapFn | None = None,
) -> SweepResult:
    """Replay loop closure over a recorded front end for every grid point and score it (module docstring).

    Args:
        rec: :class:`~slam.pipeline.loop_replay.FrontEndRecord`; ground-truth scoring when it has ground truth.
        config: base configuration (its ``loops`` is the grid's base, its ``backend`` solves every setting).
        relations: Kümmerle relations to score each setting's trajectory with, or None.
        revisit_radius: true distance [m] under which two keyframes see the same place (ground truth only).
        min_separation: smallest keyframe-id gap of a true revisit; default the base config's
            ``exclude_recent_keyframes + 1`` (closer pairs are never candidates). Fixed over the grid,
            so recall has the same denominator in every row.
        progress: called with a one-line message after each setting.
        map_fn: runs :func:`score_setting` over the grid (:data:`MapFn`); default one after another here.
            ``slam loops --parallel`` passes the Ray executor's; the rows are the same either way.
    """
    sweeps = list(sweeps)
    grid = sweep_grid(config.loops, sweeps)
    gt_kf = rec.keyframe_ground_truth
    sep = config.loops.exclude_recent_keyframes + 1 if min_separation is None else int(min_separation)
    names = [s.name for s in sweeps]
    cols = names + list(COLUMNS_TRUTH if gt_kf is not None else COLUMNS_SELF)
    if relations is not None:
        cols += list(COLUMNS_RELATIONS)

    def done(_: int, scored: tuple[dict[str, object], tuple[int, int] | None]) -> None:
        if progress is not None:
            progress("  ".join(f"{c}={_fmt(scored[0][c])}" for c in cols))

    shared = (rec, config.backend, relations, revisit_radius, sep)
    scored = (map_fn or _sequential_map)(score_setting, shared, [(setting, loop_cfg) for setting, loop_cfg in grid],
                                         done)
    rows = [{c: _nan_to_none(row[c]) for c in cols} for row, _ in scored]
    relations_used = scored[-1][1] if scored else None  # the same stamps in every row
    meta = {
        "scans": int(len(rec.stamps)), "keyframes": len(rec.keyframes), "dimension": 2 if rec.planar else 3,
        "ground_truth": gt_kf is not None, "front_end_time_s": rec.time_s,
        "sweeps": {s.name: list(s.values) for s in sweeps},
        "scoring": ({"kind": "ground truth", "revisit_radius_m": revisit_radius, "min_separation": sep}
                    if gt_kf is not None else {"kind": "self-consistency (Hess et al. 2016)"})
        | {"trans_tol_m": TRANS_TOL, "rot_tol_deg": ROT_TOL_DEG,
           "closures": "all accepted by verification, before pruning"},
        "base_loops": config.loops.model_dump(mode="json"),
    }
    if relations_used is not None:
        meta["relations_used"], meta["relations_total"] = relations_used
    return SweepResult(cols, rows, meta)


def score_setting(
    rec,  # slam.pipeline.loop_replay.FrontEndRecord
    backend,  # slam.pipeline.config.BackendConfig
    relations,  # evaluation.relations.Relations | None
    revisit_radius: float,
    min_separation: int,
    setting: dict[str, float | int],
    loop_cfg: LoopConfig,
) -> tuple[dict[str, object], tuple[int, int] | None]:
    """One grid point: replay loop closure and the pose graph with *loop_cfg*, score the accepted closures.

    Returns the row (the swept values, then the columns of the module docstring) and, with *relations*,
    (relations used, relations in the file).
    """
    from .loop_replay import replay_loops

    gt_kf = rec.keyframe_ground_truth
    rep = replay_loops(rec, loop_cfg, backend)
    edges = loop_edges_from_closures(rep.loops)  # keyframe id = node index
    self_score = score_loops(edges, rep.keyframe_poses)
    row: dict[str, object] = dict(setting)
    row["accepted"] = len(edges)
    row["pruned"] = int(rep.stats.get("pruned", 0))
    if gt_kf is not None:
        t = score_against_truth(edges, gt_kf, revisit_radius, min_separation)
        row |= {"true_positive": t.n_true_positive, "false_positive": t.n_loops - t.n_true_positive,
                "precision": t.precision, "revisits_found": t.n_revisit_nodes_found,
                "revisits": t.n_revisit_nodes, "recall": t.recall, "consistent": self_score.n_correct}
    else:
        row |= {"consistent": self_score.n_correct, "precision": self_score.precision}
    row["time_s"] = rep.time_s
    used = None
    if relations is not None:
        from core.trajectory import Trajectory

        from evaluation.relations import evaluate_relations

        res = evaluate_relations(Trajectory(rec.stamps, rec.scan_poses(rep.keyframe_poses)), relations)
        row |= {"relation_trans_mean_m": res.trans_mean, "relation_rot_mean_deg": res.rot_mean_deg}
        used = (res.n_used, res.n_used + res.n_missing)
    return row, used


def _fmt(v: object) -> str:
    if v is None:
        return "nan"
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


#: Files every sweep folder holds: an existing folder with them is an earlier sweep, which a new one replaces.
SWEEP_MARKER = ("loops.csv", "loops.json")


def write_sweep(out_dir, result: SweepResult, extra_meta: dict | None = None) -> None:  # out_dir: str | Path
    """Write ``loops.csv``, ``loops.json`` and ``pr.png`` into *out_dir*, atomically (all or nothing).

    CSV: a header of :attr:`SweepResult.columns`, one line per grid point, missing numbers empty.
    JSON: ``{"columns", "rows", **meta}`` with missing numbers as null. The plot is precision against
    recall with ground truth, against the number of accepted closures without.
    """
    import csv
    import json

    from core.atomic import atomic_directory

    from evaluation.plots import sweep_png

    meta = result.meta | (extra_meta or {})
    with atomic_directory(out_dir, SWEEP_MARKER) as tmp:
        with open(tmp / "loops.csv", "w", newline="", encoding="utf-8") as fh:
            w = csv.writer(fh)
            w.writerow(result.columns)
            for row in result.rows:
                w.writerow(["" if row[c] is None else (repr(row[c]) if isinstance(row[c], float) else row[c])
                            for c in result.columns])
        with open(tmp / "loops.json", "w", encoding="utf-8") as fh:
            json.dump(meta | {"columns": result.columns, "rows": result.rows}, fh, indent=2)
            fh.write("\n")
        swept = list(meta.get("sweeps", {}))
        name = Path(str(meta.get("log", "the log"))).name
        x = "recall" if result.has_truth else "accepted"
        xlabel = "recall (true-revisit keyframes closed)" if result.has_truth else "accepted closures"
        ylabel = ("precision (agrees with ground truth, 20 cm / 1°)" if result.has_truth
                  else "precision (consistent after optimisation, 20 cm / 1°)")
        (tmp / "pr.png").write_bytes(sweep_png(result.rows, swept, x, "precision", xlabel, ylabel,
                                               title=f"Loop closure on {name}, {len(result.rows)} settings"))
