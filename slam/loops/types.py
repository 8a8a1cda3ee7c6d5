"""The data that flows between the loop-closure stages.

A :class:`Candidate` (which old keyframe, where the new one should be relative to it and how far off
that may be) goes to the verifier; a :class:`Verified` alignment (pose, covariance, quality) or a
:class:`Rejection` comes back; the acceptance stage turns verified alignments into
:class:`LoopClosure` constraints for the pose graph. Poses are 4×4 ``float64``; an ``i_sensor_T_j_sensor``
is keyframe *j*'s sensor frame in keyframe *i*'s. Covariances are in the tangent order of
:mod:`core.geometry` (translation first), metres and radians.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field, fields
from enum import Enum

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


class Source(str, Enum):
    """Where a candidate came from."""

    SPATIAL = "spatial"  # the estimate puts the keyframes within reach of each other
    DESCRIPTOR = "descriptor"  # the scans look alike (Scan Context)
    GLOBAL = "global"  # the estimate is too uncertain to say where: the old place is searched whole
    HYPOTHESIS = "hypothesis"  # a pending closure of a recent keyframe, followed with the odometry since


class Rejection(str, Enum):
    """Why a verification failed (the name of its counter in :class:`LoopStats`)."""

    DEGENERATE = "rejected_degenerate"  # too few points or pairs for the correlative search or ICP
    SCORE = "rejected_score"  # nothing in the window scores like a match of this scan
    CHI2 = "rejected_chi2"  # the residual χ² test
    FIT = "rejected_fit"  # inlier fraction or RMSE far below the keyframe's own registration
    FREE_SPACE = "rejected_free_space"  # one scan sees through the other's walls
    BACKWARD = "rejected_backward"  # the old scan aligned onto the new keyframe's map disagrees
    AMBIGUOUS = "rejected_ambiguous"  # unvouched and another pose in the window scores almost as well
    INCONSISTENT = "rejected_consistency"  # vouched for, yet beyond the estimate's uncertainty


@dataclass(frozen=True)
class Window:
    """Half-widths of a correlative search around a guess: ± *xy_m* in x and y, ± *theta_rad* in heading."""

    xy_m: float
    theta_rad: float


@dataclass(frozen=True)
class Candidate:
    """A pair of keyframes to verify.

    Attributes:
        i, j: the old keyframe (the candidate place) and the new one.
        source: where it came from.
        guess: ``i_sensor_T_j_sensor`` to start from.
        window: how far the search looks around *guess*.
        estimate: the estimate's ``i_sensor_T_j_sensor`` and its covariance, when the graph has one for
            this pair (the consistency test's reference), else None.
        vouched: the estimate is sure enough that a match consistent with it is a revisit, not an alias.
        map_half: the half-width (keyframes) of the local map to verify against; None: sized by the window.
        plausible: the window around ``estimate[0]`` within which a closure is plausible at all (three
            search windows of the estimate), or None when the place is beyond any spatial window (then
            groups alone decide).
        max_mahalanobis2: the largest squared Mahalanobis distance from ``estimate`` at which a closure is
            plausible at all, for a search the estimate's covariance does not bound (the global one; a descriptor's
            the estimate cannot vouch for), or None.
        corroborated_mahalanobis2: ... and the largest at which it is, when an independent match of the same
            kind beyond ``max_mahalanobis2`` agrees with it (:mod:`slam.loops.accept`), or None.
    """

    i: int
    j: int
    source: Source
    guess: Array
    window: Window
    estimate: tuple[Array, Array] | None
    vouched: bool
    map_half: int | None = None
    plausible: Window | None = None
    max_mahalanobis2: float | None = None
    corroborated_mahalanobis2: float | None = None


@dataclass(frozen=True)
class Verified:
    """An alignment that passed every test of the verifier: ``i_sensor_T_j_sensor`` and its covariance
    (ICP Fisher information at the a-posteriori σ, plus the floor), with its quality figures."""

    candidate: Candidate
    transform: Array
    covariance: Array
    fitness: float
    rmse_m: float
    score: float  # best correlative score (0 without the correlative search)
    map_half: int = 0  # half-width (keyframes) of the local map it was verified against


@dataclass
class LoopClosure:
    """An accepted constraint ``i_T_j`` between keyframes (base frames) for the pose graph."""

    i: int  # older keyframe (the candidate)
    j: int  # newer keyframe
    measurement: Array
    covariance: Array
    fitness: float
    rmse: float
    source: str  # a :class:`Source` value
    group: bool = False  # accepted as a member of an agreeing group, not on its own


@dataclass
class LoopStats:
    """Counters of one run's loop closure (written to ``summary.json`` as ``loop_stats``)."""

    candidates: Counter = field(default_factory=Counter)  # per :class:`Source`
    rejections: Counter = field(default_factory=Counter)  # per :class:`Rejection`
    verified: int = 0  # passed every verification test
    accepted: int = 0  # accepted on their own (the estimate vouched)
    accepted_as_group: int = 0  # accepted as members of an agreeing group
    pending_expired: int = 0  # pending closures whose window passed without a group
    groups_contradicted: int = 0  # groups refused because an accepted closure nearby disagrees
    groups_out_of_context: int = 0  # groups refused because the recent path, matched as a whole, lands elsewhere (or fits the estimate's placement better)
    overruling: int = 0  # unique closures the estimate vouched against, held for a group its recent path bears out
    groups_not_overruling: int = 0  # such groups refused: the recent path, matched from the estimate, stays
    unique_by_path: int = 0  # closures whose scan was ambiguous held pending because the recent path is unique there
    groups_by_path: int = 0  # groups that gave way to a rival at the same place whose recent path fits better
    left_to_their_place: int = 0  # members of a consistent set left out of its group: their old place is one the chain cannot compare
    global_searches: int = 0
    corroborated: int = 0  # global matches beyond the estimate's gate held for a group because another agreed
    reseeks: int = 0  # keyframes sought again after a relocalisation (around refused global matches)

    def as_dict(self) -> dict:
        """Flat counters: ``candidates`` (total), ``candidates_<source>``, ``rejected_<reason>``, the rest."""
        d: dict = {"candidates": sum(self.candidates.values())}
        d |= {f"candidates_{s.value}": self.candidates[s] for s in Source}
        d |= {r.value: self.rejections[r] for r in Rejection}
        d |= {f.name: getattr(self, f.name) for f in fields(self) if f.name not in ("candidates", "rejections")}
        return d
