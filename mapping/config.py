"""Mapping configuration (pydantic, loadable from YAML). Distances in metres."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid")  # a misspelt key is an error, not a silent default


class GPConfig(_Model):
    """GP kernel and hyperparameter policy (Yuan et al. 2018 §IV: Matérn ν = 7/2, fitted on frame 1)."""

    nu: float = 3.5
    hyperparameters: Literal["fit_first_frame", "fixed"] = "fit_first_frame"
    #: start values of the fit, or the values used when ``fixed`` (the reference code's constants)
    length_scale_m: float = 1.90
    sigma_f: float = 8.13
    sigma_n: float = 0.226
    #: at most this many training samples (thinned by beam) enter the marginal-likelihood fit
    fit_max_points: int = 600
    fit_restarts: int = 1


class FastGPOMConfig(_Model):
    """Fast-GPOM (Yuan et al. 2018, Alg. 3)."""

    free_step_m: float | None = Field(None, description="d, spacing of free samples along a beam (m); None = resolution_m")
    stop_before_hit: float = Field(1.5, description="free samples stop this many d before the hit")
    region_a_mean: float = -1.0
    region_a_variance: float = 0.1
    #: local GP blocks: beams per block and beams of overlap on each side (locality, see README)
    block_beams: int = 16
    block_overlap: int = 8
    #: ring samples of every n-th beam train the local GPs (cells of all beams are predicted)
    train_beam_stride: int = 2
    exact_gp: bool = Field(False, description="one GP over all ring samples instead of the local blocks")


class GPOMConfig(_Model):
    """Classic GPOM (O'Callaghan & Ramos 2012; Yuan et al. 2018 Alg. 2)."""

    #: the exact GP costs O(n³ + n²·cells) per scan: every 12th beam and free samples every 0.3 m keep
    #: n ≈ 250–450 training points for the 667-beam laser (see mapping/README.md)
    free_step_m: float = 0.3
    stop_before_hit: float = 1.5
    beam_stride: int = 12


class LogOddsConfig(_Model):
    """Log-odds occupancy grid with an inverse sensor model (Thrun et al., Prob. Robotics §9.2)."""

    l_occ: float = 0.85
    l_free: float = -0.4
    l_min: float = -5.0
    l_max: float = 5.0


class MappingConfig(_Model):
    method: Literal["fastgpom", "gpom", "logodds"] = "fastgpom"
    resolution_m: float = 0.05
    #: probit squash p = Φ((αμ + β)/√(1 + α²σ²)) (Yuan et al. 2018 eq. 6)
    squash_alpha: float = 100.0
    squash_beta: float = 0.0
    #: ROS export thresholds on p
    occupied_thresh: float = 0.65
    free_thresh: float = 0.35
    gp: GPConfig = GPConfig()
    fastgpom: FastGPOMConfig = FastGPOMConfig()
    gpom: GPOMConfig = GPOMConfig()
    logodds: LogOddsConfig = LogOddsConfig()
