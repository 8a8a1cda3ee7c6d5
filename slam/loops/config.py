"""Typed configuration of loop closure (pydantic; loadable from YAML as the ``loops`` section of ``slam run``).

Every field is a sensor or robot quantity, a statistical level, or a documented algorithm constant;
none was chosen for one log (the development-set table in ``docs/LOOP_CLOSURE.md`` is the evidence for
each default). Names carry their units: ``_m`` metres, ``_deg`` degrees (converted to radians where used),
``_keyframes`` counts of keyframes; probabilities are in (0, 1).
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field


class LoopConfig(BaseModel):
    """Loop-closure candidates, verification, acceptance and the back end's treatment of closures."""

    model_config = ConfigDict(extra="forbid")

    enabled: bool = True
    # ------------------------------------------------------------------ candidates
    exclude_recent_keyframes: int = Field(15, ge=1, description="keyframes this recent are the odometry's, not loop candidates")
    overlap_radius_m: float | None = Field(None, gt=0, description="two keyframes this close can see the same structure (the search radius before uncertainty); None: the upper quartile of the ranges of the new keyframe's scan points, a property of the sensor in its environment")
    window_sigmas: float = Field(3.0, gt=0, description="search windows and radii span this many standard deviations of the estimate's relative uncertainty")
    heading_drift_deg_per_m: float = Field(0.015, ge=0, description="σ of a heading rate (° per metre travelled) common to a whole stretch of odometry: the systematic drift independent edge noise cannot represent, added to every place's uncertainty along its path (0: none)")
    window_calibration: bool = Field(True, description="2D: once at least 30 accepted closures span 101 keyframes or more, every variance the closer uses to search and to decide what may wait for a group is scaled up by the factor at which those closures' chains average NEES/dof 1 under this model, when it exceeds 1 (slam.loops.calibration); the stated model stays the floor, and a closure accepted on its own is still held to it. Closes returns under a heading drift the covariance does not know (docs/LOOP_CLOSURE.md, \"The closer's variances widened by its own closures\")")
    window_floor_m: float = Field(1.0, gt=0, description="smallest correlative search window (± m): what the graph's covariance does not model (local-map blur, ICP basins)")
    window_floor_deg: float = Field(5.0, gt=0, description="smallest correlative heading window (± degrees)")
    max_window_m: float = Field(10.0, gt=0, description="largest spatial search window (± m), a cost bound; places the estimate cannot place within it are left to the global search")
    near_candidates: int = Field(4, ge=0, description="spatial candidates per keyframe, nearest first (their local maps not overlapping)")
    uncertain_candidates: int = Field(2, ge=0, description="... plus this many of the most uncertain places within reach (an old pass is not crowded out by the recent one)")
    near_closures: int | None = Field(2, ge=1, description="the nearest candidates are verified, nearest first, until this many closures of the new keyframe are accepted (a cost bound, cf. the sampling ratio of Hess et al. 2016 §V-C: a further one measures the same scan against the same place again); the most uncertain places are always verified; None: every candidate")
    local_map_keyframes: int = Field(3, ge=0, description="a candidate's local map: its scan and those of ±this many keyframes, in its frame")
    local_map_path_m: float | None = Field(0.5, ge=0, description="... widened to cover the search window: keyframes within window + this much path (m) of the candidate; None: the overlap radius")
    max_local_map_keyframes: int = Field(40, ge=1, description="... up to ±this many keyframes (memory and build time)")
    descriptor: bool = Field(True, description="Scan Context place recognition (Kim & Kim 2018: bin heights of a 3D cloud, bin occupancy of a 2D scan) when a keyframe closed nothing spatially")
    descriptor_candidates: int = Field(2, ge=0)
    descriptor_max_distance: float = Field(0.35, gt=0, le=1, description="Scan Context distance (eq. 5, 0–1) below which a place is a candidate")
    global_search: bool = Field(True, description="2D: places within the new keyframe's uncertainty but beyond max_window_m are searched whole, one per global_every_keyframes (Hess et al. 2016 §V-C)")
    global_every_keyframes: int = Field(2, ge=1, description="a cost bound: one global search per this many keyframes that have such places")
    global_resolution_m: float = Field(0.2, gt=0, description="likelihood-field cell (and σ) of the global search, coarser than the spatial one for its larger windows")
    # ------------------------------------------------------------------ verification
    correlative: bool = Field(True, description="2D: branch-and-bound correlative search of the window gives ICP its start (Hess et al. 2016)")
    correlative_resolution_m: float = Field(0.1, gt=0, description="likelihood-field cell (and σ) of the spatial correlative search")
    correlative_max_range_m: float = Field(30.0, gt=0, description="scan points beyond this range are left out of the correlative search (its angular step moves the farthest point by one cell, Hess et al. 2016 eq. 7)")
    min_relative_score: float = Field(0.5, ge=0, le=1, description="the best correlative score must reach this fraction of the keyframe's own score against its preceding local map (what a true match of this scan scores)")
    icp_gates_m: tuple[float, ...] = Field((1.0, 0.4, 0.15), description="verification ICP correspondence gates, coarse to fine")
    icp_method: Literal["point", "plane"] = Field("plane", description="point-to-point SVD-ICP or point-to-plane (point-to-line in 2D)")
    icp_tolerance_m: float = Field(1e-4, gt=0, description="an ICP stage ends when the pose increment is below this (m) ...")
    icp_tolerance_rad: float = Field(1e-4, gt=0, description="... and below this (rad)")
    icp_max_iterations: int = Field(40, ge=1)
    icp_sigma_m: float = Field(0.03, gt=0, description="a-priori point-to-line residual σ of the χ² test; the keyframe's own residual σ replaces it when larger")
    chi2_factor: float = Field(3.0, gt=0, description="χ² test: reject when Res > factor·(n − dof)·σ²")
    min_relative_fitness: float = Field(0.6, ge=0, le=1, description="the closure's inlier fraction must reach this fraction of the keyframe's own against its preceding local map")
    max_relative_rmse: float = Field(2.0, gt=0, description="... and its RMSE at most this multiple of that registration's")
    max_free_space_violation: float = Field(0.15, ge=0, le=1, description="2D: largest fraction of either scan's points in the other's observed free space (negative information, Olson 2009)")
    # ------------------------------------------------------------------ acceptance
    consistency_probability: float = Field(0.95, gt=0, lt=1, description="a closure the estimate can vouch for is accepted when its Mahalanobis distance from the estimate is within this χ² quantile")
    ambiguity_ratio: float = Field(0.9, gt=0, le=1, description="a closure the estimate cannot vouch for must be unique: the best correlative score outside its neighbourhood must stay below this fraction of its own")
    group_min_size: int = Field(3, ge=2, description="closures the estimate cannot vouch for are accepted together when this many, from as many keyframes, agree pairwise (PCM, Mangelson et al. 2018)")
    group_window_keyframes: int = Field(10, ge=1, description="pending closures wait this many keyframes for a group, and a group is decided once its window has passed")
    group_context_path_m: float | None = Field(20.0, gt=0, description="2D: before a group is accepted, the keyframes of this much path up to its newest member are matched as one cloud on the old place's surroundings (as much path either side of its old keyframes); the group is refused when that cloud fits clearly better (ambiguity_ratio) more than a floor window from the group's pose — a corridor's alias repeats for a scan, not for the path that led there. The same path makes a closure whose scan is ambiguous unique when it is (slam.loops.context.path_unique). None: off")
    group_context_window_m: float = Field(6.0, gt=0, description="± m (x and y) of that search round the group's pose: twice the uniqueness test's ±3 floor windows")
    relocalise_sigmas: float = Field(10.0, gt=0, description="an accepted group with a member this many σ (per degree of freedom) from the estimate moves the graph by a batch solve without kernels first: the Cauchy kernel (scale 1σ) leaves a closure that far 1 % of its weight")
    # ------------------------------------------------------------------ closures in the back end
    robust_kernel: Literal["none", "huber", "cauchy", "gm"] = "cauchy"
    robust_scale: float = Field(1.0, gt=0, description="kernel width in whitened units (σ)")
    covariance_floor_m: float = Field(0.01, ge=0, description="added to a closure's translation σ (ICP covariances treat both maps as exact)")
    covariance_floor_deg: float = Field(0.3, ge=0, description="... and heading σ")
    prune_translation_m: float = Field(0.2, gt=0, description="after the final solve, closures violated by more than this (Hess et al. 2016, §VII-B) ...")
    prune_rotation_deg: float = Field(1.0, gt=0, description="... or this are dropped and the graph solved again")
    prune_rounds: int = Field(3, ge=0, description="rounds of prune-and-solve after the final solve (ends early when no closure is violated)")
