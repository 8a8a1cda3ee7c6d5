"""``slam batch SPEC.yaml --out DIR``: many logs × many settings, each run a Ray task.

The short form ``slam batch LOG... --out DIR [--sweep NAME=start:stop:count ...] [--config FILE]`` is a
spec without a file. The batch (:mod:`slam.batch.spec`) is checked whole before anything runs; every
run is :func:`slam.cli.batch_task.run_job` (the ``slam run --eval`` code path) in a Ray task of
``--cpus-per-run`` CPUs (:mod:`slam.batch.executor`: a local Ray by default, ``--address`` for a
cluster), writing ``DIR/runs/<log>/<setting>/`` atomically. Then ``results.csv``, ``results.json``,
``results.md`` and ``report.html`` (:mod:`evaluation.batch_report`). A failed run is its row's
``failed: …`` and the exit status 1; the others finish. With ``--resume`` (the default) a run whose
folder holds a complete result for the same log content, config and code hash is not run again. Ctrl-C
cancels the outstanding runs and keeps the finished ones; no staging folder is left behind.
"""

from __future__ import annotations

import shutil
import time
from pathlib import Path

import typer

_SPEC_SUFFIXES = (".yaml", ".yml")


def _remove_staging(jobs, out: Path, out_existed: bool) -> None:  # type: ignore[no-untyped-def]
    """Delete what runs interrupted while writing left behind: ``.<setting>.*.part`` beside each run folder,
    then the folders the batch created that stayed empty (``runs/<log>/``, ``runs/``, ``--out``)."""
    from core.atomic import sigint_deferred

    with sigint_deferred():
        parents = dict.fromkeys(Path(job.out).parent for job in jobs)
        for job in jobs:
            final = Path(job.out)
            if final.parent.is_dir():
                for p in final.parent.glob(f".{final.name}.*.part"):
                    shutil.rmtree(p, ignore_errors=True)
        for d in [*parents, out / "runs", *([] if out_existed else [out])]:
            try:
                d.rmdir()  # only when empty
            except OSError:
                pass


def _line(row: dict) -> str:
    """One line about a finished run for the console."""
    parts = [f"{row['log']} / {row['setting']}: {row['status']}"]
    if row.get("relation_trans_mean_m") is not None:
        parts.append(f"relations {row['relation_trans_mean_m']:.4f} m")
    if row.get("ape_rmse_m") is not None:
        parts.append(f"APE {row['ape_rmse_m']:.4f} m")
    if row.get("wall_time_s") is not None:
        parts.append(f"{row['wall_time_s']:.1f} s")
    return "  ".join(parts)


def batch(
    inputs: list[str] = typer.Argument(..., metavar="SPEC.yaml | LOG...",
                                       help="A batch spec (YAML: logs, config, sweep, settings; see examples/), or "
                                            "logs (paths or globs) for the short form."),
    out: Path = typer.Option(..., "--out", help="Batch folder: runs/<log>/<setting>/, results.csv/.json/.md, report.html."),
    sweep: list[str] = typer.Option([], "--sweep", help="Short form: NAME=start:stop:count (as slam loops; a dotted "
                                    "name such as odometry.icp_2d.icp.tol_translation_m for any numeric config value); repeat for a grid."),
    config: Path | None = typer.Option(None, "--config", help="Short form: the base YAML configuration."),
    address: str | None = typer.Option(None, "--address", help="A running Ray cluster (auto, HOST:6379 or "
                                       "ray://HOST:10001); default: a local Ray started for this batch and stopped after."),
    cpus_per_run: float = typer.Option(1.0, "--cpus-per-run", help="CPUs Ray reserves per run. With 1 the stage "
                                       "processes are off inside a run; with 2 or more they run as configured."),
    resume: bool = typer.Option(True, "--resume/--no-resume", help="Skip runs whose folder holds a complete result "
                                "for the same log content, config and code (the installed packages' sources)."),
    quiet: bool = typer.Option(False, "--quiet", help="No progress bar, no line per run; only the final table."),
) -> None:
    """Run SLAM over many logs × many settings, each run a Ray task; one table and report for them all."""
    from core.atomic import check_output_file
    from core.errors import ConfigError
    from evaluation.batch_report import flat_rows, markdown_table, write_results
    from slam.batch.fingerprint import completed_row
    from slam.batch.spec import load_spec, spec_from_command_line

    from .batch_task import failed_row, run_job
    from .run_eval import log_stem

    t0 = time.perf_counter()
    # Everything the user gave is checked before any work (and before --out exists).
    if not cpus_per_run > 0:
        raise ConfigError(f"--cpus-per-run {cpus_per_run}: must be > 0")
    if out.exists() and not out.is_dir():
        raise ConfigError(f"--out {out}: exists and is not a folder")
    check_output_file(out / "results.csv")  # --out is a folder files can be created in (issue 27)
    if len(inputs) == 1 and inputs[0].lower().endswith(_SPEC_SUFFIXES):
        if sweep or config is not None:
            raise ConfigError(f"--sweep and --config belong in the spec ({inputs[0]}: sweep:, config:)")
        spec = load_spec(inputs[0], log_stem)
    else:
        spec = spec_from_command_line(inputs, sweep, config, log_stem)
    jobs = spec.jobs(out, cpus_per_run)
    out_existed = out.exists()
    rows: list[dict | None] = [None] * len(jobs)
    todo = []
    for i, job in enumerate(jobs):
        done_row = completed_row(job.out, job.log_sha256, job.config_sha256) if resume else None
        if done_row is not None:
            rows[i] = done_row | {"resumed": True}
        else:
            todo.append(i)
    echo = (lambda msg: None) if quiet else (lambda msg: typer.echo(msg, err=True))  # noqa: E731
    echo(f"batch: {len(spec.logs)} log(s) × {len(spec.settings)} setting(s) = {len(jobs)} runs; "
         f"{len(jobs) - len(todo)} already done (same log and config hash), {len(todo)} to run")
    tasks_run, ray_start_s, ray_stop_s, cluster_cpus = 0, 0.0, 0.0, None
    if todo:
        from slam.batch.executor import RayExecutor, TaskFailure

        finished = 0
        try:
            with RayExecutor(address) as ex:
                ray_start_s, cluster_cpus = ex.start_s, ex.cluster_cpus
                echo(f"ray: {'local instance' if address is None else address}, {cluster_cpus:g} CPUs, "
                     f"{cpus_per_run:g} per run ({ray_start_s:.1f} s to connect)")
                items = [(jobs[i],) for i in todo]
                bar, task = None, None
                if not quiet:
                    from rich.console import Console
                    from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn,
                                               TimeRemainingColumn)

                    bar = Progress(TextColumn("[bold]slam batch"), BarColumn(), MofNCompleteColumn(),
                                   TextColumn("runs  running {task.fields[running]}  failed {task.fields[failed]}  ETA"),
                                   TimeRemainingColumn(), TimeElapsedColumn(), console=Console(stderr=True),
                                   transient=True)
                    task = bar.add_task("runs", total=len(todo), running=0, failed=0)
                    bar.start()
                failed = 0

                def done(k: int, result) -> None:  # type: ignore[no-untyped-def]
                    nonlocal finished, failed
                    i = todo[k]
                    rows[i] = (failed_row(jobs[i], f"{jobs[i].log}: {result.message}") if isinstance(result, TaskFailure)
                               else result)
                    finished += 1
                    failed += rows[i]["status"] != "ok"
                    if bar is not None:
                        bar.console.print(_line(rows[i]))
                        bar.update(task, completed=finished, failed=failed)

                def tick(outstanding: int) -> None:
                    if bar is not None and outstanding:
                        running = min(outstanding, round(ex.busy_cpus() / cpus_per_run))
                        bar.update(task, running=running)

                try:
                    ex.map(run_job, (), items, done, cpus_per_task=cpus_per_run, on_tick=tick)
                finally:
                    if bar is not None:
                        bar.stop()
                tasks_run = ex.submitted
            ray_stop_s = ex.stop_s
        except KeyboardInterrupt:
            typer.echo(f"interrupted: {finished} of {len(todo)} runs finished and kept under {out / 'runs'}; the same "
                       "command resumes the rest", err=True)
            raise
        finally:
            _remove_staging([jobs[i] for i in todo], out, out_existed)
    final_rows = [r for r in rows if r is not None]
    n_failed = sum(1 for r in final_rows if r["status"] != "ok")
    meta = {
        "spec": spec.source, "logs": [str(e.path) for e in spec.logs], "settings": [s.id for s in spec.settings],
        "value_names": spec.value_names, "sweeps": spec.sweeps, "runs": len(final_rows),
        "ok": len(final_rows) - n_failed, "failed": n_failed, "resumed": len(jobs) - len(todo), "tasks_run": tasks_run,
        "address": address or "local", "cpus_per_run": cpus_per_run, "cluster_cpus": cluster_cpus,
        "ray_start_s": ray_start_s, "ray_stop_s": ray_stop_s, "wall_time_s": time.perf_counter() - t0,
    }
    write_results(out, final_rows, spec.value_names, meta)
    typer.echo(markdown_table(flat_rows(final_rows, spec.value_names), spec.value_names), nl=False)
    typer.echo(f"runs: {len(final_rows)} ({meta['ok']} ok, {n_failed} failed, {meta['resumed']} resumed, "
               f"{tasks_run} run as Ray tasks) in {meta['wall_time_s']:.1f} s")
    typer.echo(f"results: {out.resolve()} (results.csv, results.json, results.md, report.html, runs/)")
    if n_failed:
        raise typer.Exit(code=1)


def register(app: typer.Typer, eval_app: typer.Typer) -> None:
    app.command("batch")(batch)
