"""Point-to-plane ICP (Chen & Medioni 1992) with PCA normals, for 3D LiDAR (2D works too).

Each iteration minimises Σ w_i (n_iᵀ(T p'_i − q_i))² linearised about the current pose with a left
increment ``T ← Exp(ξ) T`` (Low 2004, "Linear least-squares optimization for point-to-plane ICP"):
row i of the Jacobian is ``[n_iᵀ, (m_i × n_i)ᵀ]`` for the moved point m_i. Normals are
the eigenvectors of the smallest eigenvalue of the k-neighbour scatter matrix (Hoppe et al. 1992).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from core import geometry as geo
from core.errors import DegenerateInputError
from core.geometry import se3_exp

from . import alignment
from .alignment import IcpResult, as_target, evaluate_matches, prepare, robust_weights
from .config import IcpConfig
from .matching import INCREMENTAL_MIN_POINTS, IncrementalMatcher
from .target import IcpTarget, gated_nearest

Array = NDArray[np.float64]

__all__ = ["PosePrior", "icp_point_to_plane"]


@dataclass(frozen=True)
class PosePrior:
    """A Gaussian prior on the ICP pose: ``Log(pose⁻¹ · T)`` (the error in T's own frame, translation
    first) has information *information*, in units of one unit-weight point residual: a prior of
    σ_prior on an axis, for point residuals of σ_point, has information (σ_point / σ_prior)²."""

    pose: Array  # 4×4, the prior mean (e.g. the wheel-odometry prediction)
    information: Array  # (3, 3) planar (x, y, θ) or (6, 6) (ρ, φ)


def icp_point_to_plane(source: ArrayLike, target: ArrayLike | IcpTarget, init: ArrayLike | None = None,
                       config: IcpConfig | None = None, prior: PosePrior | None = None) -> IcpResult:
    """Point-to-plane ICP of *source* onto *target*; same arguments and result as :func:`registration.icp.icp`.

    With a *prior*, each Gauss-Newton step minimises the point-to-plane cost plus the prior's
    (a maximum-a-posteriori step): along directions the scan leaves unconstrained, such as the axis
    of a featureless corridor, the pose stays near the prior instead of drifting; elsewhere the
    points outweigh it. (The soft form of the degeneracy remedy of Zhang, Kaess & Singh, "On
    degeneracy of optimization-based state estimation problems", ICRA 2016, with the motion model
    as the prior, as in Cartographer's scan matcher, Hess et al. 2016, §IV-C.) The covariance of
    the result uses the plane model, without the prior, whatever ``config.covariance_model`` says.
    """
    config = (config or IcpConfig()).model_copy(update={"covariance_model": "plane"})
    tgt = as_target(target, config)
    S, T = prepare(source, tgt, init, config)
    d = tgt.dim
    if d == 2 and prior is None and alignment.COMPILED_2D and config.robust in alignment.ROBUST_CODES:
        return _icp_plane_2d_compiled(S, tgt, T, config)
    if d == 3 and prior is None and alignment.COMPILED_3D and config.robust in alignment.ROBUST_CODES:
        return _icp_plane_3d_compiled(S, tgt, T, config)
    n_tgt = len(tgt.points)
    matcher = IncrementalMatcher(tgt.tree, config.workers, incremental=len(S) >= INCREMENTAL_MIN_POINTS)
    robust = config.robust != "none"
    it = 0
    converged = False
    R, t = T[:d, :d].copy(), T[:d, 3].copy()
    moved = None  # the source moved by the current pose, when already computed
    for gate in config.gates_m:
        converged = False
        while it < config.max_iterations:
            it += 1
            moved = S @ R.T + t
            idx = matcher.match(moved, gate)
            if idx[-1] < n_tgt and idx.max() < n_tgt:  # every point matched: no mask copies
                m, i_in = moved, idx
            else:
                ok = np.flatnonzero(idx < n_tgt)
                if len(ok) < config.min_inliers:
                    raise DegenerateInputError(
                        f"point-to-plane ICP iteration {it}: {len(ok)} pairs within {gate} m (need {config.min_inliers})")
                m, i_in = moved.take(ok, axis=0), idx.take(ok)
            n = tgt.normals(i_in)
            e = np.einsum("ij,ij->i", m - tgt.points.take(i_in, axis=0), n)
            J = _plane_rows(m, n)
            if robust:
                Jw = J * robust_weights(np.abs(e), config)[:, None]
            else:
                Jw = J
            H, g = J.T @ Jw, Jw.T @ e
            if prior is not None:
                H, g = _add_prior(H, g, prior, R, t, d)
            try:
                xi = np.linalg.solve(H, -g)
            except np.linalg.LinAlgError as exc:
                raise DegenerateInputError(f"point-to-plane ICP iteration {it}: singular normal equations") from exc
            if d == 2:
                R, t = _apply_se2_left(xi, R, t)
            else:
                E = se3_exp(xi)
                R, t = E[:3, :3] @ R, E[:3, :3] @ t + E[:3, 3]
            moved = None
            if np.linalg.norm(xi[: d]) < config.tol_translation_m and np.linalg.norm(xi[d:]) < config.tol_rotation_rad:
                converged = True
                break
    T = np.eye(4)
    T[:d, :d], T[:d, 3] = R, t
    if moved is None:
        moved = S @ R.T + t
    gate = config.gates_m[-1]
    return evaluate_matches(S, tgt, T, moved, matcher.match(moved, gate), gate, config, it, converged)


def _icp_plane_2d_compiled(S: Array, tgt: IcpTarget, T: Array, config: IcpConfig) -> IcpResult:
    """The 2D iterations above, compiled (:func:`registration.kernels_icp.plane_icp_2d`), then the same evaluation."""
    from . import kernels_icp

    g = tgt.grid
    R, t, it, converged, status, stage, pairs = kernels_icp.plane_icp_2d(
        *alignment.compiled_loop_args(S, T, config, 2), tgt._normals, tgt._have,
        min(tgt.normal_neighbors, len(tgt.points)), g.points, *g.args())
    _refuse(status, it, pairs, stage, config)
    T = np.eye(4)
    T[:2, :2], T[:2, 3] = R, t
    moved = S @ R.T + t
    gate = config.gates_m[-1]
    return evaluate_matches(S, tgt, T, moved, gated_nearest(tgt, moved, gate), gate, config, it, converged)


def _icp_plane_3d_compiled(S: Array, tgt: IcpTarget, T: Array, config: IcpConfig) -> IcpResult:
    """The 3D iterations above, compiled (:func:`registration.kernels_icp3d.plane_icp_3d`: the same nearest
    neighbours and PCA normals on a hashed voxel grid instead of the k-d tree), then the same evaluation."""
    from . import kernels_icp3d

    g = tgt.grid3
    R, t, it, converged, status, stage, pairs, idx = kernels_icp3d.plane_icp_3d(
        *alignment.compiled_loop_args(S, T, config, 3), tgt._normals, tgt._have,
        min(tgt.normal_neighbors, len(tgt.points)), g.points, *g.args())
    _refuse(status, it, pairs, stage, config)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    moved = S @ R.T + t
    return evaluate_matches(S, tgt, T, moved, idx, config.gates_m[-1], config, it, converged)


def _add_prior(H: Array, g: Array, prior: PosePrior, R: Array, t: Array, d: int) -> tuple[Array, Array]:
    """Normal equations plus the prior's terms: its error e = Log(P⁻¹T) moves by Ad_{T⁻¹} ξ under the left
    increment T ← Exp(ξ)T, so H += AᵀΛA and g += AᵀΛe with A = Ad_{T⁻¹}."""
    T = np.eye(4)
    T[:d, :d], T[:d, 3] = R, t
    E = geo.relative(prior.pose, T)
    e = geo.se2_log(E) if d == 2 else geo.se3_log(E)
    A = geo.adjoint(geo.inverse(T), planar=d == 2)
    AL = A.T @ prior.information
    return H + AL @ A, g + AL @ e


def _plane_rows(m: Array, n: Array) -> Array:
    """Jacobian rows ``[nᵀ, (m × n)ᵀ]`` of nᵀ(m − q) under a left increment of the moved points *m*."""
    d = m.shape[1]
    J = np.empty((len(m), 3 if d == 2 else 6))
    J[:, :d] = n
    if d == 2:
        J[:, 2] = m[:, 0] * n[:, 1] - m[:, 1] * n[:, 0]
    else:
        J[:, 3:] = np.cross(m, n)
    return J


def _apply_se2_left(xi: Array, R: Array, t: Array) -> tuple[Array, Array]:
    """``Exp(ξ) · (R, t)`` for ξ = (ρx, ρy, θ) — :func:`core.geometry.se2_exp` in scalar form
    (this runs once per ICP iteration, where numpy's per-call overhead would dominate)."""
    rx, ry, th = float(xi[0]), float(xi[1]), float(xi[2])
    c, s = math.cos(th), math.sin(th)
    if abs(th) < 1e-9:
        a, b = 1.0 - th * th / 6.0, th / 2.0
    else:
        a, b = s / th, (1.0 - c) / th
    ex, ey = a * rx - b * ry, b * rx + a * ry
    E = np.array([[c, -s], [s, c]])
    return E @ R, E @ t + (ex, ey)


def _refuse(status: int, it: int, pairs: int, stage: int, config: IcpConfig) -> None:
    """The numpy loop's errors for a compiled loop's *status* (1: too few pairs, 2: singular normal equations)."""
    if status == 1:
        raise DegenerateInputError(f"point-to-plane ICP iteration {it}: {pairs} pairs within "
                                   f"{config.gates_m[stage]} m (need {config.min_inliers})")
    if status == 2:
        raise DegenerateInputError(f"point-to-plane ICP iteration {it}: singular normal equations")
