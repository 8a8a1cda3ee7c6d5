"""The acceptance stage: which verified alignments become pose-graph constraints.

* A verified alignment the estimate vouches for (its search window was at the floor, see :mod:`slam.loops.candidates`)
  is accepted when it is consistent with the estimate: the squared Mahalanobis distance of the alignment from the
  estimate's relative pose, under the sum of both covariances, is within the ``consistency_probability`` quantile
  of χ²(dof) (the χ² gate of Bar-Shalom et al., *Estimation with Applications to Tracking and Navigation*, §5.4).
  The estimate's covariance is the model as stated, also where the run's closures scaled the closer's variances
  (:mod:`slam.loops.calibration`): the scale widens where the closer looks and what may wait for a group, not how far
  one closure may move the estimate on its own.
  One that fails the gate is rejected — unless it is unique, when it waits for a group like the closures below,
  and that group stands only if the closer's :attr:`Acceptance.overrule` hook also agrees: the recent path,
  matched on the old place from where the estimate puts it, moves where the group says
  (:func:`~slam.loops.context.path_overrules`). An estimate that vouches is overconfident when its odometry
  erred beyond its model (wheels that turn wrong, an unmodelled heading drift), and then it refused every true
  revisit; a road whose trees repeat every metre offered a consistent group 1 m along, which the path, started
  from the right estimate, does not follow (docs/LOOP_CLOSURE.md has both).
* Everything else — an alignment the estimate cannot vouch for — waits, *pending*. But none outside
  three of the windows the estimate itself would have searched (9 σ per axis, with the floors), when
  the place lies within spatial reach: a descriptor match of a corridor seen turned round is an alias
  no group may overturn. Pending closures are accepted together when ``group_min_size`` of them, from
  as many keyframes, are pairwise consistent — each pair's cycle through the estimate's short stretches
  between their old and between their new keyframes passes the same χ² gate (pairwise consistent
  measurement set maximisation, PCM: Mangelson, Dominic, Eustice & Vasudevan, ICRA 2018; the maximum
  clique is exact here; :mod:`slam.loops.pairwise`), at one old place (:meth:`Acceptance._one_place`) — and no closure
  accepted on its own between the same stretches disagrees with them. A group is decided once the
  window of ``group_window_keyframes`` after its first member has passed, so the evidence against it
  that arrives in that window (a closure accepted where the estimate was) is seen. The window's other
  old places (old keyframes the graph cannot tie to the group's) get a group of their own, decided alike;
  of two rival sets at one place, the one whose recent path fits the old place better stands (``fit``).
* A global match — or a descriptor's the estimate cannot vouch for — beyond its χ² gate of the estimate
  (``Candidate.max_mahalanobis2``) is rejected unless it is
  *corroborated*: an earlier such match beyond the gate, against a place whose local map shares no
  keyframe with its own, agrees with it (the same pairwise test) while the odometry between the two new
  keyframes and the graph between the two places are sure enough to vouch for the comparison, and both
  lie within the looser ``Candidate.corroborated_mahalanobis2``. Then it waits for a group like any
  closure the estimate cannot vouch for. The gate is the estimate's prior; a heading drift beyond the
  model puts a true return a few σ past it, and two independent searches landing on one correction are
  what an alias rarely does (docs/LOOP_CLOSURE.md has the measurements).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
from numpy.typing import NDArray
from scipy.stats import chi2

from core import geometry as G
from slam.graph.connectivity import component_labels
from slam.keyframes import Keyframe

from .candidates import vouches
from .config import LoopConfig
from .pairwise import PairwiseConsistency
from .types import LoopClosure, LoopStats, Rejection, Verified, Window
from .uncertainty import RelativeUncertainty

Array = NDArray[np.float64]


@dataclass
class Pending:
    """A verified alignment waiting for a group, as the constraint it would become."""

    closure: LoopClosure
    vouched: bool
    map_half: int  # of the local map it was verified against (its follow-ups use the same)
    overrules: bool = False  # the estimate vouched against it: its group needs :attr:`Acceptance.overrule`


def to_closure(v: Verified, keyframes: list[Keyframe], planar: bool, group: bool = False) -> LoopClosure:
    """The base-frame constraint ``i_base_T_j_base`` of a verified sensor-frame alignment, its covariance
    carried through ``base_T_sensor`` of keyframe j (right perturbations: Ad(B_j) Σ Ad(B_j)ᵀ)."""
    c = v.candidate
    Bi, Bj = keyframes[c.i].base_T_sensor, keyframes[c.j].base_T_sensor
    A = G.adjoint(Bj, planar=planar)
    return LoopClosure(c.i, c.j, Bi @ v.transform @ G.inverse(Bj), A @ v.covariance @ A.T, v.fitness, v.rmse_m,
                       c.source.value, group)


def _within(expected: Array, T: Array, window: Window) -> bool:
    """Whether *T* lies within ± *window* of *expected* (per axis of the translation, and in rotation angle)."""
    d = G.inverse(expected) @ T
    return bool(np.abs(d[:3, 3]).max() <= window.xy_m and G.rotation_angle(d[:3, :3]) <= window.theta_rad)


def mahalanobis2(expected: Array, expected_cov: Array, T: Array, cov: Array, planar: bool) -> float:
    """Squared Mahalanobis distance of the pose *T* (covariance *cov*) from *expected* (covariance
    *expected_cov*), on the tangent space of *expected*."""
    d = G.inverse(expected) @ T
    innov = G.se2_log(d) if planar else G.se3_log(d)
    return float(innov @ np.linalg.solve(expected_cov + cov, innov))


# Refused global matches remembered for the search after a relocalisation (a cost bound: each costs a
# search of 2 · group_window_keyframes + 1 keyframes).
_REFUSED_KEPT = 32


class Acceptance:
    """Decides on verified alignments; keeps the pending ones and forms their groups."""

    def __init__(self, config: LoopConfig, planar: bool, uncertainty: RelativeUncertainty, stats: LoopStats) -> None:
        self.config = config
        self.planar = planar
        self.dof = 3 if planar else 6
        self.uncertainty = uncertainty
        self.stats = stats
        self.gate = float(chi2.ppf(config.consistency_probability, self.dof))
        self.pairwise = PairwiseConsistency(uncertainty, planar, self.gate)
        self.pending: list[Pending] = []
        self.recent: list[LoopClosure] = []  # accepted on their own, within the group window
        self.beyond: list[tuple[LoopClosure, int]] = []  # global matches beyond the gate (closure, map half)
        self.refused: list[int] = []  # new keyframes of unique global matches refused beyond the gate, newest last
        #: a group's last word after its pairwise test (the closer's :func:`~slam.loops.context.context_agrees`)
        self.confirm: Callable[[list[LoopClosure], Array], bool] | None = None
        #: how well a group's recent path fits where it puts it (the closer's :func:`~slam.loops.context.path_score`;
        #: None: nothing to tell): decides between rival groups at one place
        self.fit: Callable[[list[LoopClosure], Array], float | None] | None = None
        #: whether a group with members that overrule the estimate (:attr:`Pending.overrules`) is borne out by its
        #: recent path (the closer's :func:`~slam.loops.context.path_overrules`; None: no such group stands)
        self.overrule: Callable[[list[LoopClosure], Array], bool] | None = None

    def consider(self, v: Verified, keyframes: list[Keyframe], poses: Array,
                 unique: Callable[[Verified], bool], hold: list[Pending] | None = None) -> LoopClosure | None:
        """Accept *v* now (vouched for and consistent with the estimate *poses*) or keep it pending (None) when
        it is *unique* in its search window (else it is dropped: a group of aliases agrees as well as a group
        of revisits) — in *hold* when given (a search decided at once, :meth:`decide_held`), else in the
        pool whose windows :meth:`decide` closes."""
        c = v.candidate
        pending = self.pending if hold is None else hold
        if c.plausible is not None and c.estimate is not None and not _within(c.estimate[0], v.transform, c.plausible):
            self.stats.rejections[Rejection.INCONSISTENT] += 1
            return None  # where the estimate says the robot cannot be: an alias no group may overturn
        if c.max_mahalanobis2 is not None and c.estimate is not None:
            m2 = mahalanobis2(c.estimate[0], c.estimate[1], v.transform, v.covariance, self.planar)
            if m2 > c.max_mahalanobis2:  # beyond the estimate's whole uncertainty (a search it did not bound)
                if not (c.corroborated_mahalanobis2 is not None and m2 <= c.corroborated_mahalanobis2 and unique(v)):
                    self.stats.rejections[Rejection.INCONSISTENT] += 1
                    return None
                lc = to_closure(v, keyframes, self.planar)
                if not self._corroborated(lc, v.map_half, poses):
                    self.refused = self.refused[-(_REFUSED_KEPT - 1):] + [c.j]
                    self.stats.rejections[Rejection.INCONSISTENT] += 1
                    return None
                self.stats.corroborated += 1
                pending.append(Pending(lc, False, v.map_half))
                return None
        if c.vouched and c.estimate is not None:
            stated = c.estimate[1] / self.uncertainty.scale  # the model as stated (module docstring)
            if mahalanobis2(c.estimate[0], stated, v.transform, v.covariance, self.planar) <= self.gate:
                lc = to_closure(v, keyframes, self.planar)
                self.recent.append(lc)
                self.stats.accepted += 1
                return lc
            if self.overrule is None or not unique(v):
                self.stats.rejections[Rejection.INCONSISTENT] += 1
                return None
            self.stats.overruling += 1
            pending.append(Pending(to_closure(v, keyframes, self.planar), True, v.map_half, overrules=True))
            return None  # the estimate vouches and disagrees: only a group its recent path bears out overturns it
        if not unique(v):
            self.stats.rejections[Rejection.AMBIGUOUS] += 1
            return None
        pending.append(Pending(to_closure(v, keyframes, self.planar), c.vouched, v.map_half))
        return None

    def decide(self, j: int, poses: Array) -> list[LoopClosure]:
        """After keyframe *j*: the group whose window has just passed, if one agrees (empty otherwise).
        Pending closures older than the window expire."""
        c = self.config
        W = c.group_window_keyframes
        self.recent = [lc for lc in self.recent if lc.j > j - 2 * W]
        if not self.pending:
            return []
        first = min(p.closure.j for p in self.pending)
        if j < first + W - 1:
            return []  # the window after the first pending closure is not complete yet
        window = [p for p in self.pending if p.closure.j < first + W]
        accepted = self._agreeing(window, poses)
        # The window is decided: its closures leave the pool (a group's members as accepted ones).
        self.pending = [p for p in self.pending if p.closure.j >= first + W]
        return accepted

    def decide_held(self, held: list[Pending], poses: Array) -> list[LoopClosure]:
        """The group among *held* closures (those :meth:`consider` kept aside for one search), decided at once."""
        return self._agreeing(held, poses)

    def _agreeing(self, pending: list[Pending], poses: Array) -> list[LoopClosure]:
        """The groups among the *pending* closures: the largest pairwise-consistent subset, its part at one old place
        (:meth:`_one_place`; or its rival there whose recent path fits better, :meth:`_fitter`), accepted when
        it spans ``group_min_size`` new keyframes, no closure accepted alone nearby contradicts it,
        :attr:`confirm` (when set) agrees and, when a member overrules the estimate, :attr:`overrule` does; then
        the same again among the closures against *other* old places — those whose old keyframe the graph
        cannot vouch for relative to any accepted member's (:meth:`_other_places`) — until no group is left
        (the rest expire). A return seen against two old passes that the graph has
        misplaced relative to each other gives two groups, each consistent and each inconsistent with the
        other through the graph's wrong stretch between the passes: both are revisits, and the larger one
        does not refute the smaller."""
        closures = [p.closure for p in pending]
        overruling = {id(p.closure) for p in pending if p.overrules}
        accepted: list[LoopClosure] = []
        left = closures
        while left:
            group = self._one_place(self.pairwise.largest_set(left, poses), poses)
            if len({lc.j for lc in group}) < self.config.group_min_size:
                break
            others = self._other_places(left, group, poses)
            chosen = self._fitter(group, left, others, poses)
            if chosen is not group:
                group, others = chosen, self._other_places(left, chosen, poses)
            if self._contradicted(group, poses):
                self.stats.groups_contradicted += 1
                break
            if self.confirm is not None and not self.confirm(group, poses):
                self.stats.groups_out_of_context += 1
                break
            overrules = any(id(lc) in overruling for lc in group)
            if overrules and not (self.overrule is not None and self.overrule(group, poses)):
                self.stats.groups_not_overruling += 1
                break
            accepted += group
            left = others
        members = {id(lc) for lc in accepted}
        self.stats.pending_expired += sum(1 for lc in closures if id(lc) not in members)
        for lc in accepted:
            lc.group = True
        self.stats.accepted_as_group += len(accepted)
        return accepted

    def _fitter(self, group: list[LoopClosure], closures: list[LoopClosure], others: list[LoopClosure],
                poses: Array) -> list[LoopClosure]:
        """*group*, or its rival — the largest consistent set among the *closures* at the same place, neither in
        the group nor among the *others* (:meth:`_other_places`: those at other places), when it also spans
        ``group_min_size`` new keyframes and its recent path fits the old place better (:attr:`fit`). Two such
        sets are a return and its alias along a corridor whose doors repeat; the larger is the one matched
        against more old keyframes, which says nothing about which is right, while the path that led there does."""
        if self.fit is None:
            return group
        out = {id(lc) for lc in others} | {id(lc) for lc in group}
        rival = self.pairwise.largest_set([lc for lc in closures if id(lc) not in out], poses)
        if len({lc.j for lc in rival}) < self.config.group_min_size:
            return group
        mine, theirs = self.fit(group, poses), self.fit(rival, poses)
        if mine is None or theirs is None or theirs <= mine:
            return group
        self.stats.groups_by_path += 1
        return rival

    def _one_place(self, group: list[LoopClosure], poses: Array) -> list[LoopClosure]:
        """The part of a consistent *group* at one old place (members linked through old keyframes whose chain
        vouches, as :meth:`_other_places` tells places apart) with most distinct new keyframes. Between places
        the chain cannot vouch for, the pairwise test's variance passes anything: a closure there agrees with
        every member without being compared with any, so it counts in its own place's group, not this one's."""
        olds = sorted({lc.i for lc in group})
        if len(olds) < 2:
            return group
        pos = poses[:, :(2 if self.planar else 3), 3]
        tied = np.array([(x, y) for x in range(len(olds)) for y in range(x + 1, len(olds))
                         if vouches(*self.uncertainty.chain_variance(olds[x], olds[y], pos), self.config, self.planar)],
                        dtype=np.int64).reshape(-1, 2)
        place = dict(zip(olds, component_labels(len(olds), tied[:, 0], tied[:, 1])))
        parts: dict[int, list[LoopClosure]] = {}
        for lc in group:
            parts.setdefault(int(place[lc.i]), []).append(lc)
        part = max(parts.values(), key=lambda p: (len({lc.j for lc in p}), len(p)))
        self.stats.left_to_their_place += len(group) - len(part)
        return part

    def _other_places(self, closures: list[LoopClosure], group: list[LoopClosure], poses: Array) -> list[LoopClosure]:
        """The *closures* outside the accepted *group* whose old keyframe is at another place than every
        member's: the chain of keyframes between them is too uncertain to vouch for (those the chain ties to a
        member and that disagree with the group are its aliases)."""
        d = 2 if self.planar else 3
        pos = poses[:, :d, 3]
        members = {id(lc) for lc in group}
        return [lc for lc in closures if id(lc) not in members and not any(
            vouches(*self.uncertainty.chain_variance(lc.i, a.i, pos), self.config, self.planar) for a in group)]

    def take_refused(self) -> list[int]:
        """The new keyframes of the unique global matches refused beyond the gate since the last call
        (where the estimate was off by more than it knew: worth seeking again once it has moved)."""
        out, self.refused = self.refused, []
        return out

    def decide_open_window(self, poses: Array) -> list[LoopClosure] | None:
        """At the end of the log: decide the oldest window still open on the evidence that arrived before the
        log ended (a return to the start at the end of a log is the commonest loop of all); None when no
        closure is pending."""
        if not self.pending:
            return None
        first = min(p.closure.j for p in self.pending)
        return self.decide(first + self.config.group_window_keyframes - 1, poses)

    def _corroborated(self, lc: LoopClosure, half: int, poses: Array) -> bool:
        """Whether an earlier global match beyond the gate (kept while the odometry from its new keyframe to
        *lc*'s vouches for the comparison) agrees with *lc*, against a place whose local map shares no
        keyframe with *lc*'s (±*half*): two searches of different old structure that find one correction.
        The places' relative pose is the graph's (closures included), and must be as sure as the
        odometry's. *lc* is kept for the matches to come."""
        d = 2 if self.planar else 3
        pos = poses[:, :d, 3]
        self.beyond = [(b, h) for b, h in self.beyond if b.j < lc.j and vouches(*self.uncertainty.chain_variance(b.j, lc.j, pos), self.config, self.planar)]
        agree = False
        for b, h in self.beyond:
            if abs(b.i - lc.i) <= h + half:
                continue  # the same old structure: one piece of evidence, not two
            graph = self.uncertainty.from_node(b.i, pos)
            old = (float(graph.position_var[lc.i]), float(graph.rotation_var[lc.i]))
            if vouches(*old, self.config, self.planar) and self.pairwise.consistent(lc, b, poses, old):
                agree = True
                break
        self.beyond.append((lc, half))
        return agree

    def _contradicted(self, group: list[LoopClosure], poses: Array) -> bool:
        """Whether a closure accepted on its own between the same stretches of old and new keyframes (within
        the group window of a member's) disagrees with a member: the estimate was right there, and the
        group is an alias (a door along a corridor whose doors repeat)."""
        W = self.config.group_window_keyframes
        pairs = [(a, r) for a in group for r in self.recent if abs(r.i - a.i) <= W and abs(r.j - a.j) <= W]
        return bool(pairs) and not bool(np.all(self.pairwise.of_pairs(pairs, poses)))

    def relocalises(self, group: list[LoopClosure], poses: Array) -> bool:
        """Whether the accepted *group* says the estimate is off by more than a robust kernel lets a
        closure pull: a member beyond ``relocalise_sigmas`` of the estimate, whitened by its own covariance
        (the back end then re-solves without kernels first)."""
        limit = self.config.relocalise_sigmas**2 * self.dof
        for lc in group:
            d = G.relative(lc.measurement, G.relative(poses[lc.i], poses[lc.j]))
            e = G.se2_log(d) if self.planar else G.se3_log(d)
            if float(e @ np.linalg.solve(lc.covariance, e)) > limit:
                return True
        return False

    def hypotheses(self) -> list[Pending]:
        """Pending closures the estimate could not vouch for (global, descriptor, uncertain spatial): the
        places the next keyframes are followed into, newest per old place."""
        latest: dict[int, Pending] = {}
        for p in self.pending:
            if not p.vouched and (p.closure.i not in latest or p.closure.j > latest[p.closure.i].closure.j):
                latest[p.closure.i] = p
        return list(latest.values())
