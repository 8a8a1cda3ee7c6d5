"""Typed configuration of ``slam run`` (pydantic; loadable from YAML, dumped next to every output).

Distances are metres, angles radians, times seconds.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field

from mapping.config import MappingConfig
from slam.keyframes import KeyframeConfig


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid")


class OdometryStageConfig(_Model):
    """Which registration source gives odometry: ``kiss`` (KISS-ICP), ``icp`` (our scan-to-map SVD-ICP)
    or ``auto`` — KISS-ICP for 3D clouds, our ICP for planar scans. On the whole Intel log the SLAM
    relation error was 0.044 m with ``icp`` against 0.41 m with ``kiss`` (KISS-ICP loses track in
    places there), so planar logs default to ``icp``."""

    method: Literal["auto", "kiss", "icp"] = "auto"
    use_wheel_odometry: bool = True
    icp_point_to_plane: bool = Field(True, description="our ICP odometry: point-to-line/plane steps instead of point-to-point")
    icp_gates: tuple[float, ...] = Field((0.3,), description="2D, our ICP odometry: correspondence gates (m), coarse to fine, from the wheel guess; whole Intel log (0.5, 0.2) at 1e-4 / (0.3,) at 5e-4: 0.0290 / 0.0288 m, 351 / 260 s CPU")
    icp_tolerance: float = Field(5e-4, gt=0, description="2D, our ICP odometry: a gate stage ends when the pose increment is below this (m and rad)")
    icp_map_step_m: float = Field(0.0, ge=0, description="our ICP odometry: a scan joins the local map after this much motion (0 = every scan) ...")
    icp_max_guess_deviation_m: float | None = Field(0.3, gt=0, description="our ICP odometry: a step this far from the wheel guess is a failure ...")
    icp_max_guess_deviation_rad: float | None = Field(0.35, gt=0, description="... or turned this much more; the wheel guess is kept")
    icp_alternative_start_m: float | None = Field(0.05, gt=0, description="our ICP odometry: when the wheel increment differs by more than this (or the angle below) both from the last estimated increment and from the previous wheel increment (lumpy wheel odometry, MIT CSAIL), ICP also starts from the last increment and the clearly better fit wins")
    icp_alternative_start_rad: float | None = Field(0.05, gt=0)
    icp_map_step_rad: float = Field(0.1, gt=0, description="... or this much turning (the map's k-d tree is rebuilt only then)")
    icp_wheel_prior_sigma: float | None = Field(None, gt=0, description="our ICP odometry with smooth wheel odometry: the wheel prediction enters each ICP step as a prior with the wheel_sigma_* model below (floors 1 cm, 5 mrad), weighed against point residuals of this σ (m); None = no prior. Freiburg hospital (relations < 10 s apart, odometry alone): none / 0.05 / 0.15 / 0.5 gave 0.0986 / 0.0928 / 0.0834 / 0.0794 m, but the drift over the whole log grew (0.76 → 0.94–1.30 m) and the far return was lost (SLAM 0.80–1.30 m against 0.119 m without): off by default")
    unguided_window_m: float | None = Field(1.0, gt=0, description="2D, our ICP odometry without wheel odometry: each scan is first placed by a correlative search of ± this (m, x and y) around the constant-velocity guess on the local map, as far as the robot may stray from constant velocity between two scans; None = ICP from the guess alone")
    unguided_window_deg: float = Field(30.0, gt=0, description="... and ± this in heading (degrees)")
    max_range: float = Field(30.0, gt=0, description="2D: beams beyond this are ignored for registration")
    min_range: float = Field(0.05, ge=0)
    # Edge covariance: the Fisher information of the keyframe's scan against the previous keyframe's
    # at the odometry's relative pose (registration.covariance), with this residual σ and gate.
    edge_sigma_m: float = Field(0.02, gt=0, description="per-point residual σ of the keyframe-to-keyframe registration")
    edge_sigma_from_residuals: bool = Field(True, description="scale the edge covariance by max(1, σ̂²/σ²), σ̂ the scan's own residual σ (the a-posteriori variance factor; median σ̂: Freiburg hospital 7 cm, Intel and MIT CSAIL 2.7 cm). Replays of the recorded front ends, together with the wheel calibration and the gate as before: hospital 0.1179 → 0.1102 m, Intel 0.0166 → 0.0164 m, CSAIL 0.0269 m either way")
    edge_gate_m: float = Field(0.3, gt=0)
    # Noise floor added to the odometry covariance per keyframe edge: σ² = a + b·distance (translation)
    # and c + d·|angle| (rotation). Registration covariances treat the map as exact and are
    # optimistic; the floor keeps loop closures able to correct accumulated drift.
    floor_translation_m: float = Field(0.005, ge=0)
    floor_translation_per_m: float = Field(0.01, ge=0)
    floor_rotation_rad: float = Field(0.002, ge=0)
    floor_rotation_per_rad: float = Field(0.01, ge=0)
    # Wheel odometry, when the log has it, also enters the graph as its own edge between keyframes
    # (so registration-degenerate directions, e.g. along a corridor, fall back on the wheels):
    # σ_xy = a·d + 1 mm, σ_θ = b·d + c·|Δθ| + 1 mrad for a step of length d (m) and turn Δθ (rad).
    wheel_edges: bool = True
    wheel_sigma_per_m: float = Field(0.1, gt=0)
    wheel_sigma_rad_per_m: float = Field(0.08, gt=0)
    wheel_sigma_rad_per_rad: float = Field(0.1, gt=0)
    wheel_sigma_m_per_rad: float = Field(0.15, ge=0, description="translation σ per radian turned (a turn in place moves the base a little: Intel's wheel edges that disagreed with the registration were turns of 17° in place (median) off by 0.029 m sideways, σ ≈ 0.15 m/rad; with 0 the model gave them 1 mm)")
    wheel_gate_probability: float | None = Field(0.999, gt=0, lt=1, description="a wheel edge whose disagreement with the registration edge exceeds this χ² quantile (Mahalanobis, both covariances) is left out: wheel odometry logged in lumps says 0° over a keyframe the robot turned 40° in (MIT CSAIL); None keeps every wheel edge")
    wheel_gate_lumpy_only: bool = Field(True, description="... but only when the wheels were lumpy in the interval (the ICP odometry took its constant-velocity start); over smooth wheels the registration slid, and the wheel edge stays. Recorded with the calibration and wheel_sigma_m_per_rad = 0.15: Freiburg hospital 0.1102 → 0.1077 m (its corridor slides keep their wheel edges), Intel 0.0164 → 0.0151 m, MIT CSAIL 0.0269 m; without the turn term Intel's in-place turns became wheel edges 1 mm sure of the base's position (0.0267 m)")
    wheel_calibration: bool = Field(True, description="scale the wheel model per block (translation, rotation) online so that the wheel-vs-registration disagreement has its expected χ² mean (slam.pipeline.wheel_calibration); the fitted scales are in summary.json (odometry_stats): Freiburg hospital 0.41 / 0.13, Intel 0.33 / 0.90, MIT CSAIL 0.49 / 1.23")
    wheel_calibration_min_edges: int = Field(50, ge=1, description="wheel edges before the calibration starts (until then the model as configured)")


class LoopConfig(_Model):
    """Loop-closure detection and verification."""

    enabled: bool = True
    search_radius_m: float = Field(2.0, gt=0, description="base radius around the current estimate")
    radius_sigma_factor: float = Field(3.0, ge=0, description="a keyframe's radius grows by this × the σ of its position relative to the new keyframe, along the graph")
    max_radius_m: float = Field(8.0, gt=0)
    exclude_recent_keyframes: int = Field(15, ge=1, description="keyframes this recent are not loop candidates")
    max_candidates: int = Field(4, ge=1, description="spatial candidates verified per keyframe (nearest first)")
    far_sigma_m: float = Field(1.0, gt=0, description="keyframes whose position σ relative to the new one exceeds this are 'graph-far' (only a long chain links them: the estimate may have drifted metres) ...")
    far_candidates: int = Field(1, ge=0, description="... and this many of them (nearest first) are verified besides the max_candidates nearest, so the nearby recent passes cannot crowd out the revisit of an old one ...")
    far_max_radius_m: float = Field(15.0, gt=0, description="... searched within base + factor·σ up to this radius (m), the correlative window up to the same ...")
    far_submap_keyframes: int = Field(25, ge=0, description="... against a larger local map (±k keyframes): the Freiburg hospital's return after 80 min, 10 m off, scores fitness 0.29–0.41 against ±3 keyframes and 0.58–0.66 against ±25")
    far_min_correlative_score: float = Field(0.5, ge=0, le=1, description="... and rejected before ICP unless a pose in the window scores this (mean likelihood, 0–1); the bound prunes the ±15 m search from ~0.5 s to ~0.05 s. The hospital's true return scores 0.74; its first 3000 scans' far candidates 0.30–0.57")
    opposite_retry_min_gap_keyframes: int | None = Field(100, ge=1, description="2D: when a keyframe closed nothing, its graph-near spatial candidates seen from the opposite direction (relative heading beyond 90°) and at least this many keyframes older are verified again against their larger far_submap_keyframes map; what passes is held like a closure inconsistent with the estimate and enters only in an agreeing group (group_min_size). A 180° scanner driving a corridor the other way shares little but the side walls with a ±submap_keyframes map: the Freiburg hospital's last 170 s retrace its first corridor the opposite way. Replays without / with (and the two gates below): hospital 0.1078 / 0.1031 m, both 100 % precision (ICP-tolerance perturbations 4e-4 … 6e-4: 0.1076–0.1110 / 0.1031–0.1085 m); Intel 0.0151 / 0.0144 m at 99.25 / 99.38 %; MIT CSAIL 0.0269 m both, at 100 %; Killian bag precision 98.52 / 98.87 %, loop stage 102 / 127 s. Accepted alone instead of held: precision 98.0 / 98.4 / 97.3 % (hospital / Intel / CSAIL); with a gap of 1 CSAIL's dead-end turn-arounds gave opposite views 1–5° off in heading at fitness 0.96–1.0; at most one retry per keyframe: hospital 0.1077 m. None = no retry")
    opposite_max_mahalanobis: float = Field(2.0, gt=0, description="... such a closure must lie within this many σ (per degree of freedom, as max_mahalanobis) of the estimate, which is sure of these graph-near places ...")
    opposite_max_heading_deg: float = Field(1.5, gt=0, description="... and turn the estimate's relative heading by at most this (°): opposite views of a corridor fix the heading mostly through its side walls, and the retried closures the hospital's final solution violated (by 1.1–1.7° in heading, 2–3 of them per run without these gates: 95.7 % precision) had turned it by 1.9–2.6°, the ones it kept by up to 1.7°")
    min_information_gain: float = Field(0.0, ge=0, description="a spatial candidate is verified only when a closure could add this much information (nats): 0.5·Σ log(1 + σ²_rel/σ²_floor) over the axes, with σ_rel its uncertainty relative to the new keyframe along the graph and σ_floor the closure covariance floor, an upper bound on the mutual information a closure brings (the link-selection criterion of Ila, Porta & Andrade-Cetto, 'Information-based compact Pose SLAM', T-RO 2010); 0 verifies every candidate. Whole Intel log (`slam loops --sweep min_information_gain=0:4:5`): 0 / 2 / 3 / 4 nats gave 0.0157 / 0.0161 / 0.0173 / 0.0207 m with the loop stage at 117 / 101 / 68 / 43 s")
    use_descriptor: bool = True
    descriptor_candidates: int = Field(2, ge=0)
    descriptor_max_distance: float = Field(0.35, gt=0, description="Scan Context distance below which a place is a candidate; whole Intel log 0.25 / 0.35 / 0.5 / 0.65: 0.0565 / 0.0293 / 0.0295 / 0.0288 m (0.35: 0.6 % of places > 5 m apart pass, 12 % of those < 1 m)")
    submap_keyframes: int = Field(3, ge=0, description="candidate's neighbours (±k keyframes) forming the ICP target")
    icp_gates: tuple[float, ...] = (1.0, 0.4, 0.15)
    icp_method: Literal["point", "plane"] = Field("plane", description="verification ICP: point-to-point SVD-ICP or point-to-plane (point-to-line in 2D)")
    icp_tolerance: float = Field(1e-4, gt=0, description="ICP stops a gate stage when the pose increment is below this (m and rad)")
    icp_max_iterations: int = Field(40, ge=1)
    require_convergence: bool = Field(False, description="reject alignments still moving at the iteration cap (removes corridor slides; on Intel it did not lower the relation error)")
    correlative: bool = Field(True, description="2D: a branch-and-bound correlative search of a window around the guess gives the ICP start (registration.correlative)")
    correlative_resolution_m: float = Field(0.1, gt=0, description="cell size of the correlative likelihood field (its σ is the same); on Intel's first 3000 scans 0.1 m gave 0.0171 m relation error and 100 % precision, 0.05 m 0.0219 m and 99.6 % at 1.4× the time")
    correlative_window_m: float = Field(2.5, gt=0, description="spatial candidates: ± this in x and y around the estimate's relative pose; Intel's first 3000 scans 1.5 / 2.5 m: 0.0601 / 0.0171 m (the east-corridor revisit at t ≈ 400 s starts ~1.5 m off)")
    correlative_window_deg: float = Field(10.0, gt=0, description="... and ± this in heading")
    correlative_window_sigmas: float = Field(3.0, ge=0, description="spatial candidates: the window widens to ± this × the candidate's σ relative to the new keyframe (position and heading), up to far_max_radius_m ...")
    correlative_max_window_deg: float = Field(30.0, gt=0, description="... and ± this in heading")
    correlative_max_range_m: float = Field(30.0, gt=0, description="scan points farther than this (m, sensor frame) are left out of the correlative search (ICP uses all): its angular step moves the farthest point by one cell (Hess et al. 2016, Eq. 7), so the Freiburg hospital's 80 m returns made it 0.07° and a ±15 m / ±30° search took ~1 s")
    descriptor_window_m: float = Field(1.5, gt=0, description="descriptor candidates: ± this around the place (the descriptor gives no offset)")
    descriptor_window_deg: float = Field(8.0, gt=0, description="... and ± this around the descriptor's heading")
    correlative_min_gain: float = Field(0.05, ge=0, description="ICP starts from the correlative pose only when its score (mean likelihood of the scan's points, 0–1) beats the guess's by this much; Intel's first 3000 scans: 0 / 0.05 / 0.15 gave 0.0171 / 0.0174 / 0.0589 m")
    min_correlative_score: float = Field(0.5, ge=0, le=1, description="reject before ICP when the best score in the window is below this (the bound also prunes the search). Of the spatial candidates verified at 0, those below 0.5 were Intel 29 %, MIT CSAIL 44 %, Freiburg hospital 83 %, and none of them was accepted (the accepted ones' 1st percentile: 0.56–0.59)")
    icp_sigma: float = Field(0.03, gt=0, description="a-priori range-point noise σ (m) for the χ² test")
    chi2_factor: float = Field(3.0, gt=0)
    min_fitness: float = Field(0.6, gt=0, le=1.0)
    max_rmse: float = Field(0.08, gt=0)
    max_rotation_sigma_deg: float | None = Field(0.12, gt=0, description="reject a closure whose ICP rotation σ (largest axis, from the Fisher information at icp_sigma, before the covariance floor) exceeds this (°): few or short-range points constrain its heading poorly, and such closures were most of the ones the final solution violates. Intel (slam loops --sweep max_rotation_sigma_deg=0.12:0.2:3): precision before pruning 93.6 % without, 99.1 / 98.3 / 98.0 % at 0.12 / 0.16 / 0.2, relation error 0.0157 → 0.0163 / 0.0161 / 0.0159 m; MIT CSAIL 0.0267 m either way; None = no check")
    max_mahalanobis: float = Field(6.0, gt=0, description="consistency of a spatial closure with the estimate (σ per degree of freedom, after the radius); a closure beyond it can still be accepted in a consistent group. slam loops --sweep max_mahalanobis=...: 15 / 6 gave precision before pruning 96.6 / 99.0 % on MIT CSAIL, 99.1 / 99.2 % on Intel (0.0163 / 0.0160 m), 100 % on the hospital (0.1256 / 0.1224 m)")
    group_min_size: int = Field(3, ge=0, description="closures that fail only the consistency test are accepted together when this many, from as many different keyframes within group_window_keyframes, agree with each other (0: never)")
    group_window_keyframes: int = Field(10, ge=1)
    group_delay_keyframes: int = Field(3, ge=0, description="a group is formed only from closures at least this many keyframes old, so that closures accepted on their own meanwhile can contradict it (MIT CSAIL: keyframes 892–894 offered a group 2.45 m off, one door along; 895–898 then closed on their own where the estimate was)")
    group_max_drift_fraction: float | None = Field(0.05, gt=0, description="such a closure joins a group only when the drift it implies, its translation from the estimate over the distance travelled between its two keyframes, is at most this fraction: a long loop's odometry drifts, a short stretch of corridor does not slide metres. MIT CSAIL: true returns 0.2–2.6 %, a door-periodic corridor's aliases 2.4 m off after 11–21 m, 12–22 %; None = no check")
    group_tolerance_m: float = Field(0.15, gt=0, description="pairwise agreement of two such closures: their cycle through the estimate's local relative poses within this (m) ...")
    group_tolerance_deg: float = Field(2.0, gt=0, description="... and this (°)")
    max_free_space_violation: float = Field(0.15, ge=0, le=1, description="2D: largest fraction of either scan's points inside the other's observed free space")
    global_search: bool = Field(True, description="2D: relocalisation against places the estimate cannot reach (Cartographer's global constraint search, Hess et al. 2016 §V): when old places lie within reach of the new keyframe's uncertainty but beyond the far search's, one of them (round robin) is searched whole — its local map of ±far_submap_keyframes, every heading — by branch and bound on a coarse likelihood field, then verified by ICP as any closure. A hit is never accepted alone: it becomes a hypothesis the next keyframes are verified against, and enters the graph only as a consistent group (group_min_size). The Freiburg hospital returns after 80 min with the estimate 25–45 m / 10–25° off, seeing the old corridors from 90–170° away (single-scan descriptors 0.56–0.95 apart)")
    global_min_sigma_m: float = Field(4.0, gt=0, description="... places whose position σ relative to the new keyframe exceeds this (the far search, base + radius_sigma_factor·σ up to far_max_radius_m, no longer covers them) ... A spatial candidate this uncertain is verified as usual but held like a global closure: the estimate cannot vouch for it")
    global_radius_sigma_factor: float = Field(3.0, gt=0, description="... and whose estimate lies within base + this × σ ...")
    global_max_radius_m: float = Field(100.0, gt=0, description="... at most this (m); position σ is tracked up to this too")
    global_every_keyframes: int = Field(2, ge=1, description="one place is searched every this many keyframes that have such places and no other closure")
    global_resolution_m: float = Field(0.2, gt=0, description="cell size (and σ) of the coarse likelihood field of the global search: the hospital's true returns score 0.56–0.83 at 0.2 m (0.1 m missed two of five), and a whole ±30 m, ±180° search takes 0.06–0.17 s")
    global_window_deg: float = Field(45.0, gt=0, le=180.0, description="heading window (±°) of the global search around the estimate's relative heading: the hospital's return was 25° off (3.7 × the graph's heading σ, which underestimates), and the wrong places that scored and passed ICP there were 50–180° off; ±45° costs a quarter of ±180°")
    global_max_free_space_violation: float = Field(0.3, ge=0, le=1, description="global closures: largest mean, over the two directions, of each scan's fraction of points in the other's observed free space (max_free_space_violation bounds each direction): 80 minutes apart, people and doors move — the hospital's true returns showed 0.01–0.42 one way, means 0.14–0.28, the wrong places 0.29–0.50")
    global_min_score: float = Field(0.55, ge=0, le=1, description="a global search hit must score this (mean likelihood) on the coarse field; places the scan does not see score 0.01–0.15")
    descriptor_min_fitness: float = Field(0.8, gt=0, le=1.0)
    descriptor_max_mahalanobis: float | None = Field(15.0, gt=0, description="a descriptor closure is rejected when it lies this many σ (per degree of freedom, as max_mahalanobis) from the graph's estimate of the two keyframes' relative pose, with that estimate's uncertainty relative to the new keyframe; None = no check. Descriptor closures before the check, in the final solutions: Intel 0 of 20, MIT CSAIL 0 of 4, Freiburg hospital 0 of 15 within 20 cm / 1° (all 5–28 m off)")
    robust_kernel: Literal["none", "huber", "cauchy", "gm"] = "cauchy"
    robust_scale: float = Field(1.0, gt=0, description="kernel width in whitened units (σ)")
    covariance_floor_m: float = Field(0.01, ge=0)
    covariance_floor_rad: float = Field(0.005, ge=0)
    prune_translation_m: float = Field(0.2, gt=0, description="after the final solve, drop closures violated by more than this ...")
    prune_rotation_deg: float = Field(1.0, gt=0, description="... or this, then solve again")
    prune_rounds: int = Field(3, ge=0, description="rounds of prune-and-solve after the final solve (ends early when no closure is violated)")


class BackendConfig(_Model):
    """Pose-graph back end: iSAM2 online + final batch LM (``gtsam``), or batch ``chordal``."""

    kind: Literal["gtsam", "chordal"] = "gtsam"
    isam2_relinearize_threshold: float = Field(0.01, gt=0)
    isam2_factorization: Literal["cholesky", "qr"] = Field("cholesky", description="iSAM2's linear solver; after the first 'indeterminate system' error the run restarts iSAM2 from a batch solution with QR and keeps it. Cholesky squares the condition number: on the Freiburg hospital's long odometry chain (millimetre wheel edges during turns in place) it failed from keyframe 2349 on, 13 restarts while it stayed Cholesky, and QR factored every later update; QR throughout costs Intel 13.4 s of back end against 9.8 s")
    final_batch: bool = True
    chordal_every_keyframes: int = Field(50, ge=1, description="chordal back end: batch re-solve period for the online estimate")


class MappingStageConfig(_Model):
    """Occupancy map from the keyframe scans: Fast-GPOM submaps built online, fused at the optimised poses.

    ``params.method`` ``gpom`` / ``logodds`` build the baseline maps from the keyframes at the final
    poses instead; ``params.resolution`` is the cell size.
    """

    enabled: bool = True
    max_range_m: float = Field(12.0, gt=0, description="beams are used up to this range; longer and no-return beams carve free space to it (GMapping's maxUrange)")
    keyframes_per_submap: int = Field(10, ge=1)
    submap_half_size_m: float = Field(12.0, gt=0, description="half side of a submap's square grid")
    recompose_every_keyframes: int = Field(50, ge=1, description="recompose the global map after an optimisation at most this often")
    params: MappingConfig = Field(default_factory=MappingConfig, description="GP / Fast-GPOM / squash parameters")
    height_band: tuple[float, float] = Field((-0.5, 1.5), description="3D logs: z band (m, sensor frame) sliced into the 2D map")
    virtual_beams: int = Field(720, ge=8, description="3D logs: beams of the virtual planar scan made from the height band")
    point_map_voxel: float = Field(0.2, gt=0, description="3D logs: voxel size of the PLY point map")


class SlamConfig(_Model):
    """Everything ``slam run`` needs besides the log."""

    odometry: OdometryStageConfig = OdometryStageConfig()
    keyframes: KeyframeConfig = KeyframeConfig()
    loops: LoopConfig = LoopConfig()
    backend: BackendConfig = BackendConfig()
    mapping: MappingStageConfig = MappingStageConfig()
    stage_processes: bool = Field(True, description="run the front end (odometry, keyframes) and the mapping stage each in its own process, beside loop closure and the back end; the results are the same either way")
    max_scans: int | None = Field(None, ge=1)
    on_error: Literal["stop", "skip"] = "stop"

    @classmethod
    def from_yaml(cls, path: str | Path) -> "SlamConfig":
        """Load from YAML; unknown keys and bad values raise ConfigError naming the file."""
        from registration.config import load_yaml

        return load_yaml(cls, path)  # type: ignore[return-value]

    def to_yaml(self) -> str:
        return yaml.safe_dump(self.model_dump(mode="json"), sort_keys=False)
