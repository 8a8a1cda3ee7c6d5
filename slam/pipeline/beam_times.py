"""Which way a log's beam times run, read from its first scans before the run.

A log's beam times (ROS ``time_increment``, or ``odometry.laser_revolution_s``) are trusted only as far as
its scans bear them out (:mod:`registration.sweep_check`: some drivers list a clockwise mirror's beams
against the order it took them). Read while the run goes, the first scans would be registered, closed
into loops and mapped undeskewed and the later ones deskewed, and a return to the start would compare
the two (simulated URG-04LX tours: docs/ODOMETRY.md). So the frame loop first registers the log's opening
scans on their own (odometry only, nothing kept) until the check decides, at most ``LIMIT_SCANS``, and
the run proper then starts with the reading fixed: deskewed as listed or reversed, or not deskewed (also
when the scans have not decided by then). A log without beam times costs nothing here: its first frame
says so.
"""

from __future__ import annotations

import dataclasses
from typing import Iterator

from core import interrupts
from core.frame import Frame
from registration.deskew import sweep_times
from registration.sweep_check import SweepCheck

from .config import OdometryStageConfig, SlamConfig
from .odometry_source import make_odometry

__all__ = ["LIMIT_SCANS", "timed_frame", "read_beam_time_order"]

#: scans registered at most before the run to read the beam times' order (undecided by then: not deskewed)
LIMIT_SCANS = 1500


def timed_frame(frame: Frame, c: OdometryStageConfig) -> Frame | None:
    """*frame* with its beam times (the log's, or ``laser_revolution_s``'s) when it is to be deskewed, else None."""
    if not (c.deskew and frame.is_planar and frame.angles is not None):
        return None
    if frame.beam_times is None and c.laser_revolution_s is not None:
        return dataclasses.replace(frame, beam_times=sweep_times(frame.angles, c.laser_revolution_s))
    return frame if frame.beam_times is not None else None


def read_beam_time_order(frames: Iterator[Frame], config: SlamConfig) -> tuple[SlamConfig, list[Frame], dict]:
    """With ``odometry.beam_time_order`` ``auto`` and a log whose scans carry beam times: register its first
    scans (taken from *frames*) until the sweep check decides, and return the configuration with the
    reading fixed (``beam_time_order`` listed / reversed, or ``deskew`` off), the frames read (to be fed
    again) and what the check saw (for ``summary.json``). Otherwise the configuration as it is, and at
    most the one frame read."""
    c = config.odometry
    if not c.deskew or c.beam_time_order != "auto":
        return config, [], {}
    head: list[Frame] = []
    limit = min(LIMIT_SCANS, config.max_scans or LIMIT_SCANS)
    check, odometry = SweepCheck(), None
    for frame in frames:
        interrupts.check()
        head.append(frame)
        timed = timed_frame(frame, c)
        if timed is None:
            return config, head, {}
        if odometry is None:
            odometry = make_odometry(config, planar=True)
        step = odometry.update(frame)
        if check.add(timed, step.world_T_sensor) is not None or len(head) >= limit:
            break
    if check.verdict is None:
        check.verdict = "none"  # the scans did not bear the times out within the limit: no deskewing
    stats = {"beam_times": check.verdict, "beam_time_pairs": check.pairs,
             "beam_time_scans_read": check.scans,
             "beam_time_costs_m": {k: round(v / max(check.pairs, 1), 5) for k, v in check.costs.items()}}
    if check.verdict == "none":
        config = config.model_copy(update={"odometry": c.model_copy(update={"deskew": False})})
    else:
        config = config.model_copy(update={"odometry": c.model_copy(update={"beam_time_order": check.verdict})})
    return config, head, stats
