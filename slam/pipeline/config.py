"""Typed configuration of ``slam run`` (pydantic; loadable from YAML, dumped next to every output).

Distances are metres, angles radians, times seconds.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, model_validator

from mapping.config import MappingConfig
from registration.config import IcpConfig, IcpOdometryConfig, KissOdometryConfig
from slam.keyframes import KeyframeConfig
from slam.loops.config import LoopConfig


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid")


# The odometry defaults of the pipeline (docs/ODOMETRY.md has the evidence for each).
#: Planar scans, our ICP: point-to-line steps from the wheel guess through one 0.3 m gate with a Cauchy
#: kernel, a local map at 3 cm of 30 scans spaced 0.5 m or 0.2 rad apart (without wheels: the last 10 scans);
#: a step 0.3 m / 0.35 rad off the wheel guess is a failure; without wheels, a ±1 m / ±30° correlative search first,
#: whose widened search passes over a pose that contradicts the local map's free space by more than 15 %.
PLANAR_ICP = IcpOdometryConfig(
    icp=IcpConfig(gates_m=(0.3,), max_iterations=30, tol_translation_m=5e-4, tol_rotation_rad=5e-4, robust="cauchy",
                  robust_scale_m=0.05, workers=1),
    map_scans=30, unguided_map_scans=10, point_to_plane=True, map_voxel_m=0.03, map_step_m=0.5, map_step_rad=0.2,
    max_range_m=30.0, min_range_m=0.05, max_guess_deviation_m=0.3, max_guess_deviation_rad=0.35, alternative_start_m=0.05,
    alternative_start_rad=0.05, unguided_window_m=1.0, unguided_window_rad=float(np.radians(30.0)),
    unguided_max_contradiction=0.15)
#: 3D clouds, our ICP: coarse-to-fine gates on 0.5 m voxels against a 0.3 m local map of the last 10 scans.
SPATIAL_ICP = PLANAR_ICP.model_copy(update={
    "icp": IcpConfig(gates_m=(1.5, 0.6, 0.3), voxel_m=0.5, robust="cauchy", robust_scale_m=0.2),
    "map_scans": 10, "unguided_map_scans": None, "map_step_m": 0.0, "map_step_rad": 0.1, "map_voxel_m": 0.3,
    "max_range_m": 100.0, "unguided_window_m": None, "first_step_gate_m": 6.0})
#: KISS-ICP: its own defaults for 3D, the indoor planar ones (``KissOdometryConfig.planar_default``) to
#: 30 m for planar scans; the pipeline computes its own keyframe-edge covariance, so KISS's per-scan one is off.
PLANAR_KISS = KissOdometryConfig.planar_default().model_copy(update={"max_range_m": 30.0, "compute_covariance": False})
SPATIAL_KISS = KissOdometryConfig(compute_covariance=False)


def _merged(default: dict, given: dict) -> dict:
    """*given* over *default*, nested mappings merged key by key."""
    out = dict(default)
    for key, value in given.items():
        out[key] = _merged(out[key], value) if isinstance(value, dict) and isinstance(out.get(key), dict) else value
    return out


class OdometryStageConfig(_Model):
    """Which registration source gives odometry: ``kiss`` (KISS-ICP), ``icp`` (our scan-to-map SVD-ICP)
    or ``auto``, the measured choice per kind of frame — today our ICP for planar scans and 3D clouds alike
    (KISS-ICP's constant-velocity model loses track of a planar laser where the robot turns in place, and on
    real LiDAR frames its first steps from an empty map err by decimetres; ``docs/ODOMETRY.md``).
    Each source has its settings for planar scans and for 3D clouds (``icp_2d``, ``icp_3d``, ``kiss_2d``,
    ``kiss_3d``: ``registration.config``); every default is explained in ``docs/ODOMETRY.md`` with its
    evidence."""

    method: Literal["auto", "kiss", "icp"] = "auto"
    use_wheel_odometry: bool = Field(True, description="the log's wheel odometry predicts each scan's pose (else constant velocity)")
    deskew: bool = Field(True, description="planar scans whose beam times are known (the log's LaserScan.time_increment, or laser_revolution_s) are corrected for the motion during the sweep at the last increment's velocity (registration.deskew)")
    laser_revolution_s: float | None = Field(None, gt=0, description="a sensor quantity for logs that do not record beam times (CARMEN): the seconds a planar laser takes for one revolution (a Hokuyo URG-04LX 0.1, a UTM-30LX 0.025, a SICK LMS 2xx 1/75), its beam times counted from the first listed at the stamp (which way they run: beam_time_order); None: the log's own times, or none")
    beam_time_order: Literal["auto", "listed", "reversed"] = Field("auto", description="which way a planar laser took its beams against their listed times: auto reads it from the log's first scans before the run (registration.sweep_check; some drivers list a clockwise mirror's beams by increasing angle with the times the other way) and deskews only as the scans bear out; listed / reversed: as set")
    icp_2d: IcpOdometryConfig = Field(default_factory=lambda: PLANAR_ICP, description="our ICP odometry on planar scans")
    icp_3d: IcpOdometryConfig = Field(default_factory=lambda: SPATIAL_ICP, description="our ICP odometry on 3D clouds")
    kiss_2d: KissOdometryConfig = Field(default_factory=lambda: PLANAR_KISS, description="KISS-ICP on planar scans")
    kiss_3d: KissOdometryConfig = Field(default_factory=lambda: SPATIAL_KISS, description="KISS-ICP on 3D clouds")

    # Edge covariance: the Fisher information of the keyframe's scan against the previous keyframe's
    # at the odometry's relative pose (registration.covariance), with this residual σ and gate.
    edge_sigma_m: float = Field(0.02, gt=0, description="per-point residual σ of the keyframe-to-keyframe registration")
    edge_sigma_from_residuals: bool = Field(True, description="scale the edge covariance by max(1, σ̂²/σ²), σ̂ the scan's own residual σ (the a-posteriori variance factor: a long-range sparse laser fits at several times the σ of a short-range one)")
    edge_gate_m: float = Field(0.3, gt=0)
    edge_ambiguity_window_m: float | None = Field(1.0, gt=0, description="2D, a step no wheel edge backs, or whose smooth wheels fail the gate's test against it: its registration edge's covariance also covers the poses within ± this (m, x and y) whose keyframe-to-keyframe correlative score reaches edge_ambiguity_ratio of the best (a scan that slides along a corridor, or a second match), as their second moment about the odometry's pose, so that the wheel edge beside it holds a step the registration slid; None = the registration covariance alone")
    edge_ambiguity_ratio: float = Field(0.95, gt=0, le=1, description="... the fraction of the best score that counts as as good (the ratio test of place recognition; 0.8, 0.9 and 0.95 compared in docs/LOOP_CLOSURE.md)")
    edge_ambiguity_cell_m: float = Field(0.05, gt=0, description="... the likelihood-field cell (and σ) of that surface")
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
    wheel_sigma_m_per_rad: float = Field(0.15, ge=0, description="translation σ per radian turned (a turn in place moves the base a little; with 0 the model gives such a turn millimetres)")
    wheel_gate_probability: float | None = Field(0.999, gt=0, lt=1, description="a wheel edge whose disagreement with the registration edge exceeds this χ² quantile (Mahalanobis, both covariances) is left out: wheel odometry logged in lumps can say 0° over a keyframe the robot turned 40° in; None keeps every wheel edge")
    wheel_gate_lumpy_only: bool = Field(True, description="... but only when the wheels were lumpy in the interval (the ICP odometry took its constant-velocity start); over smooth wheels the registration slid (a corridor), and the wheel edge stays")
    wheel_calibration: bool = Field(True, description="scale the wheel model per block (translation, rotation) online so that the wheel-vs-registration disagreement has its expected χ² mean, per keyframe interval and, for the heading, summed over runs of consecutive intervals (slam.noise_scale); the fitted scales are in summary.json (odometry_stats)")
    wheel_calibration_min_edges: int = Field(50, ge=1, description="wheel edges before the calibration starts (until then the model as configured)")


    @model_validator(mode="before")
    @classmethod
    def _onto_pipeline_defaults(cls, data: object) -> object:
        """A partial ``icp_2d`` (…) given as a mapping changes the pipeline's defaults above, not the
        registration model's own: ``icp_2d: {icp: {gates_m: [0.5]}}`` keeps every other planar setting."""
        if not isinstance(data, dict):
            return data
        data = dict(data)
        for name, default in (("icp_2d", PLANAR_ICP), ("icp_3d", SPATIAL_ICP), ("kiss_2d", PLANAR_KISS),
                              ("kiss_3d", SPATIAL_KISS)):
            if isinstance(data.get(name), dict):
                data[name] = _merged(default.model_dump(), data[name])
        return data


class BackendConfig(_Model):
    """Pose-graph back end: iSAM2 online + final batch LM (``gtsam``), or batch ``chordal``."""

    kind: Literal["gtsam", "chordal"] = "gtsam"
    isam2_relinearize_threshold: float = Field(0.01, gt=0)
    isam2_factorization: Literal["cholesky", "qr"] = Field("cholesky", description="iSAM2's linear solver; after the first 'indeterminate system' error the run restarts iSAM2 from a batch solution with QR and keeps it (Cholesky squares the condition number; QR throughout costs about 40 % more back-end time)")
    final_batch: bool = True
    lone_odometry_kernel_sigmas: float | None = Field(3.0, gt=0, description="Cauchy kernel, threshold in σ, on a scan-registration edge of a step no wheel odometry measured (a log without it, or wheel_edges off): a match that slid along a corridor, whose covariance still claims centimetres, then yields to the loop closures; None = no kernel. Steps the wheels measured keep no kernel, even where their wheel edge was left out as lumpy (there the registration was preferred)")
    chordal_every_keyframes: int = Field(50, ge=1, description="chordal back end: batch re-solve period for the online estimate")
    variance_components: bool = Field(False, description="after the final solve and its pruning, scale the translation and rotation variance of each edge group (registration, wheels, closures) so that the solution's residuals match their redundancy (variance-component estimation, Förstner 1979; slam.backends.variance_components) and solve again under those covariances without kernels (the pruned closures are the inliers); a group with fewer than 20 redundant observations keeps its model, and nothing changes while the closures give fewer. The scales go to summary.json (variance_components) and graph.g2o holds the scaled covariances. Off by default: it assumes independent errors, which the registration's jitter and closures on one local map are not, and it makes some runs worse (docs/LOOP_CLOSURE.md, \"How sure the edges are\")")


class MappingStageConfig(_Model):
    """Occupancy map from the keyframe scans: Fast-GPOM submaps built online, fused at the optimised poses.

    ``params.method`` ``gpom`` / ``logodds`` build the baseline maps from the keyframes at the final
    poses instead; ``params.resolution_m`` is the cell size.
    """

    enabled: bool = True
    max_range_m: float = Field(12.0, gt=0, description="beams are used up to this range; longer and no-return beams carve free space to it (GMapping's maxUrange)")
    keyframes_per_submap: int = Field(10, ge=1)
    submap_half_size_m: float = Field(12.0, gt=0, description="half side of a submap's square grid")
    recompose_every_keyframes: int = Field(50, ge=1, description="recompose the global map after an optimisation at most this often")
    params: MappingConfig = Field(default_factory=MappingConfig, description="GP / Fast-GPOM / squash parameters")
    height_band_m: tuple[float, float] = Field((-0.5, 1.5), description="3D logs: z band (sensor frame) sliced into the 2D map")
    virtual_beams: int = Field(720, ge=8, description="3D logs: beams of the virtual planar scan made from the height band")
    point_map_voxel_m: float = Field(0.2, gt=0, description="3D logs: voxel size of the PLY point map")


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
        from core.yaml_config import load_yaml

        return load_yaml(cls, path)  # type: ignore[return-value]

    def to_yaml(self) -> str:
        return yaml.safe_dump(self.model_dump(mode="json"), sort_keys=False)
