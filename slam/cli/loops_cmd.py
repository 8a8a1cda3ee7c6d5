"""``slam loops LOG [--sweep NAME=start:stop:count ...]``: loop-closure precision/recall over a parameter grid.

The front end runs once; loop detection, verification and the pose graph run once per setting
(:mod:`slam.pipeline.loop_sweep`). Writes ``loops.csv``, ``loops.json`` and ``pr.png`` into ``--out``.
"""

from __future__ import annotations

from pathlib import Path

import typer

_SUFFIXES = (".bz2", ".gz", ".clf", ".log", ".mcap", ".bag")


def relations_beside(log: Path) -> Path | None:
    """``<stem>.relations`` next to *log*, the stem without its log/compression suffixes, if it exists."""
    name = log.name
    cands = [log.with_name(name + ".relations")]
    while True:
        cut = next((s for s in _SUFFIXES if name.endswith(s) and len(name) > len(s)), None)
        if cut is None:
            break
        name = name[: -len(cut)]
        cands.append(log.with_name(name + ".relations"))
    return next((c for c in reversed(cands) if c.is_file()), None)


def _cell(v: object) -> str:
    if v is None:
        return "nan"
    return f"{v:.4g}" if isinstance(v, float) else str(v)


def loops(
    log: Path = typer.Argument(..., help="Robot log: CARMEN .clf/.log[.bz2|.gz], MCAP, ROS 1 bag or KITTI sequence."),
    sweep: list[str] = typer.Option([], "--sweep", help="NAME=start:stop:count over a numeric loops setting (e.g. "
                                    "min_relative_fitness=0.5:0.8:4); repeat for a grid. Default: the configured setting only."),
    out: Path = typer.Option(Path("out/loops"), "--out", help="Output folder: loops.csv, loops.json, pr.png (atomic; "
                             "an earlier sweep's folder there is replaced whole)."),
    config: Path | None = typer.Option(None, "--config",
                                       help="YAML configuration (its loops section is the grid's base)."),
    relations: Path | None = typer.Option(None, "--relations", help="Kümmerle relations for the relation error "
                                          "(default: <stem>.relations beside the log, if present)."),
    max_scans: int | None = typer.Option(None, "--max-scans", min=1, help="Stop after this many scans."),
    topic: str | None = typer.Option(None, "--topic", help="Sensor topic (MCAP / ROS 1)."),
    quiet: bool = typer.Option(False, "--quiet", help="Only the final table."),
    parallel: bool = typer.Option(False, "--parallel", help="Replay the settings as Ray tasks, one CPU each (the "
                                  "executor of slam batch: a local Ray, or --address); the rows are the same."),
    address: str | None = typer.Option(None, "--address", help="With --parallel: a running Ray cluster (auto, "
                                       "HOST:6379 or ray://HOST:10001); default a local Ray for this command."),
) -> None:
    """Loop closure on LOG under each setting of a grid: precision/recall against ground truth (simulated
    logs) or Cartographer's 20 cm / 1° consistency after optimisation (real logs)."""
    from core.atomic import check_output_dir
    from slam.cli.run_cmd import load_config
    from slam.logs import open_log
    from slam.pipeline.loop_sweep import SWEEP_MARKER, parse_sweep, run_loop_sweep, sweep_grid, write_sweep

    # Everything the user typed is checked before any work (and before --out exists).
    sweeps = [parse_sweep(s) for s in sweep]
    cfg = load_config(config, {"max_scans": max_scans, "mapping.enabled": False})
    check_output_dir(out, SWEEP_MARKER)
    sweep_grid(cfg.loops, sweeps)
    rel_path = relations if relations is not None else relations_beside(log)
    rel = None
    if rel_path is not None:
        from evaluation.relations import read_relations

        rel = read_relations(rel_path)
    reader = open_log(log, topic)

    def progress(msg: str) -> None:
        if not quiet:
            typer.echo(msg, err=True)

    if parallel:
        from functools import partial

        from slam.batch.executor import RayExecutor

        with RayExecutor(address) as ex:
            res = run_loop_sweep(reader.frames(), cfg, sweeps, relations=rel, progress=progress,
                                 map_fn=partial(ex.map, failures="raise"))
    else:
        res = run_loop_sweep(reader.frames(), cfg, sweeps, relations=rel, progress=progress)
    extra = {"log": str(log), "relations": str(rel_path) if rel_path is not None else None}
    write_sweep(out, res, extra)
    typer.echo(f"scans: {res.meta['scans']}  keyframes: {res.meta['keyframes']}  "
               f"front_end_s: {res.meta['front_end_time_s']:.1f}  scoring: {res.meta['scoring']['kind']}")
    typer.echo("\t".join(res.columns))
    for row in res.rows:
        typer.echo("\t".join(_cell(row[c]) for c in res.columns))
    typer.echo(f"results: {out.resolve()} (loops.csv, loops.json, pr.png)")


def register(app: typer.Typer, eval_app: typer.Typer) -> None:
    app.command("loops")(loops)
