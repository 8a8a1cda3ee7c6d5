"""``slam run LOG``: the end-to-end SLAM pipeline on a robot log, with all outputs in one folder."""

from __future__ import annotations

from enum import Enum
from pathlib import Path
from typing import Callable, Iterator

import typer

from .options import Backend


def load_config(config: Path | None, overrides: dict):  # type: ignore[no-untyped-def]
    """The configuration of a run: *config* (YAML) or the defaults, with the non-None *overrides*
    (``"section.key": value``) applied. Raises ConfigError naming the setting a value does not fit."""
    from pydantic import ValidationError

    from core.errors import ConfigError
    from core.yaml_config import describe_validation_error
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
    try:
        return SlamConfig.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(f"invalid setting: {describe_validation_error(exc)}") from None


class OnError(str, Enum):
    stop = "stop"
    skip = "skip"


class Odometry(str, Enum):
    auto = "auto"
    kiss = "kiss"
    icp = "icp"


class MapMethod(str, Enum):
    fastgpom = "fastgpom"
    gpom = "gpom"
    logodds = "logodds"
    none = "none"


def run_log(log: Path, out: Path, cfg, topic: str | None = None, quiet: bool = False,  # type: ignore[no-untyped-def]
            reference=None, peak_main_mb: Callable[[], float | None] | None = None) -> dict:
    """Run the pipeline on *log*, write the outputs into *out*, return the summary dict.

    ``cfg.on_error``: ``"stop"`` ends the run at the first corrupt record (LogFormatError, nothing
    written); ``"skip"`` leaves corrupt records out, and the summary counts them: ``skipped_records``
    (lines, messages, files; None when a cut stream lost an unknown number), ``skipped_scans`` (the
    scans among them; ``skipped_scans_exact`` false when that is a lower bound) and ``errors`` (one
    ``file:pos: what`` line per skip: a chunk is one). With a *reference*
    (:class:`slam.cli.run_eval.Reference`) the evaluation report is written into *out* too; its
    headline lines are returned under ``"evaluation"``. Every file, the report included, is moved
    into *out* only once all are written. *peak_main_mb* gives this process's peak memory for the summary
    (default: its lifetime peak, ``ru_maxrss``; a batch worker that ran other tasks before measures its own).
    """
    import resource
    import time

    from core.run_summary import RunSummary
    from slam.logs import SkipLog, open_log
    from slam.pipeline.outputs import summarise, write_outputs
    from slam.pipeline.run import run_slam

    from .run_eval import GroundTruthRecorder, write_evaluation

    reader = open_log(log, topic)
    skipped = SkipLog() if cfg.on_error == "skip" else None
    recorder = GroundTruthRecorder() if reference is not None and reference.gt_in_frames else None
    frames = _explain_no_scans(reader.frames(on_skip=skipped), log, skipped)
    if recorder is not None:
        frames = recorder.wrap(frames)
    t0 = time.perf_counter()
    if quiet:
        result = run_slam(frames, cfg)
    else:
        from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

        # The log is read once: the bar's total comes from the log's index when it has one (MCAP, bag, KITTI),
        # else the bar counts without one (a CARMEN text log would have to be read through for it).
        hint = reader.scan_count_hint()
        total = hint if cfg.max_scans is None else (cfg.max_scans if hint is None else min(hint, cfg.max_scans))
        with Progress(TextColumn("[bold]slam run"), BarColumn(), TextColumn("{task.completed}{task.fields[of]} scans"),
                      TextColumn("{task.fields[rate]:.0f} scans/s  keyframes {task.fields[kf]}  closures {task.fields[lc]}"),
                      TimeElapsedColumn(), transient=True) as bar:
            task = bar.add_task("run", total=total, rate=0.0, kf=0, lc=0, of="" if total is None else f"/{total}")

            def progress(p):  # type: ignore[no-untyped-def]
                if p.scans % 25 == 0:
                    bar.update(task, completed=p.scans, rate=p.scans / max(p.elapsed_s, 1e-9), kf=p.keyframes,
                               lc=p.loop_closures)

            result = run_slam(frames, cfg, progress)
            # the final keyframes come when the front end is flushed, after the last update above
            bar.update(task, completed=len(result.stamps), rate=len(result.stamps) / max(time.perf_counter() - t0, 1e-9),
                       kf=len(result.keyframes), lc=_loop_closures(result))
    wall_run = time.perf_counter() - t0
    evaluation: list[str] = []

    written: list[RunSummary] = []

    def summary(outputs_s: float) -> RunSummary:
        # Every process's peak, summed: an upper bound on the memory the run held at any one time.
        peak = peak_main_mb() if peak_main_mb is not None else None
        written.append(summarise(result, str(log), cfg, wall_run, time.perf_counter() - t0, outputs_s,
                                 peak if peak is not None else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
                                 skipped))
        return written[0]

    def evaluate(folder: Path) -> None:
        """The evaluation report, before the move into *out*."""
        if reference is not None:
            evaluation.extend(write_evaluation(folder, reference, recorder, result.stamps, str(out)))

    write_outputs(out, result, result.occupancy_map, cfg, summary, before_commit=evaluate)
    out_summary = written[0].model_dump(mode="json")
    if reference is not None:
        out_summary["evaluation"] = evaluation
    return out_summary


def _loop_closures(result) -> int:  # type: ignore[no-untyped-def]
    """Loop closures the run kept: accepted minus those the back end pruned."""
    return len(result.loops) - result.loop_stats.get("pruned", 0)


def _explain_no_scans(frames, log: Path, skipped) -> Iterator:  # type: ignore[no-untyped-def]
    """*frames*, raising LogFormatError naming *log* when it yields none: every scan was skipped as corrupt
    (then the first skip says why), or the log has none."""
    from core.errors import LogFormatError

    n = 0
    try:
        for f in frames:
            n += 1
            yield f
    finally:
        close = getattr(frames, "close", None)
        if close is not None:
            close()
    if n == 0:
        if skipped:
            raise LogFormatError(log, None, f"no scan could be read: {len(skipped)} corrupt record(s) skipped, "
                                            f"the first: {skipped.lines()[0]}")
        raise LogFormatError(log, None, "the log yielded no scans")


def run(
    log: Path | None = typer.Argument(None, help="Robot log: CARMEN .clf/.log[.bz2|.gz], MCAP, ROS 1 bag or KITTI sequence.",
                                      show_default=False),
    out: Path = typer.Option(Path("out/run"), "--out", help="Output folder (written atomically; an earlier run's "
                             "folder there is replaced whole)."),
    config: Path | None = typer.Option(None, "--config", help="YAML configuration (see config.yaml of any run)."),
    odometry: Odometry | None = typer.Option(None, "--odometry", help="auto (default: our ICP, 2D and 3D), kiss (KISS-ICP) or icp."),
    backend: Backend | None = typer.Option(None, "--backend", help="gtsam (iSAM2 + batch LM) or chordal (batch)."),
    map_method: MapMethod | None = typer.Option(None, "--map", help="fastgpom, gpom, logodds or none."),
    topic: str | None = typer.Option(None, "--topic", help="Sensor topic (MCAP / ROS 1)."),
    max_scans: int | None = typer.Option(None, "--max-scans", min=1, help="Stop after this many scans."),
    on_error: OnError | None = typer.Option(None, "--on-error", help="A corrupt record in the log: stop the run (default; "
                                            "nothing is written) or skip it and count it in summary.json."),
    evaluate: bool = typer.Option(False, "--eval", help="Evaluate the run against <log stem>.relations beside the log "
                                  "or the log's ground truth; writes report.html and metrics.json."),
    relations: Path | None = typer.Option(None, "--relations", help="Relations file to evaluate against (implies --eval)."),
    gt: Path | None = typer.Option(None, "--gt", help="Ground-truth trajectory (TUM/KITTI, or a log with ground truth) "
                                   "to evaluate against (implies --eval)."),
    quiet: bool = typer.Option(False, "--quiet", help="No progress bar."),
    print_config: bool = typer.Option(False, "--print-config", help="Print the whole configuration this run would use "
                                      "(defaults, --config and the options above) as YAML, and exit; it reads back "
                                      "with --config."),
) -> None:
    """Run SLAM on LOG: odometry, keyframes, verified loop closures, pose graph, Fast-GPOM map, all outputs."""
    from core.atomic import check_output_dir
    from slam.pipeline.outputs import RUN_MARKER

    overrides = {"odometry.method": odometry.value if odometry is not None else None,
                 "backend.kind": backend.value if backend is not None else None, "max_scans": max_scans,
                 "on_error": on_error.value if on_error is not None else None}
    if map_method is not None:
        overrides["mapping.enabled"] = map_method is not MapMethod.none
        if map_method is not MapMethod.none:
            overrides["mapping.params.method"] = map_method.value
    cfg = load_config(config, overrides)
    if print_config:
        typer.echo(cfg.to_yaml(), nl=False)
        return
    if log is None:
        raise typer.BadParameter("a log is needed (or --print-config)", param_hint="'LOG'")
    check_output_dir(out, RUN_MARKER)
    reference = None
    if evaluate or relations is not None or gt is not None:
        from slam.logs import open_log

        from .run_eval import find_reference

        reference = find_reference(log, open_log(log, topic), relations, gt)
    typer.echo(f"log: {log}")
    if reference is not None:
        typer.echo(f"evaluate against: {reference.describe()}")
    s = run_log(log, out, cfg, topic, quiet, reference)
    typer.echo(f"scans: {s['scans']}")
    typer.echo(f"keyframes: {s['keyframes']}")
    typer.echo(f"loop_closures: {s['loop_closures']}")
    sc = s.get("self_check") or {}
    if sc:
        t0 = sc.get("start_stamp", 0.0)
        where = "; ".join(f"keyframes {w['first_keyframe']}–{w['last_keyframe']} "
                          f"({w['first_stamp'] - t0:.0f}–{w['last_stamp'] - t0:.0f} s into the log)"
                          for w in sc.get("where", [])[:3])
        # How much could be checked: a map whose passes never overlap in the estimate offers nothing to compare.
        checked = f"{sc.get('keyframes_checked', 0)} of {s['keyframes']} keyframes overlap another pass and were checked"
        if sc.get("keyframes_changed"):  # contradictions no placement explains: not held against the map
            checked += f"; {sc['keyframes_changed']} saw the world changed between passes"
        typer.echo(f"self_check: {sc['verdict']} ({checked}" + (f"; contradictions at {where})" if sc["verdict"] != "consistent" and where else ")"))
    typer.echo(f"wall_time_s: {s['wall_time_s']:.2f}")
    for line in s.get("evaluation", []):
        typer.echo(line)
    if reference is not None:
        typer.echo(f"report: {(out / 'report.html').resolve()}")
    typer.echo(f"results: {out.resolve()}")
    if s.get("stamps_not_increasing"):
        typer.echo(f"warning: {s['stamps_not_increasing']} of {s['scans']} scans of {log} are stamped no later than "
                   "the scan before (the log's stamps are rounded or out of order); the outputs keep them as read", err=True)
    if s["errors"]:
        recs = s["skipped_records"] if s["skipped_records"] is not None else "an unknown number of"
        n = s["skipped_scans"]
        scans = f"{'' if s['skipped_scans_exact'] else 'at least '}{n} scan{'' if n == 1 else 's'}"
        typer.echo(f"warning: skipped {recs} corrupt record(s) ({scans}) of {log}, listed under 'errors' in "
                   f"summary.json; the first: {s['errors'][0]}", err=True)


def register(app: typer.Typer, eval_app: typer.Typer) -> None:
    app.command("run")(run)
