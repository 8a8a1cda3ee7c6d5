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
from slam.loops.config import LoopConfig


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid")


class OdometryStageConfig(_Model):
    """Which registration source gives odometry: ``kiss`` (KISS-ICP), ``icp`` (our scan-to-map SVD-ICP)
    or ``auto`` — KISS-ICP for 3D clouds, our ICP for planar scans (KISS-ICP's constant-velocity model
    loses track of a planar laser where the robot turns in place; measurements in ``docs/ODOMETRY.md``).
    Every default below is explained there with its evidence."""

    method: Literal["auto", "kiss", "icp"] = "auto"
    use_wheel_odometry: bool = True
    icp_point_to_plane: bool = Field(True, description="our ICP odometry: point-to-line/plane steps instead of point-to-point")
    icp_gates_m: tuple[float, ...] = Field((0.3,), description="2D, our ICP odometry: correspondence gates, coarse to fine, from the wheel guess")
    icp_tolerance: float = Field(5e-4, gt=0, description="2D, our ICP odometry: a gate stage ends when the pose increment is below this (m and rad)")
    icp_map_step_m: float = Field(0.0, ge=0, description="our ICP odometry: a scan joins the local map after this much motion (0 = every scan) ...")
    icp_max_guess_deviation_m: float | None = Field(0.3, gt=0, description="our ICP odometry: a step this far from the wheel guess is a failure ...")
    icp_max_guess_deviation_rad: float | None = Field(0.35, gt=0, description="... or turned this much more; the wheel guess is kept")
    icp_alternative_start_m: float | None = Field(0.05, gt=0, description="our ICP odometry: when the wheel increment differs by more than this (or the angle below) both from the last estimated increment and from the previous wheel increment (wheel odometry logged in lumps), ICP also starts from the last increment and the clearly better fit wins")
    icp_alternative_start_rad: float | None = Field(0.05, gt=0)
    icp_map_step_rad: float = Field(0.1, gt=0, description="... or this much turning (the map's k-d tree is rebuilt only then)")
    icp_wheel_prior_sigma: float | None = Field(None, gt=0, description="our ICP odometry with smooth wheel odometry: the wheel prediction enters each ICP step as a prior with the wheel_sigma_* model below (floors 1 cm, 5 mrad), weighed against point residuals of this σ (m); None = no prior (the default: it helps short stretches but lets drift grow, see docs/ODOMETRY.md)")
    unguided_window_m: float | None = Field(1.0, gt=0, description="2D, our ICP odometry without wheel odometry: each scan is first placed by a correlative search of ± this (m, x and y) around the constant-velocity guess on the local map, as far as the robot may stray from constant velocity between two scans; None = ICP from the guess alone")
    unguided_window_deg: float = Field(30.0, gt=0, description="... and ± this in heading (degrees)")
    max_range_m: float = Field(30.0, gt=0, description="2D: beams beyond this are ignored for registration")
    min_range_m: float = Field(0.05, ge=0, description="2D: beams shorter than this are ignored for registration")
    # Edge covariance: the Fisher information of the keyframe's scan against the previous keyframe's
    # at the odometry's relative pose (registration.covariance), with this residual σ and gate.
    edge_sigma_m: float = Field(0.02, gt=0, description="per-point residual σ of the keyframe-to-keyframe registration")
    edge_sigma_from_residuals: bool = Field(True, description="scale the edge covariance by max(1, σ̂²/σ²), σ̂ the scan's own residual σ (the a-posteriori variance factor: a long-range sparse laser fits at several times the σ of a short-range one)")
    edge_gate_m: float = Field(0.3, gt=0)
    edge_ambiguity_window_m: float | None = Field(1.0, gt=0, description="2D, a step no wheel edge backs (no wheel odometry, or lumpy wheels the gate left out): its edge covariance also covers the poses within ± this (m, x and y) whose keyframe-to-keyframe correlative score reaches edge_ambiguity_ratio of the best (a scan that slides along a corridor, or a second match), as their second moment about the odometry's pose; None = the registration covariance alone")
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
    wheel_calibration: bool = Field(True, description="scale the wheel model per block (translation, rotation) online so that the wheel-vs-registration disagreement has its expected χ² mean (slam.noise_scale); the fitted scales are in summary.json (odometry_stats)")
    wheel_calibration_min_edges: int = Field(50, ge=1, description="wheel edges before the calibration starts (until then the model as configured)")


class BackendConfig(_Model):
    """Pose-graph back end: iSAM2 online + final batch LM (``gtsam``), or batch ``chordal``."""

    kind: Literal["gtsam", "chordal"] = "gtsam"
    isam2_relinearize_threshold: float = Field(0.01, gt=0)
    isam2_factorization: Literal["cholesky", "qr"] = Field("cholesky", description="iSAM2's linear solver; after the first 'indeterminate system' error the run restarts iSAM2 from a batch solution with QR and keeps it (Cholesky squares the condition number; QR throughout costs about 40 % more back-end time)")
    final_batch: bool = True
    lone_odometry_kernel_sigmas: float | None = Field(3.0, gt=0, description="Cauchy kernel, threshold in σ, on a scan-registration edge of a step no wheel odometry measured (a log without it, or wheel_edges off): a match that slid along a corridor, whose covariance still claims centimetres, then yields to the loop closures; None = no kernel. Steps the wheels measured keep no kernel, even where their wheel edge was left out as lumpy (there the registration was preferred)")
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
