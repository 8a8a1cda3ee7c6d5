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
both included; integer fields are rounded); several sweeps form their cartesian product.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable

import numpy as np
from pydantic import ValidationError

from registration.errors import ConfigError
from slam.pipeline.config import LoopConfig, SlamConfig

from .loops import ROT_TOL_DEG, TRANS_TOL, LoopEdges, score_against_truth, score_loops

__all__ = ["Sweep", "SweepResult", "parse_sweep", "sweep_grid", "run_loop_sweep", "sweep_recorded", "write_sweep",
           "COLUMNS_TRUTH", "COLUMNS_SELF", "COLUMNS_RELATIONS"]

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


def _sweepable() -> dict[str, type]:
    """LoopConfig fields a sweep may vary: the int and float ones, optional (None = off) or not."""
    out = {}
    for name, f in LoopConfig.model_fields.items():
        for kind in (int, float):
            if f.annotation in (kind, kind | None):
                out[name] = kind
    return out


def parse_sweep(text: str) -> Sweep:
    """``NAME=start:stop:count`` → :class:`Sweep`; ConfigError (one line) for anything malformed.

    Values are checked against the field's constraints by :func:`sweep_grid`.
    """
    fields = _sweepable()
    name, eq, spec = text.partition("=")
    name = name.strip()
    if not eq or not name:
        raise ConfigError(f"--sweep {text!r}: expected NAME=start:stop:count")
    if name not in fields:
        kind = "is not a numeric loop setting" if name in LoopConfig.model_fields else "is not a loop setting"
        raise ConfigError(f"--sweep {text!r}: {name!r} {kind}; sweepable: {', '.join(sorted(fields))}")
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


def sweep_grid(base: LoopConfig, sweeps: Iterable[Sweep]) -> list[tuple[dict[str, float | int], LoopConfig]]:
    """Cartesian product of *sweeps* over *base*: ``(swept values, LoopConfig)`` per grid point, first sweep slowest.

    Without sweeps: the base setting alone. ConfigError for a field swept twice or a value the model rejects.
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
        try:
            cfg = LoopConfig.model_validate(data | setting)
        except ValidationError as exc:
            err = exc.errors()[0]
            where = ".".join(str(p) for p in err["loc"])
            raise ConfigError(f"--sweep {where}={setting.get(where, '?')}: {err['msg']}") from None
        grid.append((setting, cfg))
    return grid


def _loop_edges(replay) -> LoopEdges:  # replay: slam.pipeline.loop_replay.LoopReplay
    """Every accepted closure as :class:`LoopEdges` (keyframe id = node index)."""
    L = replay.loops
    return LoopEdges(np.array([lc.i for lc in L], np.int64), np.array([lc.j for lc in L], np.int64),
                     np.array([lc.measurement for lc in L], float).reshape(-1, 4, 4))


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
) -> SweepResult:
    """Record the front end over *frames* once (``config.max_scans`` honoured), then :func:`sweep_recorded`.

    The grid is validated before the log is read. *progress* is called with a one-line message after
    the front end and after each setting.
    """
    from slam.pipeline.loop_replay import record_front_end

    sweeps = list(sweeps)
    sweep_grid(config.loops, sweeps)
    def scans(n: int, k: int) -> None:
        if progress is not None and n % 500 == 0:
            progress(f"front end: {n} scans, {k} keyframes")

    rec = record_front_end(frames, config, scans)
    if progress is not None:
        progress(f"front end: {len(rec.stamps)} scans, {len(rec.keyframes)} keyframes, {rec.time_s:.1f} s")
    return sweep_recorded(rec, config, sweeps, relations=relations, revisit_radius=revisit_radius,
                          min_separation=min_separation, progress=progress)


def sweep_recorded(
    rec,  # slam.pipeline.loop_replay.FrontEndRecord
    config: SlamConfig,
    sweeps: Iterable[Sweep] = (),
    *,
    relations=None,  # evaluation.relations.Relations
    revisit_radius: float = 1.0,
    min_separation: int | None = None,
    progress: Callable[[str], None] | None = None,
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
    """
    from slam.pipeline.loop_replay import replay_loops

    sweeps = list(sweeps)
    grid = sweep_grid(config.loops, sweeps)
    gt_kf = rec.keyframe_ground_truth
    sep = config.loops.exclude_recent_keyframes + 1 if min_separation is None else int(min_separation)
    names = [s.name for s in sweeps]
    cols = names + list(COLUMNS_TRUTH if gt_kf is not None else COLUMNS_SELF)
    if relations is not None:
        cols += list(COLUMNS_RELATIONS)
    rows: list[dict[str, object]] = []
    relations_used: tuple[int, int] | None = None
    for setting, loop_cfg in grid:
        rep = replay_loops(rec, loop_cfg, config.backend)
        edges = _loop_edges(rep)
        self_score = score_loops(edges, rep.keyframe_poses)
        row: dict[str, object] = dict(setting)
        row["accepted"] = len(edges)
        row["pruned"] = int(rep.stats.get("pruned", 0))
        if gt_kf is not None:
            t = score_against_truth(edges, gt_kf, revisit_radius, sep)
            row |= {"true_positive": t.n_true_positive, "false_positive": t.n_loops - t.n_true_positive,
                    "precision": t.precision, "revisits_found": t.n_revisit_nodes_found,
                    "revisits": t.n_revisit_nodes, "recall": t.recall, "consistent": self_score.n_correct}
        else:
            row |= {"consistent": self_score.n_correct, "precision": self_score.precision}
        row["time_s"] = rep.time_s
        if relations is not None:
            from slam.trajectory_io import Trajectory

            from .relations import evaluate_relations

            res = evaluate_relations(Trajectory(rec.stamps, rec.scan_poses(rep.keyframe_poses)), relations)
            row |= {"relation_trans_mean_m": res.trans_mean, "relation_rot_mean_deg": res.rot_mean_deg}
            relations_used = (res.n_used, res.n_used + res.n_missing)  # the same stamps in every row
        rows.append({c: _nan_to_none(row[c]) for c in cols})
        if progress is not None:
            progress("  ".join(f"{c}={_fmt(row[c])}" for c in cols))
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


def _fmt(v: object) -> str:
    if v is None:
        return "nan"
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


def write_sweep(out_dir, result: SweepResult, extra_meta: dict | None = None) -> None:  # out_dir: str | Path
    """Write ``loops.csv``, ``loops.json`` and ``pr.png`` into *out_dir*, atomically (all or nothing).

    CSV: a header of :attr:`SweepResult.columns`, one line per grid point, missing numbers empty.
    JSON: ``{"columns", "rows", **meta}`` with missing numbers as null. The plot is precision against
    recall with ground truth, against the number of accepted closures without.
    """
    import csv
    import json

    from registration.atomic import atomic_directory

    from .plots import sweep_png

    meta = result.meta | (extra_meta or {})
    with atomic_directory(out_dir) as tmp:
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
