"""Typed configuration of ICP and odometry (pydantic models; YAML through :mod:`core.yaml_config`).

Distances are metres, angles radians. The models are frozen so a config cannot change under a
running estimator; use ``model_copy(update=...)`` to derive variants.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

__all__ = ["IcpConfig", "KissOdometryConfig", "IcpOdometryConfig"]


class _Frozen(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")


class IcpConfig(_Frozen):
    """SVD-ICP (Besl & McKay 1992) and point-to-plane ICP (Chen & Medioni 1992) settings.

    Attributes:
        gates_m: coarse-to-fine correspondence gates (m): pairs farther apart than the current gate
            are ignored; each stage runs to convergence before the next, smaller gate.
        max_iterations: iteration cap over all stages.
        tol_translation_m: convergence when the pose increment is below this (m) ...
        tol_rotation_rad: ... and below this (rad).
        voxel_m: voxel subsampling of the source before matching (m); None = off.
        target_voxel_m: voxel subsampling of the target (m); None = off.
        robust: ``none`` (all gated pairs weight 1), ``trim`` (keep the ``trim_fraction`` closest
            pairs), ``huber`` or ``cauchy`` (IRLS weights with scale ``robust_scale_m``).
        sigma_m: a-priori residual standard deviation per scalar residual (m); None = estimate it
            from the residual as σ̂² = Res / (n − dof) (then the χ² test cannot reject).
        chi2_factor: reject when Res > chi2_factor · (n − dof) · σ² (the course's rule uses 3).
        false_rejection_rate: if set, the threshold is instead the (1 − α) quantile of
            σ² χ²(n − dof), so correct alignments are rejected at rate α.
        covariance_model: Fisher information of the ``plane`` cost (residuals along the target
            surface normal: the Hessian of the nearest-neighbour distance field) or of the
            ``point`` cost (fixed correspondences, all coordinates).
        normal_neighbors: neighbours used for PCA normals (point-to-plane and plane covariance).
        workers: cKDTree query threads (-1 = all cores).
    """

    gates_m: tuple[float, ...] = (1.0, 0.5, 0.25)
    max_iterations: int = 100
    tol_translation_m: float = 1e-6
    tol_rotation_rad: float = 1e-7
    voxel_m: float | None = None
    target_voxel_m: float | None = None
    robust: Literal["none", "trim", "huber", "cauchy"] = "none"
    trim_fraction: float = Field(0.9, gt=0.0, le=1.0)
    robust_scale_m: float = Field(0.1, gt=0.0)
    sigma_m: float | None = Field(None, gt=0.0)
    chi2_factor: float = Field(3.0, gt=0.0)
    false_rejection_rate: float | None = Field(None, gt=0.0, lt=1.0)
    covariance_model: Literal["plane", "point"] = "plane"
    normal_neighbors: int = Field(10, ge=3)
    min_inliers: int = Field(10, ge=3)
    workers: int = -1

    @field_validator("gates_m")
    @classmethod
    def _gates_positive(cls, v: tuple[float, ...]) -> tuple[float, ...]:
        if len(v) == 0 or any(g <= 0 for g in v):
            raise ValueError("gates must be a non-empty list of positive distances")
        return tuple(float(g) for g in v)


class KissOdometryConfig(_Frozen):
    """Our settings for KISS-ICP (Vizzo et al., RA-L 2023), mapped onto ``kiss_icp.config.KISSConfig``.

    For planar lasers (points with z = 0) deskewing is forced off (CARMEN scans carry no per-beam
    time and the sweep is short). ``voxel_m`` None means KISS-ICP's own rule ``max_range_m / 100``.
    """

    max_range_m: float = Field(100.0, gt=0.0)
    min_range_m: float = Field(0.0, ge=0.0)
    deskew: bool = True
    voxel_m: float | None = Field(None, gt=0.0)
    max_points_per_voxel: int = Field(20, ge=1)
    initial_threshold_m: float = Field(2.0, gt=0.0)
    min_motion_m: float = Field(0.1, ge=0.0)
    fixed_threshold_m: float | None = Field(None, gt=0.0)
    max_num_iterations: int = Field(500, ge=1)
    convergence_criterion: float = Field(1e-4, gt=0.0)
    max_num_threads: int = Field(0, ge=0)
    compute_covariance: bool = True
    covariance_sigma_m: float | None = Field(None, gt=0.0)

    @model_validator(mode="after")
    def _ranges(self) -> "KissOdometryConfig":
        if self.min_range_m >= self.max_range_m:
            raise ValueError(f"min_range_m {self.min_range_m} must be below max_range_m {self.max_range_m}")
        return self

    @classmethod
    def planar_default(cls) -> "KissOdometryConfig":
        """Indoor 2D laser defaults: 20 m range, 10 cm voxels with ≤ 5 points, no deskew, one thread.

        One thread is ~5× faster than TBB's automatic pool for scans of a few hundred beams, and 20 m /
        5 points per voxel keep the local map small (``benchmarks/registration.py``, docs/ODOMETRY.md).
        """
        return cls(max_range_m=20.0, min_range_m=0.1, deskew=False, voxel_m=0.1, max_points_per_voxel=5,
                   initial_threshold_m=0.5, min_motion_m=0.02, max_num_threads=1)

    def to_kiss(self, planar: bool):
        """The equivalent ``kiss_icp.config.KISSConfig`` (deskew off when *planar*)."""
        from kiss_icp.config import KISSConfig
        from kiss_icp.config.config import AdaptiveThresholdConfig, DataConfig, MappingConfig, RegistrationConfig

        return KISSConfig(
            data=DataConfig(max_range=self.max_range_m, min_range=self.min_range_m, deskew=self.deskew and not planar),
            mapping=MappingConfig(voxel_size=self.voxel_m if self.voxel_m is not None else self.max_range_m / 100.0,
                                  max_points_per_voxel=self.max_points_per_voxel),
            registration=RegistrationConfig(max_num_iterations=self.max_num_iterations,
                                            convergence_criterion=self.convergence_criterion,
                                            max_num_threads=self.max_num_threads),
            adaptive_threshold=AdaptiveThresholdConfig(fixed_threshold=self.fixed_threshold_m,
                                                       initial_threshold=self.initial_threshold_m,
                                                       min_motion_th=self.min_motion_m),
        )


class IcpOdometryConfig(_Frozen):
    """Scan-to-local-map SVD-ICP odometry: the map is ``map_scans`` scans in world frame, spaced along the path."""

    icp: IcpConfig = IcpConfig(gates_m=(0.5, 0.2, 0.1), voxel_m=0.05, robust="trim", trim_fraction=0.9)
    map_scans: int = Field(10, ge=1)
    #: a scan registered without the wheel guess (no wheel odometry) joins the map whatever map_step_m says, and
    #: its map is the last unguided_map_scans scans; None = as one registered with it
    unguided_map_scans: int | None = Field(None, ge=1)
    #: point-to-plane (point-to-line in 2D, Chen & Medioni 1992) instead of point-to-point SVD steps:
    #: no bias towards zero motion where the scan samples the surfaces differently than the map
    point_to_plane: bool = False
    map_voxel_m: float = Field(0.05, gt=0.0)
    #: a scan joins the local map when the sensor moved ≥ map_step_m or turned ≥ map_step_rad since the
    #: last one that did (0 = every scan); the map's k-d tree is rebuilt only then
    map_step_m: float = Field(0.0, ge=0.0)
    map_step_rad: float = Field(0.1, gt=0.0)
    max_range_m: float = Field(30.0, gt=0.0)
    min_range_m: float = Field(0.0, ge=0.0)
    #: with wheel odometry as the guess: an ICP increment further than this from it (m, rad) is a
    #: registration failure (e.g. a wrong basin in a featureless stretch) and the guess is kept instead
    max_guess_deviation_m: float | None = Field(None, gt=0.0)
    max_guess_deviation_rad: float | None = Field(None, gt=0.0)
    #: wheel odometry that arrives in lumps (a few scans of zero motion, then the whole turn at once) is a
    #: wrong guess twice. When the wheel increment differs by more than this
    #: (m, rad) from the constant-velocity one (the last ICP increment) and from the previous wheel
    #: increment, ICP also runs from the former; a result that stayed near its own start beats one
    #: that left it, else the clearly larger inlier fraction (by ``alternative_start_min_gain``) wins.
    alternative_start_m: float | None = Field(None, gt=0.0)
    alternative_start_rad: float | None = Field(None, gt=0.0)
    alternative_start_min_gain: float = Field(0.05, ge=0.0)
    #: point-to-plane with smooth wheel odometry: a Gaussian prior at the wheel prediction enters every
    #: ICP step (registration.point_to_plane.PosePrior), with σ = prior_sigma_m + prior_sigma_per_m · d
    #: per axis of translation and prior_sigma_rad + prior_sigma_rad_per_m · d + prior_sigma_rad_per_rad · |Δθ|
    #: of rotation for a wheel step of d metres and Δθ radians, against point residuals of
    #: prior_point_sigma_m; None = no prior. Holds the pose along a featureless corridor.
    prior_point_sigma_m: float | None = Field(None, gt=0.0)
    prior_sigma_m: float = Field(0.01, gt=0.0)
    prior_sigma_per_m: float = Field(0.1, ge=0.0)
    prior_sigma_rad: float = Field(0.005, gt=0.0)
    prior_sigma_rad_per_m: float = Field(0.08, ge=0.0)
    prior_sigma_rad_per_rad: float = Field(0.1, ge=0.0)
    #: 2D without wheel odometry: the constant-velocity guess says little when the robot accelerates or
    #: the log keeps only some scans, so the scan is first placed by a correlative branch-and-bound search
    #: of ± unguided_window_m (x and y) and ± unguided_window_rad around it on the local map's likelihood
    #: field (cells of unguided_resolution_m; Olson 2009, Hess et al. 2016 §IV), and ICP starts from
    #: the best pose when it scores better than the guess; None = ICP from the guess alone
    unguided_window_m: float | None = Field(None, gt=0.0)
    unguided_window_rad: float | None = Field(None, gt=0.0)
    unguided_resolution_m: float = Field(0.05, gt=0.0)
    #: When the best pose scores below unguided_escalation × the median of the last scans' scores (the
    #: robot turned or jumped beyond the window between two kept scans), the search is repeated over
    #: twice the distance and every heading, around the guess and around the last pose; its result is
    #: kept when it scores better by the same factor. None = never.
    unguided_escalation: float | None = Field(0.8, gt=0.0, le=1.0)
    #: A candidate of the widened search is passed over while another does not contradict the local map:
    #: the larger mean fraction of its points in the map scans' observed free space, or of theirs in its own,
    #: above this (negative information, Olson 2009 §III-B; the loop verifier's and the self-check's limit).
    #: None = candidates by score alone.
    unguided_max_contradiction: float | None = Field(None, gt=0.0, le=1.0)
    #: The first registration without wheel odometry has no velocity to start from: a log that begins in
    #: motion is a whole scan interval's travel away from the identity guess (3 m at 30 m/s and 10 Hz),
    #: beyond the first gate. That step runs this gate before the configured ones (m; KISS-ICP's first
    #: frames correspond over 3 × its 2 m initial threshold); None = the configured gates alone.
    first_step_gate_m: float | None = Field(None, gt=0.0)
