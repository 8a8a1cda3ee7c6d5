"""``summary.json`` of a run folder: what ``slam run`` did, written once when the run's files are complete, read
by the evaluation report and by ``slam batch``. One typed record (pydantic), so a writer cannot misspell a key
and a reader gets the types it expects."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, ValidationError

from .errors import MapFormatError

__all__ = ["RunSummary", "read_run_summary"]


class RunSummary(BaseModel):
    """One run of the pipeline over a log."""

    model_config = ConfigDict(extra="forbid")

    log: str  # the log as given
    scans: int  # scans read
    keyframes: int
    loop_closures: int  # accepted and kept by the final solve
    loop_stats: dict[str, Any]  # the loop closer's counters (candidates, rejections by reason, pruned, …)
    odometry_stats: dict[str, Any]  # the front end's counters (alternative starts, wheel edges left out, …)
    self_check: dict[str, Any]  # verdict, contradicting keyframes, violated closures, where
    dimension: Literal[2, 3]
    stage_times_s: dict[str, float]  # wall time per stage (odometry_s, loop_closure_s, …, outputs_s)
    map_scans_fused: int
    on_error: Literal["stop", "skip"]
    skipped_records: int | None  # corrupt records left out; None when a cut stream lost an unknown number
    skipped_scans: int  # the scans among them (at least, unless skipped_scans_exact)
    skipped_scans_exact: bool
    errors: list[str]  # one ``file:pos: what`` line per skip
    wall_time_s: float  # from the first scan read to the last file written
    scans_per_second: float  # scans / the pipeline's own time (reading and SLAM, not the outputs)
    peak_memory_mb: float  # every process's peak resident memory until the outputs are written, summed (the
    # evaluation report, when asked for, comes after)
    peak_memory_by_process_mb: dict[str, float]
    versions: dict[str, str]  # python and the libraries that shape the result
    config: dict[str, Any]  # the whole configuration (the same as config.yaml)
    pruned_closures: list[dict[str, Any]] = []  # the closures the final solve dropped: keyframes i → j, their
    # stamps, the violation (m, °) at the solution it dropped them from, the round; [] in summaries written before
    variance_components: dict[str, Any] | None = None  # the final solve's scales of each edge group's translation and
    # rotation variance, with the redundancy and χ² they were estimated from; None when it did not run (too few closures)
    closure_nees: list[dict[str, Any]] | None = None  # the front end's chains against the run's own closures: NEES/dof
    # per chain length (slam eval nees RUN); None for 3D runs, runs without closures and summaries written before
    chain_model: dict[str, Any] | None = None  # the chains' covariance calibrated by the run's closures: the steps'
    # walk and jitter shares, the long chains they were fitted on, and closure_nees under them (evaluation.chain_model);
    # None where closure_nees is, or with too few long chains
    stamps_not_increasing: int = 0  # scans stamped no later than the scan before (a log's rounded or disordered
    # stamps: the outputs keep them as read); 0 in summaries written before it was counted


def read_run_summary(path: str | Path) -> RunSummary:
    """A run's ``summary.json``; a file that is not one (bad JSON, a missing or unknown key, an older layout)
    is a :class:`MapFormatError` naming it."""
    p = Path(path)
    try:
        return RunSummary.model_validate_json(p.read_bytes())
    except OSError as exc:
        raise MapFormatError(p, None, f"cannot read: {exc.strerror or exc}") from None
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(map(str, first["loc"])) or "(top level)"
        what = "unknown key" if first["type"] == "extra_forbidden" else first["msg"]
        raise MapFormatError(p, None, f"not a run summary of this version: {where}: {what}") from None
