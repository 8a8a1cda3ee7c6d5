"""``slam run --eval``: find a run's reference beside its log and write the evaluation report.

References, in this order of preference:

* given on the command line: ``--relations FILE`` (Kümmerle et al. 2009 relations) and/or
  ``--gt FILE`` (a TUM/KITTI trajectory, or a log whose frames carry ground truth); they
  replace the search;
* found beside the log: ``<stem>.relations`` (``logs/floor2.clf.bz2`` → ``logs/floor2.relations``);
* in the log itself: the ground-truth pose of each frame (simulated MCAP logs, KITTI sequences
  with ``poses/NN.txt``), recorded while the run streams the frames (no second pass), written as
  ``ground_truth.tum`` into the run folder; a simulated log's ground-truth map
  ``<stem>_map.yaml`` beside it is used for the map ROC when present.

The report itself is :func:`evaluation.report.write_report` (the one ``slam eval report`` writes):
``report.html`` and ``metrics.json`` in the run folder.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Iterator

import numpy as np

from core.errors import InputFileError
from core.frame import Frame

_COMPRESSED = (".bz2", ".gz")
_LOG_SUFFIXES = (".clf", ".log", ".carmen", ".txt", ".mcap", ".bag", ".bin")


def log_stem(log: Path) -> str:
    """The log's name without compression and format suffixes: ``floor2.clf.bz2`` → ``floor2``."""
    name = log.name
    for suffix in _COMPRESSED:
        if name.lower().endswith(suffix):
            name = name[: -len(suffix)]
    for suffix in _LOG_SUFFIXES:
        if name.lower().endswith(suffix):
            return name[: -len(suffix)]
    return name


@dataclass
class Reference:
    """What a run is evaluated against."""

    relations: Path | None = None  # Kümmerle relations file
    gt_file: Path | None = None  # ground-truth trajectory file (TUM, KITTI, or a log with ground truth)
    gt_in_frames: bool = False  # the log's frames carry ground truth: record it during the run
    gt_map: Path | None = None  # ground-truth map (map_server YAML), for the map ROC
    given: bool = False  # named on the command line (each must then measure something), not found beside the log

    def describe(self) -> str:
        parts = []
        if self.relations is not None:
            parts.append(f"relations {self.relations}")
        if self.gt_file is not None:
            parts.append(f"ground truth {self.gt_file}")
        if self.gt_in_frames:
            parts.append("ground truth of the log's frames")
        if self.gt_map is not None:
            parts.append(f"ground-truth map {self.gt_map}")
        return ", ".join(parts)


def find_reference(log: Path, reader, relations: Path | None = None,  # type: ignore[no-untyped-def]
                   gt: Path | None = None) -> Reference:
    """The reference to evaluate a run of *log* against (see the module docstring). A relations file, and a
    ground-truth trajectory file that is not a log, are read here, before the run, so that a bad line is
    reported before any work.

    Raises:
        InputFileError: a given file does not exist or is malformed, or nothing was given and nothing found.
    """
    from evaluation.relations import read_relations
    from slam.trajectory_io import LOG_SUFFIXES, read_trajectory

    for given in (relations, gt):
        if given is not None and not Path(given).exists():
            raise InputFileError(given, None, "no such file (given for --eval)")
    if relations is not None:
        read_relations(relations)
    if gt is not None and not Path(gt).is_dir() and not Path(gt).name.lower().endswith(LOG_SUFFIXES):
        read_trajectory(gt)
    if relations is not None or gt is not None:
        return Reference(relations=relations, gt_file=gt, given=True)
    stem = log_stem(log)
    ref = Reference()
    beside = log.parent / f"{stem}.relations"
    if beside.is_file():
        read_relations(beside)
        ref.relations = beside
    if reader.has_ground_truth():
        ref.gt_in_frames = True
        gt_map = log.parent / f"{stem}_map.yaml"
        if gt_map.is_file():
            ref.gt_map = gt_map
    if ref.relations is None and not ref.gt_in_frames:
        raise InputFileError(log, None, f"--eval found no reference: no {beside.name} beside the log and its frames carry "
                                        "no ground truth (give --relations FILE or --gt FILE)")
    return ref


class GroundTruthRecorder:
    """Passes frames through unchanged, keeping the stamp and ``ground_truth`` pose of each."""

    def __init__(self) -> None:
        self.stamps: list[float] = []
        self.poses: list[np.ndarray] = []

    def wrap(self, frames: Iterable[Frame]) -> Iterator[Frame]:
        for f in frames:
            if f.ground_truth is not None:
                self.stamps.append(f.stamp)
                self.poses.append(f.ground_truth)
            yield f

    def trajectory(self, stamps: np.ndarray):  # type: ignore[no-untyped-def]
        """The recorded ground truth at the scans the run used (*stamps*, s), or None."""
        from core.trajectory import Trajectory

        if not self.stamps:
            return None
        st = np.asarray(self.stamps)
        keep = np.isin(st, stamps)
        if not keep.any():
            return None
        return Trajectory(st[keep], np.asarray(self.poses)[keep], "ground truth")


def write_evaluation(folder: Path, ref: Reference, recorder: GroundTruthRecorder | None, scan_stamps: np.ndarray,
                     result_label: str) -> list[str]:
    """Write ``report.html`` and ``metrics.json`` (and ``ground_truth.tum``) into *folder*; return the
    headline lines to print (relation error mean ± std, APE RMSE, map AUC)."""
    from .report_io import write_run_report
    from core.trajectory import write_tum

    gt = ref.gt_file
    if ref.gt_in_frames and recorder is not None:
        traj = recorder.trajectory(scan_stamps)
        if traj is not None:
            gt = folder / "ground_truth.tum"
            write_tum(gt, traj)
    gt_map = ref.gt_map if (folder / "map.npz").exists() else None  # a run without a map (--map none)
    rep = write_run_report(folder, gt, ref.relations, gt_map, folder, result_label=result_label)
    _require_measured(rep.metrics, ref, len(scan_stamps))
    quiet = ("not found", "no ground-truth trajectory")  # informational: what this run does not have
    return headline(rep.metrics) + [f"note: {n}" for n in rep.notes if not any(q in n for q in quiet)]


def _require_measured(metrics: dict, ref: Reference, n_scans: int) -> None:
    """Raise InputFileError when the evaluation measured nothing: a reference named on the command line that
    matches no scan of the run (as ``slam eval relations`` / ``eval ape`` would refuse it), or, for one found
    beside the log, no metric at all. Raised before the outputs are moved into place, so none are."""
    rel = (metrics.get("relations") or {}).get("estimate") or {}
    ape = (metrics.get("ape_trans_m") or {}).get("estimate")
    misses = []
    if ref.relations is not None and not rel.get("n_used"):
        misses.append((ref.relations, f"no relation has both stamps among the {n_scans} scans of the run (within "
                                      f"{rel.get('stamp_tol', 'the')} s): was it written for this log?"))
    if ref.gt_file is not None and ape is None:
        misses.append((ref.gt_file, f"no pose within the association tolerance of the {n_scans} scan stamps of the "
                                    "run: was it written for this log?"))
    measured = bool(rel.get("n_used")) or ape is not None or (metrics.get("map") or {}).get("auc") is not None
    if misses and (ref.given or not measured):
        path, what = misses[0]
        raise InputFileError(path, None, f"{what} Nothing to evaluate; nothing was written")


def headline(metrics: dict) -> list[str]:
    """``key: value`` lines of the main numbers of a report's metrics."""
    lines = []
    rel = (metrics.get("relations") or {}).get("estimate")
    if rel:
        if rel["n_used"]:
            lines.append(f"relations_trans_m: {rel['trans_mean']:.4g} ± {rel['trans_std']:.4g}")
            lines.append(f"relations_rot_deg: {rel['rot_mean_deg']:.4g} ± {rel['rot_std_deg']:.4g}")
        lines.append(f"relations_used: {rel['n_used']} (missing: {rel['n_missing']}, a stamp not among the scans)")
    ape = (metrics.get("ape_trans_m") or {}).get("estimate")
    if ape:
        lines.append(f"ape_rmse_m: {ape['rmse']:.4g} ({ape['pairs']} poses, SE(d)-aligned)")
    auc = (metrics.get("map") or {}).get("auc")
    if auc is not None:
        lines.append(f"map_auc: {auc:.4f}")
    return lines
