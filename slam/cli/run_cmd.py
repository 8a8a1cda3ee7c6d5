"""``slam run LOG``: the end-to-end SLAM pipeline on a robot log, with all outputs in one folder."""

from __future__ import annotations

from pathlib import Path

import typer


def _config(config: Path | None, overrides: dict):  # type: ignore[no-untyped-def]
    from slam.pipeline.config import SlamConfig

    cfg = SlamConfig.from_yaml(config) if config is not None else SlamConfig()
    data = cfg.model_dump()
    for path, value in overrides.items():
        if value is None:
            continue
        node = data
        keys = path.split(".")
        for k in keys[:-1]:
            node = node[k]
        node[keys[-1]] = value
    return SlamConfig.model_validate(data)


def run_log(log: Path, out: Path, cfg, topic: str | None = None, quiet: bool = False) -> dict:  # type: ignore[no-untyped-def]
    """Run the pipeline on *log*, write the outputs into *out*, return the summary dict."""
    import resource
    import time

    from slam.logs import open_log
    from slam.pipeline.outputs import write_outputs
    from slam.pipeline.run import run_slam

    reader = open_log(log, topic)
    t0 = time.perf_counter()
    if quiet:
        result = run_slam(reader.frames(), cfg)
    else:
        from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

        total = reader.info().scans if cfg.max_scans is None else None
        if cfg.max_scans is not None:
            total = cfg.max_scans
        with Progress(TextColumn("[bold]slam run"), BarColumn(), TextColumn("{task.completed}/{task.total} scans"),
                      TextColumn("{task.fields[rate]:.0f} scans/s  keyframes {task.fields[kf]}  closures {task.fields[lc]}"),
                      TimeElapsedColumn(), transient=True) as bar:
            task = bar.add_task("run", total=total, rate=0.0, kf=0, lc=0)

            def progress(p):  # type: ignore[no-untyped-def]
                if p.scans % 25 == 0:
                    bar.update(task, completed=p.scans, rate=p.scans / max(p.elapsed_s, 1e-9), kf=p.keyframes,
                               lc=p.loop_closures)

            result = run_slam(reader.frames(), cfg, progress)
    wall_run = time.perf_counter() - t0
    n = len(result.stamps)
    summary = {
        "log": str(log),
        "scans": n,
        "keyframes": len(result.keyframes),
        "loop_closures": len(result.loops) - result.loop_stats.get("pruned", 0),
        "loop_stats": result.loop_stats,
        "dimension": 2 if result.planar else 3,
        "stage_times_s": result.stage_times_s,
        "map_scans_fused": result.map_builder.scans_fused if result.map_builder else 0,
    }
    t1 = time.perf_counter()
    write_outputs(out, result, result.occupancy_map, cfg, summary | {"wall_time_s": None})
    wall = time.perf_counter() - t0
    summary["stage_times_s"]["outputs_s"] = time.perf_counter() - t1
    summary["wall_time_s"] = wall
    summary["scans_per_second"] = n / wall_run if wall_run > 0 else 0.0
    summary["peak_memory_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    # Rewrite the summary with the final wall time (a single small atomic file).
    import json

    from registration.atomic import atomic_open

    full = json.loads((out / "summary.json").read_text())
    full.update(summary)
    with atomic_open(out / "summary.json") as fh:
        json.dump(full, fh, indent=2, default=float)
    return summary


def run(
    log: Path = typer.Argument(..., help="Robot log: CARMEN .clf/.log[.bz2|.gz], MCAP, ROS 1 bag or KITTI sequence."),
    out: Path = typer.Option(Path("out/run"), "--out", help="Output folder (written atomically)."),
    config: Path | None = typer.Option(None, "--config", help="YAML configuration (see config.yaml of any run)."),
    odometry: str | None = typer.Option(None, "--odometry", help="auto (default: KISS-ICP for 3D, our ICP for 2D), kiss or icp."),
    backend: str | None = typer.Option(None, "--backend", help="gtsam (iSAM2 + batch LM) or chordal (batch)."),
    map_method: str | None = typer.Option(None, "--map", help="fastgpom, gpom, logodds or none."),
    topic: str | None = typer.Option(None, "--topic", help="Sensor topic (MCAP / ROS 1)."),
    max_scans: int | None = typer.Option(None, "--max-scans", help="Stop after this many scans."),
    quiet: bool = typer.Option(False, "--quiet", help="No progress bar."),
) -> None:
    """Run SLAM on LOG: odometry, keyframes, verified loop closures, pose graph, Fast-GPOM map, all outputs."""
    overrides = {"odometry.method": odometry, "backend.kind": backend, "max_scans": max_scans}
    if map_method is not None:
        overrides["mapping.enabled"] = map_method != "none"
        if map_method != "none":
            overrides["mapping.params.method"] = map_method
    cfg = _config(config, overrides)
    s = run_log(log, out, cfg, topic, quiet)
    typer.echo(f"scans: {s['scans']}")
    typer.echo(f"keyframes: {s['keyframes']}")
    typer.echo(f"loop_closures: {s['loop_closures']}")
    typer.echo(f"wall_time_s: {s['wall_time_s']:.2f}")
    typer.echo(f"results: {out.resolve()}")


def register(app: typer.Typer, eval_app: typer.Typer) -> None:
    app.command("run")(run)
