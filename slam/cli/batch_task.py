"""One run of ``slam batch`` inside a Ray worker: the ``slam run`` code path for one log × setting.

:func:`run_job` calls :func:`slam.cli.run_cmd.run_log` (what ``slam run LOG --eval`` runs, quietly) into a
staging folder beside the run's final place (``.<setting>.*.part``), adds ``batch.json`` (the log's
content hash, the config hash and the run's table row, :mod:`slam.batch.fingerprint`), and only then
moves the complete folder into place, replacing an older one; Ctrl-C (the executor's cancel) and
errors remove the staging folder. So a run folder is always complete.

The stage child processes are off inside a task of one CPU (``--cpus-per-run 1``, the default): Ray
counts one process per task. With two or more CPUs per task the configured ``stage_processes`` stand
(odometry and mapping each in their own process, as ``slam run`` does on a 2-core machine); the
results are the same either way.

Peak memory: a Ray worker runs many tasks, so its lifetime peak (``ru_maxrss``) is not the run's. The
peak resident size is reset before the run (Linux ``/proc/self/clear_refs``, value 5) and read after
it (``VmHWM``, when ``summary.json`` is written); the summary and the row get that, plus the stage
processes' own peaks.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any

from core.atomic import sigint_deferred
from core.errors import GpslamError, InputFileError
from evaluation.batch_report import RESULT_KEYS
from slam.batch.fingerprint import BATCH_FILE
from slam.batch.spec import Job

__all__ = ["run_job", "failed_row"]


def _row(job: Job, **kw: Any) -> dict[str, Any]:
    """A row with the keys of :data:`evaluation.batch_report.RESULT_KEYS`."""
    row = dict.fromkeys(RESULT_KEYS)
    row |= {"log": job.log_name, "setting": job.setting, "values": dict(job.values), "log_path": job.log,
            "resumed": False}
    row |= kw
    return row


def failed_row(job: Job, message: str) -> dict[str, Any]:
    """The row of a run that failed: ``status`` is ``failed: <one line>``."""
    return _row(job, status="failed: " + " ".join(str(message).split()))


def _reset_peak_rss() -> bool:
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
        return True
    except OSError:
        return False


def _peak_rss_mb() -> float | None:
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return float(line.split()[1]) / 1024.0
    except (OSError, ValueError, IndexError):
        pass
    return None


def _reference(job: Job):  # type: ignore[no-untyped-def]
    """What ``slam run --eval`` would evaluate against: the job's files, else what is found beside or in the log."""
    from slam.logs import open_log

    from .run_eval import find_reference

    log = Path(job.log)
    reader = open_log(log, job.topic)
    given = (Path(job.relations) if job.relations else None, Path(job.gt) if job.gt else None)
    if any(given):
        return find_reference(log, reader, *given)
    try:
        return find_reference(log, reader)
    except InputFileError:  # nothing beside the log and no ground truth in it: a run without evaluation
        return None


def _loop_precision(folder: Path, pruned: int) -> float | None:
    """Cartographer's 20 cm / 1° precision over every closure the verifier accepted, the pruned ones counting
    as violated (the report's ``precision_counting_pruned``), from ``graph.g2o``."""
    from evaluation.loops import loop_edges_from_graph, score_loops
    from slam.graph import read_graph

    graph = read_graph(folder / "graph.g2o")
    if not graph.has_initial_guess:
        return None
    s = score_loops(loop_edges_from_graph(graph), graph.poses)
    total = s.n_loops + pruned
    return s.n_correct / total if total else None


def _finish_row(job: Job, folder: Path) -> dict[str, Any]:
    """The run's table row, from its ``summary.json`` and ``metrics.json``."""
    import hashlib

    from core.run_summary import read_run_summary

    s = read_run_summary(folder / "summary.json").model_dump()
    metrics = json.loads((folder / "metrics.json").read_text()) if (folder / "metrics.json").is_file() else {}
    rel = metrics.get("relations") or {}
    est = rel.get("estimate") or {}
    cart = (rel.get("published") or {}).get("cartographer") or {}
    ape = (metrics.get("ape_trans_m") or {}).get("estimate") or {}
    pruned = int((s.get("loop_stats") or {}).get("pruned", 0))
    sc = s.get("self_check") or {}
    return _row(
        job, status="ok",
        relation_trans_mean_m=est.get("trans_mean") if est.get("n_used") else None,
        relation_rot_mean_deg=est.get("rot_mean_deg") if est.get("n_used") else None,
        relations_used=est.get("n_used"),
        cartographer_trans_mean_m=(cart.get("trans") or {}).get("mean"),
        cartographer_rot_mean_deg=(cart.get("rot") or {}).get("mean"),
        ape_rmse_m=ape.get("rmse"),
        loops_accepted=int(s["loop_closures"]) + pruned, loops_pruned=pruned,
        loop_precision=_loop_precision(folder, pruned),
        self_check=sc.get("verdict"),
        self_check_contradicting=(f"{sc['keyframes_contradicting']} / {sc['keyframes_checked']}"
                                  if "keyframes_checked" in sc else None),
        scans=s["scans"], keyframes=s["keyframes"], wall_time_s=s["wall_time_s"], peak_memory_mb=s["peak_memory_mb"],
        run_dir=str(Path(job.out)),
        trajectory_sha256=hashlib.sha256((folder / "trajectory.tum").read_bytes()).hexdigest())


def run_job(job: Job) -> dict[str, Any]:
    """Run *job* (module docstring) and return its row; a failure is the row's ``status``, not an exception.

    KeyboardInterrupt (the executor's cancel) is not caught: the staging folder is removed and it goes on.
    """
    from slam.pipeline.config import SlamConfig

    from .run_cmd import run_log

    final = Path(job.out)
    try:
        cfg = SlamConfig.model_validate(job.config)
        if job.cpus_per_run < 2:
            cfg = cfg.model_copy(update={"stage_processes": False})
        reference = _reference(job)
        final.parent.mkdir(parents=True, exist_ok=True)
        staging = Path(tempfile.mkdtemp(prefix=f".{final.name}.", suffix=".part", dir=final.parent))
    except GpslamError as exc:
        return failed_row(job, str(exc))
    except Exception as exc:  # noqa: BLE001 — every failure is the row's, in one line
        return failed_row(job, f"{type(exc).__name__}: {exc}")
    try:
        run = staging / "run"
        measured = _reset_peak_rss()
        run_log(Path(job.log), run, cfg, job.topic, quiet=True, reference=reference,
                peak_main_mb=_peak_rss_mb if measured else None)
        row = _finish_row(job, run)
        doc = {"log": job.log, "log_sha256": job.log_sha256, "config_sha256": job.config_sha256, "row": row}
        (run / BATCH_FILE).write_text(json.dumps(doc, indent=2, default=float) + "\n")
        with sigint_deferred():
            if final.exists():
                os.rename(final, staging / "previous")
            os.rename(run, final)
        return row
    except GpslamError as exc:
        return failed_row(job, str(exc))
    except MemoryError:
        return failed_row(job, f"{job.log}: out of memory")
    except Exception as exc:  # noqa: BLE001
        return failed_row(job, f"{type(exc).__name__}: {exc}")
    finally:
        with sigint_deferred():
            shutil.rmtree(staging, ignore_errors=True)
