"""Loop closure for each new keyframe: candidate sources → one verifier → one acceptance stage.

:class:`LoopCloser` wires the stages of :mod:`slam.loops.candidates`, :mod:`slam.loops.verify` and
:mod:`slam.loops.accept` in the order every keyframe goes through:

1. spatial candidates within the estimate's uncertainty, each verified, and accepted when the
   estimate vouches for it and agrees (else pending, when it is unique: its scan, or else the recent path
   that led there, :func:`~slam.loops.context.path_unique`);
2. the places of recent pending closures the estimate could not vouch for, followed into with the
   odometry since (so a revisit gathers its group);
3. when nothing was accepted, descriptor candidates (Scan Context: occupancy bins for a 2D laser,
   heights for a 3D LiDAR); and a global search of one place within reach that no spatial window could
   cover, the one that looks most like the new keyframe first (2D, every ``global_every_keyframes``);
4. the group decision over the pending closures whose window has passed (at the end of the log, over
   the windows still open: :meth:`LoopCloser.close_open_window`), a group per old place, each group's
   last word going to its recent path matched as a whole on the old place (2D, :mod:`slam.loops.context`);
5. after a group relocalised the graph, the keyframes around the global matches the estimate had refused
   are sought again under the corrected estimate (:meth:`LoopCloser.reseek`).

The result is the accepted closures and whether the graph must be relocalised (a group says the
estimate is off by more than a robust kernel lets a closure pull).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from core import geometry as G
from slam.keyframes import Keyframe

from . import candidates as C
from .accept import Acceptance, Pending, to_closure
from .config import LoopConfig
from .context import context_agrees, path_overrules, path_score, path_unique
from .descriptor import SCAN_CONTEXT_3D, DescriptorIndex, PolarDescriptorConfig, polar_descriptor
from .local_map import LocalMaps
from .surroundings import Surroundings
from .types import Candidate, LoopClosure, LoopStats, Rejection, Source, Verified
from .uncertainty import NodeUncertainty, RelativeUncertainty
from .verify import Reference, Verifier

Array = NDArray[np.float64]


class LoopCloser:
    """Finds, verifies and accepts loop closures for each new keyframe (see the module docstring)."""

    def __init__(self, config: LoopConfig, planar: bool, uncertainty: RelativeUncertainty) -> None:
        self.config = config
        self.planar = planar
        self.stats = LoopStats()
        self.maps = LocalMaps()
        self.verifier = Verifier(config, planar, self.maps)
        self.acceptance = Acceptance(config, planar, uncertainty, self.stats)
        self._keyframes: list[Keyframe] = []  # the keyframes of the last detect or reseek (a group's context)
        if planar:
            self.acceptance.confirm = self._context_agrees
            self.acceptance.fit = lambda group, poses: path_score(group, self._keyframes, poses,
                                                                  np.asarray(self._path_m), self.config)
            self.acceptance.overrule = lambda group, poses: path_overrules(group, self._keyframes, poses,
                                                                           np.asarray(self._path_m), self.config)
        self.index = (DescriptorIndex(PolarDescriptorConfig() if planar else SCAN_CONTEXT_3D)
                      if config.descriptor else None)
        self._path_m: list[float] = []  # cumulative odometry path length at each keyframe
        self._global_turn = 0
        self._radius = 0.0  # the overlap radius of the keyframe being closed
        self._global_searched: dict[int, float] = {}  # place → path (m) at its last global search
        self.surroundings = Surroundings()  # what places look like: the global search's order
        self.trace: list[tuple[Candidate, object, dict]] | None = None  # set to a list: (candidate, outcome, figures) of every verification
        self._path_floor: dict[int, float] = {}  # keyframe → the score its recent path must reach (this detect or reseek)

    def summary(self) -> dict:
        """The counters of :class:`LoopStats` (``summary.json`` ``loop_stats``)."""
        return self.stats.as_dict()

    # ------------------------------------------------------------------ local-map size
    def local_map_half(self, i: int, window_m: float, radius_m: float = 0.0) -> int:
        """Half-width (keyframes) of keyframe *i*'s local map for a search window of ± *window_m*: the
        smallest of ``local_map_keyframes`` · 2ⁿ (or ``max_local_map_keyframes``) whose path on each side of
        *i* covers the window plus ``local_map_path_m`` (None: the overlap radius *radius_m*, so that the map
        holds what the new scan can see) — or reaches the ends of the trajectory so far."""
        c = self.config
        path = self._path_m
        need = window_m + (c.local_map_path_m if c.local_map_path_m is not None else radius_m)
        h = max(1, c.local_map_keyframes)
        while h < c.max_local_map_keyframes:
            lo, hi = max(0, i - h), min(len(path) - 1, i + h)
            if (lo == 0 or path[i] - path[lo] >= need) and (hi == len(path) - 1 or path[hi] - path[i] >= need):
                return h
            h *= 2
        return c.max_local_map_keyframes

    @property
    def global_half(self) -> int:
        """Half-width of the local maps the global search matches against, and the spacing of its places."""
        return max(self.config.local_map_keyframes, self.config.max_local_map_keyframes // 2)

    # ------------------------------------------------------------------ one keyframe
    def detect(self, keyframes: list[Keyframe], poses: Array, j: int, uncertainty: NodeUncertainty
               ) -> tuple[list[LoopClosure], bool]:
        """Closures accepted for the new keyframe *j* given the estimate *poses* and every keyframe's
        *uncertainty* relative to *j*; and whether they include a group (the graph must be relocalised)."""
        c = self.config
        kj = keyframes[j]
        self._keyframes = keyframes
        self._path_floor.clear()
        step = 0.0 if j == 0 else float(np.linalg.norm(G.relative(keyframes[j - 1].odom_pose, kj.odom_pose)[:3, 3]))
        self._path_m.append((self._path_m[-1] if self._path_m else 0.0) + step)
        if not c.enabled:
            return [], False
        radius = C.overlap_radius(kj, c)
        self._radius = radius
        ref = self.verifier.reference(keyframes, poses, j)
        out: list[LoopClosure] = []
        tried: set[int] = set()
        found = C.spatial(keyframes, poses, j, uncertainty, c, self.planar, radius, np.asarray(self._path_m))
        for cand in found.near:
            if c.near_closures is not None and len(out) >= c.near_closures:
                break  # enough of this scan at this place; the rest would measure it against the same place again
            tried.add(cand.i)
            self._run(cand, keyframes, poses, ref, out)
        for cand in found.uncertain:
            tried.add(cand.i)
            self._run(cand, keyframes, poses, ref, out)
        for p in self.acceptance.hypotheses():
            h = p.closure
            if h.i in tried or h.j >= j:
                continue
            i_T_h = G.inverse(keyframes[h.i].base_T_sensor) @ h.measurement @ keyframes[h.j].base_T_sensor
            self._run(C.hypothesis(h.i, h.j, i_T_h, keyframes, poses, j, c, p.map_half), keyframes, poses, ref, out)
            tried.add(h.i)
        desc = None if self.index is None else polar_descriptor(self._described(kj), self.index.cfg)
        if not out and desc is not None:
            self._descriptor(keyframes, poses, j, desc, uncertainty, radius, ref, out, tried)
        if self.planar and c.global_search:  # closures with recent passes say nothing of the old places out of reach
            self._global(keyframes, poses, j, uncertainty, radius, ref, out)
        if desc is not None:
            self.index.insert(j, desc)
        group = self.acceptance.decide(j, poses)
        return out + group, bool(group) and self.acceptance.relocalises(group, poses)

    def close_open_window(self, poses: Array) -> tuple[list[LoopClosure], bool] | None:
        """After the last keyframe: the group of the oldest window still open (decided on the evidence the log
        gave) and whether it relocalises the graph, like :meth:`detect`'s; None when nothing is pending.
        Call until None, updating *poses* in between."""
        group = self.acceptance.decide_open_window(poses)
        if group is None:
            return None
        return group, bool(group) and self.acceptance.relocalises(group, poses)

    def _context_agrees(self, group: list[LoopClosure], poses: Array) -> bool:
        """The group's recent path, matched as a whole on its old place, lands where it says (:mod:`.context`),
        when its best pose scores at least ``min_relative_score`` of what the newest keyframe's scan scores on
        its own preceding map (the bar a single closure's search must clear)."""
        own = self.verifier.own_score(self._keyframes, poses, max(lc.j for lc in group))
        return context_agrees(group, self._keyframes, poses, np.asarray(self._path_m), self.config,
                              self.config.min_relative_score * own)

    def _unique(self, v: Verified, keyframes: list[Keyframe], poses: Array, half: int) -> bool:
        """Whether the verified alignment *v* is unique: its scan in its search window
        (:meth:`Verifier.unique`), or else — a spatial candidate in 2D — the recent path that led there,
        matched as one cloud on the old place (:func:`~slam.loops.context.path_unique`): a return along a
        corridor whose doors repeat is ambiguous scan by scan, not with the corner it came round. The path must
        score ``min_relative_score`` of what the new keyframe's scan scores on its own preceding map."""
        if self.verifier.unique(v, keyframes, poses, half):
            return True
        c = v.candidate
        if not self.planar or c.source is not Source.SPATIAL:
            return False
        if c.j not in self._path_floor:
            self._path_floor[c.j] = self.config.min_relative_score * self.verifier.own_score(keyframes, poses, c.j)
        found = path_unique(to_closure(v, keyframes, self.planar), keyframes, poses, np.asarray(self._path_m),
                            self.config, self._path_floor[c.j])
        self.stats.unique_by_path += int(found)
        return found

    @property
    def refused(self) -> bool:
        """Whether global matches were refused beyond the gate since the last :meth:`reseek`."""
        return bool(self.acceptance.refused)

    def reseek(self, keyframes: list[Keyframe], poses: Array, moved: NDArray[np.bool_],
               uncertainty: RelativeUncertainty) -> tuple[list[LoopClosure], bool]:
        """After a relocalisation (*poses* the new estimate): the keyframes within ``group_window_keyframes`` of
        each global match refused beyond the gate since the last one, whose pose *moved* by more than a floor
        window, are sought again — spatial candidates under the corrected estimate, accepted as in
        :meth:`detect`, their group (if any) decided at once. Such a keyframe was passed while the estimate
        was off by more than it knew, so its revisits were sought in the wrong place; the refused match says
        one was there. Returns the closures and whether they relocalise the graph."""
        c = self.config
        self._keyframes = keyframes
        self._path_floor.clear()
        W = c.group_window_keyframes
        newest = len(keyframes) - 1
        seek = sorted({k for r in self.acceptance.take_refused() for k in range(max(0, r - W), min(newest, r + W + 1))
                       if moved[k]})
        out: list[LoopClosure] = []
        held: list[Pending] = []
        dim = 2 if self.planar else 3
        path = np.asarray(self._path_m)
        radius_then = self._radius  # _run sizes local maps by the radius of the keyframe being sought
        try:
            for k in seek:
                unc = uncertainty.from_node(k, poses[:, :dim, 3])
                self._radius = C.overlap_radius(keyframes[k], c)
                ref = self.verifier.reference(keyframes, poses, k)
                for cand in C.spatial(keyframes, poses, k, unc, c, self.planar, self._radius, path):
                    self._run(cand, keyframes, poses, ref, out, held)
        finally:
            self._radius = radius_then
        self.stats.reseeks += len(seek)
        group = self.acceptance.decide_held(held, poses) if held else []
        return out + group, bool(group) and self.acceptance.relocalises(group, poses)

    def _run(self, cand: Candidate, keyframes: list[Keyframe], poses: Array, ref: Reference | None,
             out: list[LoopClosure], held: list[Pending] | None = None) -> None:
        """Verify one candidate and hand a verified alignment to the acceptance stage (one it cannot vouch
        for waits in *held* when given, else in the acceptance stage's pending pool)."""
        self.stats.candidates[cand.source] += 1
        if cand.map_half is not None:
            half = cand.map_half
        elif cand.source is Source.GLOBAL:
            half = self.global_half
        else:
            half = self.local_map_half(cand.i, cand.window.xy_m, self._radius)
        features = {} if self.trace is not None else None
        result = self.verifier.verify(cand, keyframes, poses, half, ref, features)
        if self.trace is not None:
            self.trace.append((cand, result, features))
        if isinstance(result, Rejection):
            self.stats.rejections[result] += 1
            return
        self.stats.verified += 1
        lc = self.acceptance.consider(result, keyframes, poses, lambda v: self._unique(v, keyframes, poses, half), held)
        if lc is not None:
            out.append(lc)

    def _described(self, kf: Keyframe) -> Array:
        """The points a keyframe's descriptor is made of: in 3D the whole scan, since Scan Context's bins
        reach 80 m while the points kept for ICP are thinned and cut at the odometry's range (30 m by
        default: cut there, scans of different streets of kitti_mini came as close as 0.19, against 0.47
        whole); in 2D the kept points, which reach past the descriptor's 15 m."""
        return kf.points if self.planar else kf.frame.points

    def _descriptor(self, keyframes: list[Keyframe], poses: Array, j: int, desc: Array, uncertainty: NodeUncertainty,
                    radius: float, ref: Reference | None, out: list[LoopClosure], tried: set[int]) -> None:
        """Candidates from the places whose descriptors are nearest the new keyframe's *desc*."""
        c = self.config
        if self.index is None or c.descriptor_candidates == 0:
            return
        hits = self.index.query(desc, k=c.descriptor_candidates, exclude_after=j - c.exclude_recent_keyframes)
        # Places of the same pass look alike because the sensor still sees them (a car's street behind
        # it): only other passes are revisits, by the spatial candidates' rule on the estimate's distance.
        places = np.array([i for i, _, _ in hits], dtype=np.int64)
        dim = 2 if self.planar else 3
        apart = np.linalg.norm(poses[places, :dim, 3] - poses[j, :dim, 3], axis=1)
        other = C.other_pass(np.asarray(self._path_m), apart, j, radius, places)
        hits = [(i, yaw) for (i, dist, yaw), o in zip(hits, other) if o and dist <= c.descriptor_max_distance
                and all(abs(i - t) > c.local_map_keyframes for t in tried)]
        sector = 2.0 * np.pi / self.index.cfg.n_sectors
        for cand in C.descriptor(hits, keyframes, poses, j, uncertainty, c, self.planar, radius, sector):
            self._run(cand, keyframes, poses, ref, out)
            if out:
                return

    def _global(self, keyframes: list[Keyframe], poses: Array, j: int, uncertainty: NodeUncertainty,
                radius: float, ref: Reference | None, out: list[LoopClosure]) -> None:
        """One global search, every ``global_every_keyframes``: of the places within reach that no spatial
        window could cover, the one whose surroundings look most like the new keyframe's, among those not
        searched since the robot was an overlap radius of path from here (:func:`candidates.next_global_place`)."""
        c = self.config
        places = C.global_places(poses, j, uncertainty, c, self.planar, radius, self.global_half)
        if len(places) == 0:
            return
        self._global_turn += 1
        if self._global_turn % c.global_every_keyframes:
            return
        here = self._path_m[j]
        fresh = C.unsearched(places, self._global_searched, here, radius)
        if len(fresh) == 0:
            return
        sd = np.sqrt(uncertainty.position_var[fresh])
        d = np.linalg.norm(poses[fresh, :2, 3] - poses[j, :2, 3], axis=1)
        alike = self.surroundings.place_distances(j, fresh, self.global_half, j - c.exclude_recent_keyframes,
                                                  keyframes, poses, np.asarray(self._path_m))
        i = C.next_global_place(fresh, alike, d / np.maximum(sd, 1e-9))
        self._global_searched[i] = here
        self.stats.global_searches += 1
        lm = self.maps.get(keyframes, poses, i, self.global_half)
        self._run(C.global_candidate(keyframes, poses, i, j, uncertainty, c, lm.extent()), keyframes, poses, ref, out)
