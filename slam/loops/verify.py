"""The verifier: one test sequence for every candidate, whatever its source.

1. In 2D, a correlative branch-and-bound search of the candidate's window (Hess et al. 2016, §V;
   Olson 2009) finds the basin; its best score must reach ``min_relative_score`` of the keyframe's
   own score (below).
2. ICP (point-to-line by default, :mod:`registration.point_to_plane`) refines from there.
3. Tests of the fit: the residual χ² test at the sensor's noise (Förstner & Wrobel 2016, the
   variance-factor test); inlier fraction and RMSE against the keyframe's own registration; in 2D,
   negative information — neither scan may have points where the other saw free space (Olson 2009,
   §III-B).
4. For an alignment the acceptance stage holds pending, local uniqueness: no pose elsewhere within
   three floor windows of the match, at any heading, may score within ``ambiguity_ratio`` of it (the
   ratio test of place recognition); a corridor whose matches slide along it, doors repeating along
   it, or a corridor that looks the same turned round (groups of matches 180° off) fail
   it. When the match moves the robot farther from where the estimate puts it than that, the stretch
   between the two is searched too: a match must outscore every pose on the way back to the estimate
   (the bays of a corridor repeat farther apart than the radius, and the right pose lies between) —
   unless the search is a global one, which looks where the estimate may be wrong.
   Farther aliases (the same corridor elsewhere in the map) are left to the group test.

*The keyframe's own registration* (:class:`Reference`) is what a true match of this scan looks like:
the scan against the local map of the keyframes just before it, at the estimate's relative pose. A
scanner with half its beams returning nothing, or an outdoor scan whose walls are 30 m away, fits
its own recent past less well than an indoor scan does; the thresholds are fractions of that, not
absolute numbers.

The covariance of a verified alignment is the ICP's Fisher information at the larger of the a-priori
and the a-posteriori residual variance (the a-posteriori variance factor), plus the configured floor.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.stats import chi2

from core import geometry as G
from core.errors import DegenerateInputError
from registration import correlative, free_space
from registration.alignment import IcpResult, evaluate_alignment
from registration.config import IcpConfig
from registration.icp import icp
from registration.point_to_plane import icp_point_to_plane
from slam.keyframes import Keyframe

from .config import LoopConfig
from .local_map import LocalMap, LocalMaps, sensor_relative
from .types import Candidate, Rejection, Source, Verified

Array = NDArray[np.float64]

PYRAMID_LEVELS = 5  # 2^5 cells per top block: larger windows start from more blocks, not deeper grids
UNIQUE_RADIUS_CELLS = 3  # the neighbourhood of a match left out of the uniqueness search
UNIQUE_RADIUS_RAD = np.radians(3.0)
UNIQUE_WINDOW_FLOORS = 3  # uniqueness is asked around the match, within three floor windows (±3 m by default), at every heading


@dataclass
class Reference:
    """The new keyframe's scan against its own preceding local map, at the estimate's relative pose.

    Attributes:
        fitness: inlier fraction at the verifier's final ICP gate.
        rmse_m: RMSE of those pairs.
        sigma2: residual variance of the point-to-line model (m²), Res / (n − dof).
        covariance: its pose covariance (Fisher information at the a-priori σ).
        local_map, pose: the map and ``map_sensor_T_keyframe_sensor``, for :meth:`score`.
    """

    fitness: float
    rmse_m: float
    sigma2: float
    covariance: Array
    local_map: LocalMap
    pose: Array
    _scores: dict[float, float] = field(default_factory=dict)

    def score(self, maps: LocalMaps, points: Array, resolution: float) -> float:
        """Correlative score of the scan *points* on its own map at *resolution* (m)."""
        if resolution not in self._scores:
            pyr = maps.pyramid(self.local_map, resolution, PYRAMID_LEVELS)
            self._scores[resolution] = correlative.score_at(points, pyr, self.pose)
        return self._scores[resolution]


class Verifier:
    """Verifies :class:`~slam.loops.types.Candidate` pairs against the old keyframe's local map."""

    def __init__(self, config: LoopConfig, planar: bool, maps: LocalMaps) -> None:
        self.config = config
        self.planar = planar
        self.dof = 3 if planar else 6
        self.maps = maps
        c = config
        self._icp = IcpConfig(gates_m=c.icp_gates_m, max_iterations=c.icp_max_iterations,
                              tol_translation_m=c.icp_tolerance_m, tol_rotation_rad=c.icp_tolerance_rad,
                              robust="cauchy", robust_scale_m=c.icp_sigma_m * 2.0, sigma_m=c.icp_sigma_m,
                              chi2_factor=c.chi2_factor, covariance_model="plane", workers=1)
        self.gate = float(chi2.ppf(c.consistency_probability, self.dof))
        self._icp_fine = self._icp.model_copy(update={"gates_m": tuple(g for g in c.icp_gates_m if g < c.icp_gates_m[0]) or c.icp_gates_m})
        self._align = icp if c.icp_method == "point" else icp_point_to_plane

    # ------------------------------------------------------------------ the keyframe's own registration
    def reference(self, keyframes: list[Keyframe], poses: Array, j: int) -> Reference | None:
        """:class:`Reference` of keyframe *j*, or None when it has no ``2 h + 1`` predecessors yet
        (h = ``local_map_keyframes``) or the registration is degenerate."""
        h = self.config.local_map_keyframes
        centre = j - h - 1
        if centre < 0:
            return None
        lm = self.maps.get(keyframes, poses, centre, h)
        pose = sensor_relative(keyframes, poses, centre, j)
        try:
            res = evaluate_alignment(keyframes[j].points, lm.target, pose, self.config.icp_gates_m[-1], self._icp)
        except DegenerateInputError:
            return None
        return Reference(res.fitness, res.rmse, _sigma2(res), res.covariance, lm, pose)

    def search_points(self, kj: Keyframe) -> Array:
        """Keyframe *kj*'s scan points the correlative search uses (within ``correlative_max_range_m``)."""
        pts = kj.points
        return pts[np.hypot(pts[:, 0], pts[:, 1]) <= self.config.correlative_max_range_m]

    def own_score(self, keyframes: list[Keyframe], poses: Array, j: int) -> float:
        """What keyframe *j*'s scan scores on its own preceding local map at the spatial search's resolution
        (what a true match of it scores; 0 without a :class:`Reference`)."""
        ref = self.reference(keyframes, poses, j)
        return 0.0 if ref is None else ref.score(self.maps, self.search_points(keyframes[j]), self.config.correlative_resolution_m)

    # ------------------------------------------------------------------ verification
    def verify(self, c: Candidate, keyframes: list[Keyframe], poses: Array, half: int,
               ref: Reference | None, features: dict | None = None) -> Verified | Rejection:
        """Run the test sequence on candidate *c* against keyframe ``c.i``'s local map of ±*half* keyframes.

        With a *features* dict, every quality figure is computed and stored in it even after a test
        failed (for the development-set analysis; slower)."""
        cfg = self.config
        full = features is not None
        f = features if full else {}
        verdict: Rejection | None = None

        def fail(reason: Rejection) -> bool:
            nonlocal verdict
            if verdict is None:
                verdict = reason
            return not full  # stop at the first failure unless every figure is wanted

        kj = keyframes[c.j]
        lm = self.maps.get(keyframes, poses, c.i, half)
        start, score, pyr, pts = c.guess, 0.0, None, kj.points
        resolution = cfg.global_resolution_m if c.source is Source.GLOBAL else cfg.correlative_resolution_m
        try:
            if self.planar and cfg.correlative:
                pyr = self.maps.pyramid(lm, resolution, PYRAMID_LEVELS)
                pts = self.search_points(kj)
                own = ref.score(self.maps, pts, resolution) if ref is not None else 0.0
                need = cfg.min_relative_score * own
                found = correlative.match(pts, pyr, c.guess, c.window.xy_m, c.window.theta_rad,
                                          min_score=0.5 * need if full else need)
                f["score"], f["score_ratio"] = found.score, found.score / own if own > 0 else np.inf
                if (found.score < need or found.score <= 0.0) and fail(Rejection.SCORE):
                    return Rejection.SCORE
                start, score = found.transform, found.score
            # From the correlative search's pose (within a cell of the basin) the finer gates suffice.
            res = self._align(kj.points, lm.target, start, self._icp_fine if pyr is not None else self._gates_for(c))
        except DegenerateInputError:
            return Rejection.DEGENERATE
        if res.degenerate:
            return verdict or Rejection.DEGENERATE
        sigma2_prior = max(cfg.icp_sigma_m**2, ref.sigma2 if ref is not None else 0.0)
        f["chi2_ratio"] = res.residual / max(cfg.chi2_factor * (res.n_residuals - res.dof) * sigma2_prior, 1e-300)
        if f["chi2_ratio"] > 1.0 and fail(Rejection.CHI2):
            return Rejection.CHI2
        T = res.transform
        cov = self._covariance(res, keyframes[c.j])
        if full:
            f.update(T=T, fitness=res.fitness, rmse=res.rmse, sigma_theta=float(np.sqrt(res.covariance[-1, -1])),
                     sigma_xy=float(np.sqrt(np.trace(res.covariance[:-1, :-1]))) if self.planar else np.nan)
            if ref is not None:
                f.update(fitness_ratio=res.fitness / max(ref.fitness, 1e-9), rmse_ratio=res.rmse / max(ref.rmse_m, 1e-9),
                         ref_sigma_theta=float(np.sqrt(ref.covariance[-1, -1])))
        if ref is not None and (res.fitness < cfg.min_relative_fitness * ref.fitness
                                or res.rmse > cfg.max_relative_rmse * ref.rmse_m) and fail(Rejection.FIT):
            return Rejection.FIT
        if self.planar:
            T = G.xytheta_to_matrix(G.matrix_to_xytheta(T))
            f["free_space"] = free_space_violation_both(T, kj, keyframes[c.i])
            if f["free_space"] > cfg.max_free_space_violation and fail(Rejection.FREE_SPACE):
                return Rejection.FREE_SPACE
            if full and pyr is not None:
                f["unique_ratio"] = self._elsewhere_ratio(pts, pyr, c, T, 0.1)
        if (verdict is None and c.vouched) or full:  # pending closures answer to their group instead
            fb = self.backward(T, keyframes[c.i], ref)
            if fb is not None:
                e = G.se2_log(fb) if self.planar else G.se3_log(fb)
                f["fb_dt"], f["fb_dth"] = float(np.linalg.norm(e[:-1] if self.planar else e[:3])), float(np.linalg.norm(e[2:] if self.planar else e[3:]))
                f["fb_chi2"] = float(e @ np.linalg.solve(2.0 * cov, e))
                if c.vouched and f["fb_chi2"] > self.gate and fail(Rejection.BACKWARD):
                    return Rejection.BACKWARD
        if verdict is not None:
            return verdict
        return Verified(c, T, cov, float(res.fitness), float(res.rmse), score, half)

    def unique(self, v: Verified, keyframes: list[Keyframe], poses: Array, half: int) -> bool:
        """Whether the verified alignment *v* is locally unique: no pose beyond a few cells and degrees of it,
        within three floor windows of it (and within its search window) at any heading, nor on the stretch
        between it and the estimate's pose (one floor window round it), nor anywhere in its own search window
        (:meth:`_window_rival`), scores within ``ambiguity_ratio`` of its own score (2D with the correlative
        search; True otherwise). Asked of every alignment the acceptance stage holds pending: accepted only in a group
        against the estimate, it must not be one of several equally good poses (a corridor's slides, the
        doors along it)."""
        c = v.candidate
        cfg = self.config
        if not (self.planar and cfg.correlative):
            return True
        lm = self.maps.get(keyframes, poses, c.i, half)
        resolution = cfg.global_resolution_m if c.source is Source.GLOBAL else cfg.correlative_resolution_m
        pyr = self.maps.pyramid(lm, resolution, PYRAMID_LEVELS)
        pts = self.search_points(keyframes[c.j])
        try:
            return self._elsewhere_ratio(pts, pyr, c, v.transform, cfg.ambiguity_ratio, cfg.ambiguity_ratio) < cfg.ambiguity_ratio
        except DegenerateInputError:
            return False

    def backward(self, T: Array, ki: Keyframe, ref: Reference | None) -> Array | None:
        """The alignment checked the other way round: keyframe *i*'s scan onto the new keyframe's own
        preceding local map (its :class:`Reference`), from the pose *T* implies; returns the difference
        ``T⁻¹ T'`` of the alignment *T'* that implies, or None without a reference (or when degenerate)."""
        if ref is None:
            return None
        start = ref.pose @ G.inverse(T)  # map_sensor_T_i_sensor
        try:
            back = self._align(ki.points, ref.local_map.target, start, self._icp_fine)
        except DegenerateInputError:
            return None
        T2 = G.inverse(back.transform) @ ref.pose
        if self.planar:
            T2 = G.xytheta_to_matrix(G.matrix_to_xytheta(T2))
        return G.relative(T, T2)

    def _gates_for(self, c: Candidate) -> IcpConfig:
        """Without a correlative search (3D), a coarse first gate as wide as the window (at most 2 m)."""
        if self.planar and self.config.correlative:
            return self._icp
        w = min(2.0, c.window.xy_m)
        if w <= self._icp.gates_m[0]:
            return self._icp
        return self._icp.model_copy(update={"gates_m": (w,) + tuple(self._icp.gates_m)})

    def _elsewhere_ratio(self, pts: Array, pyr: correlative.LikelihoodPyramid, c: Candidate, T: Array,
                         floor: float, stop_at: float | None = None) -> float:
        """The best score in the window beyond a few cells and degrees of *T*, over *T*'s own score (0 when
        nothing elsewhere reaches *floor* times it: the search prunes below that). With *stop_at* the searches
        end at the first pose whose ratio reaches it, and that ratio is returned (a lower bound of the best's):
        the uniqueness test only asks whether one does, and gets the same answer."""
        own = correlative.score_at(pts, pyr, T)
        if own <= 0:
            return np.inf
        cfg = self.config
        xy = min(c.window.xy_m, UNIQUE_WINDOW_FLOORS * cfg.window_floor_m)
        th = np.pi  # every heading: a symmetric corridor matches itself turned round as well as straight
        radius = UNIQUE_RADIUS_CELLS * pyr.resolution
        searches = (
            lambda first: correlative.best_elsewhere(pts, pyr, T, xy, th, T, radius, UNIQUE_RADIUS_RAD, floor * own,
                                                     first=first),
            lambda first: self._stretch_rival(pts, pyr, c, T, xy, radius, floor * own, first),
            lambda first: self._window_rival(pts, pyr, c, T, radius, floor * own, first),
        )
        best = None
        for search in searches:
            s = search(stop_at is not None)
            if s is not None and stop_at is not None:
                if s / own >= stop_at:
                    return s / own
                s = search(False)  # found within the bound's tolerance below the bar: this search's best decides
            if s is not None:
                best = s if best is None else max(best, s)
        return 0.0 if best is None else best / own

    def _window_rival(self, pts: Array, pyr: correlative.LikelihoodPyramid, c: Candidate, T: Array, radius: float,
                      min_score: float, first: bool = False) -> float | None:
        """The best score above *min_score* anywhere in the candidate's own search window, leaving out *T*'s
        neighbourhood; None when the window is at the floor (the three floor windows round *T* hold it), or when
        the estimate's covariance does not bound the search (a global one: its match is held to the estimate
        afterwards). Every pose of a window sized by the estimate's uncertainty is as likely a priori as the
        match: a rival there scoring almost as well is an ambiguity the estimate cannot resolve, however far it
        lies from the match."""
        if c.max_mahalanobis2 is not None or c.window.xy_m <= self.config.window_floor_m:
            return None
        return correlative.best_elsewhere(pts, pyr, c.guess, c.window.xy_m, c.window.theta_rad, T, radius,
                                          UNIQUE_RADIUS_RAD, min_score, first=first)

    def _stretch_rival(self, pts: Array, pyr: correlative.LikelihoodPyramid, c: Candidate, T: Array, xy: float,
                       radius: float, min_score: float, first: bool = False) -> float | None:
        """The best score above *min_score* on the stretch between the match *T* and the estimate's pose (plus
        one floor window, the heading half-way), leaving out *T*'s neighbourhood; None when the ±*xy* box
        round *T* already holds the estimate's floor window, when the two headings differ by more than the
        floor window (an estimate that drifted in heading is no guide to the way back), when there is no
        estimate, or when the estimate's covariance does not bound the search (a global one looks where the
        estimate may be wrong). A match that moves the robot away from where the estimate puts it must score
        better than every pose on the way there: along a corridor the right pose lies between the match and
        its alias."""
        if c.estimate is None or c.max_mahalanobis2 is not None:
            return None
        cfg = self.config
        est = G.matrix_to_xytheta(c.estimate[0])
        mine = G.matrix_to_xytheta(T)
        half = np.abs(est[:2] - mine[:2]) / 2
        if not np.any(2 * half > xy - cfg.window_floor_m):
            return None
        d_th = float(G.wrap_angle(est[2] - mine[2]))
        if abs(d_th) > np.radians(cfg.window_floor_deg):
            return None  # a corridor's alias moves the robot along its heading; an estimate turned further is no guide
        mid = G.xytheta_to_matrix(np.array([*(est[:2] + mine[:2]) / 2, mine[2] + d_th / 2]))
        return correlative.best_elsewhere(pts, pyr, mid, float(half.max()) + cfg.window_floor_m,
                                          abs(d_th) / 2 + np.radians(cfg.window_floor_deg),
                                          T, radius, UNIQUE_RADIUS_RAD, min_score, first=first)

    def _covariance(self, res: IcpResult, kj: Keyframe) -> Array:
        """ICP covariance (sensor frame) at max(a-priori, a-posteriori) residual variance, plus the floor."""
        c = self.config
        factor = max(1.0, _sigma2(res) / c.icp_sigma_m**2)
        n_t = 2 if self.planar else 3
        floor = np.diag([c.covariance_floor_m**2] * n_t + [np.radians(c.covariance_floor_deg) ** 2] * (self.dof - n_t))
        return res.covariance * factor + floor


def _sigma2(res: IcpResult) -> float:
    """A-posteriori residual variance Res / (n − dof) of an alignment (m²)."""
    return float(res.residual / max(res.n_residuals - res.dof, 1))


def free_space_violation(points_in_sensor: Array, keyframe: Keyframe, margin: float = 0.1,
                         rel_margin: float = 0.02, min_inside: float = 0.0) -> float:
    """Fraction of *points* (in *keyframe*'s sensor frame) lying in the free space its beams saw
    (:func:`registration.free_space.violation`, Olson 2009 §III-B)."""
    return free_space.violation(points_in_sensor, keyframe.frame, margin, rel_margin, min_inside)


def free_space_violation_both(i_T_j: Array, kj: Keyframe, ki: Keyframe) -> float:
    """The larger of the two directions of :func:`free_space_violation` for the alignment ``i_sensor_T_j_sensor``
    (:func:`registration.free_space.contradiction` of *kj* placed against *ki* alone)."""
    return free_space.contradiction(i_T_j, kj.frame.points, kj.frame, [(np.eye(4), ki.frame)])
