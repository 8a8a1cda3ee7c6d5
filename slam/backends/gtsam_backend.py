"""GTSAM back end: batch Levenberg-Marquardt / Gauss-Newton and an incremental iSAM2 session.

Factors (Dellaert & Kaess, "Factor graphs for robot perception", FnT 2017, §2): every edge becomes a
``BetweenFactorPose2/Pose3`` (error ``Log(Z⁻¹ X_i⁻¹ X_j)``, right perturbation) or a ``PriorFactorPose2/3``
with Gaussian noise built from the edge's information matrix. Our information is ordered translation
first (docs/ARCHITECTURE.md); Pose2's tangent is already ``(x, y, θ)`` and Pose3's is ``(rx, ry, rz, x, y, z)``,
so 3D information is permuted. Robust kernels (Huber, Cauchy, Geman-McClure; Zhang, "Parameter estimation
techniques", IVC 1997) wrap the Gaussian noise of chosen edges with ``noiseModel.Robust``. The gauge is fixed
by a tight prior on the anchored nodes (:meth:`PoseGraph.anchor_indices`) unless the graph has priors.
iSAM2: Kaess et al., "iSAM2: Incremental smoothing and mapping using the Bayes tree", IJRR 2012.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from core import geometry as geo
from core import pose_formats
from slam.graph.posegraph import PRIOR_NODE, GraphError, PoseGraph, RobustKernel

Array = NDArray[np.float64]

__all__ = [
    "GtsamResult",
    "optimize",
    "build_factor_graph",
    "refuse_indefinite",
    "to_values",
    "from_values",
    "noise_model",
    "IncrementalSmoother",
    "ANCHOR_SIGMA",
]

ANCHOR_SIGMA = 1e-6  # m / rad: the gauge prior on anchored nodes (contributes ~0 error at any solution)
_P3 = np.array([3, 4, 5, 0, 1, 2])  # (x, y, z, rx, ry, rz) → GTSAM's (rx, ry, rz, x, y, z)


def to_gtsam_information(info: ArrayLike, dim: int) -> Array:
    """Reorder an information (or covariance) matrix from our tangent order to GTSAM's."""
    M = np.asarray(info, dtype=float)
    return M if dim == 2 else M[np.ix_(_P3, _P3)]


def from_gtsam_covariance(cov: ArrayLike, dim: int) -> Array:
    """Reorder a GTSAM marginal covariance to our (translation-first) order."""
    M = np.asarray(cov, dtype=float)
    if dim == 2:
        return M
    inv = np.argsort(_P3)
    return M[np.ix_(inv, inv)]


def _kernel(kernel: RobustKernel):  # type: ignore[no-untyped-def]
    import gtsam

    m = gtsam.noiseModel.mEstimator
    # DCS: dynamic covariance scaling, Agarwal et al., "Robust map optimization using dynamic covariance
    # scaling", ICRA 2013 (the closed form of switchable constraints, Sünderhauf & Protzel 2012).
    cls = {"huber": m.Huber, "cauchy": m.Cauchy, "geman_mcclure": m.GemanMcClure, "dcs": m.DCS}[kernel.name]
    return cls.Create(float(kernel.k))


def noise_model(information: ArrayLike, dim: int, kernel: RobustKernel | None = None):  # type: ignore[no-untyped-def]
    """GTSAM noise model from our information matrix, optionally wrapped in a robust kernel."""
    import gtsam

    base = gtsam.noiseModel.Gaussian.Information(to_gtsam_information(information, dim))
    if kernel is None:
        return base
    return gtsam.noiseModel.Robust.Create(_kernel(kernel), base)


def _to_pose(T: Array, dim: int):  # type: ignore[no-untyped-def]
    return pose_formats.to_gtsam_pose2(T) if dim == 2 else pose_formats.to_gtsam_pose3(T)


def to_values(poses: ArrayLike, dim: int, keys: Sequence[int] | None = None):  # type: ignore[no-untyped-def]
    """``(N, 4, 4)`` poses → ``gtsam.Values`` with keys 0..N−1 (node indices) or *keys*."""
    import gtsam

    P = np.asarray(poses, dtype=float)
    v = gtsam.Values()
    keys = range(len(P)) if keys is None else keys
    for k, T in zip(keys, P):
        if dim == 2:
            v.insert(int(k), pose_formats.to_gtsam_pose2(T))
        else:
            v.insert(int(k), pose_formats.to_gtsam_pose3(T))
    return v


def from_values(values, n: int, dim: int, keys: Sequence[int] | None = None) -> Array:  # type: ignore[no-untyped-def]
    """``gtsam.Values`` → ``(N, 4, 4)`` poses.

    When the requested keys are exactly the Values' own keys (in its sorted order) all poses come out
    of one ``gtsam.utilities.extractPose2/3`` call instead of one Python call per key.
    """
    import gtsam

    keys = list(range(n) if keys is None else keys)
    if len(keys) == values.size() and list(values.keys()) == keys:
        if dim == 2:
            return geo.xytheta_to_matrix(np.asarray(gtsam.utilities.extractPose2(values)).reshape(-1, 3))
        a = np.asarray(gtsam.utilities.extractPose3(values)).reshape(-1, 12)
        P = np.tile(np.eye(4), (len(a), 1, 1))
        P[:, :3, :3] = a[:, :9].reshape(-1, 3, 3)
        P[:, :3, 3] = a[:, 9:]
        return P
    if dim == 2:
        xyt = np.array([[p.x(), p.y(), p.theta()] for p in (values.atPose2(int(k)) for k in keys)]).reshape(-1, 3)
        return geo.xytheta_to_matrix(xyt)
    return np.array([values.atPose3(int(k)).matrix() for k in keys], dtype=float).reshape(-1, 4, 4)


def _kernels_for(graph: PoseGraph, use_kernels: bool, robust: RobustKernel | None,
                 robust_kinds: Sequence[str]) -> list[RobustKernel | None]:
    ks = graph.edge_kernels if use_kernels else [None] * graph.num_edges
    if robust is not None:
        ks = [robust if kind in robust_kinds else k for k, kind in zip(ks, graph.edge_kinds)]
    return ks


def refuse_indefinite(graph: PoseGraph) -> None:
    """Raise GraphError naming the edges whose information is not positive definite: GTSAM's
    ``noiseModel.Gaussian.Information`` would factor such a matrix without complaint into a wrong square
    root. (The chordal back end uses their SE-Sync weights instead.)"""
    bad = graph.indefinite_edges()
    if not len(bad):
        return
    ii, jj = graph.edge_ids
    named = ", ".join(f"{int(ii[e])} → {int(jj[e])}" for e in bad[:5]) + (", …" if len(bad) > 5 else "")
    raise GraphError(f"{len(bad)} edge(s) have an information matrix that is not positive definite, which GTSAM's "
                     f"Gaussian noise model cannot use: {named} (the chordal back end uses only their SE-Sync "
                     "weights: --backend chordal)")


def build_factor_graph(
    graph: PoseGraph,
    *,
    use_kernels: bool = True,
    robust: RobustKernel | None = None,
    robust_kinds: Sequence[str] = ("loop",),
    anchor: bool = True,
    anchor_poses: ArrayLike | None = None,
):  # type: ignore[no-untyped-def]
    """A ``gtsam.NonlinearFactorGraph`` over node *indices* as keys.

    *use_kernels*: apply the kernels stored on the edges; *robust*: override the kernel of every edge whose
    kind is in *robust_kinds*; *anchor*: add the gauge priors (at *anchor_poses*, default the graph's poses).
    """
    import gtsam

    dim = graph.dim
    a = graph.edge_arrays()
    refuse_indefinite(graph)
    kernels = _kernels_for(graph, use_kernels, robust, robust_kinds)
    fg = gtsam.NonlinearFactorGraph()
    Between = gtsam.BetweenFactorPose2 if dim == 2 else gtsam.BetweenFactorPose3
    Prior = gtsam.PriorFactorPose2 if dim == 2 else gtsam.PriorFactorPose3
    for e in range(len(a.jj)):
        nm = noise_model(a.information[e], dim, kernels[e])
        Z = _to_pose(a.measurements[e], dim)
        if a.ii[e] < 0:
            fg.add(Prior(int(a.jj[e]), Z, nm))
        else:
            fg.add(Between(int(a.ii[e]), int(a.jj[e]), Z, nm))
    if anchor:
        P = graph.poses if anchor_poses is None else np.asarray(anchor_poses, dtype=float)
        tight = gtsam.noiseModel.Isotropic.Sigma(graph.dof, ANCHOR_SIGMA)
        for k in graph.anchor_indices():
            T = P[k] if np.all(np.isfinite(P[k])) else np.eye(4)
            fg.add(Prior(int(k), _to_pose(T, dim), tight))
    return fg


@dataclass
class GtsamResult:
    """``poses`` ``(N, 4, 4)``; ``error`` = GTSAM χ² (½ Σ eᵀΩe, with the robust losses used, no gauge prior)."""

    poses: Array
    error: float
    initial_error: float
    iterations: int
    time_s: float
    build_time_s: float
    weights: Array | None = None  # GNC: per edge, 1 inlier … 0 rejected outlier


def optimize(
    graph: PoseGraph,
    initial: ArrayLike | None = None,
    *,
    method: str = "lm",
    robust: RobustKernel | None = None,
    robust_kinds: Sequence[str] = ("loop",),
    use_kernels: bool = True,
    max_iterations: int = 100,
    relative_error_tol: float = 1e-6,
    absolute_error_tol: float = 1e-10,
    gnc_inlier_probability: float = 0.99,
) -> GtsamResult:
    """Batch Levenberg-Marquardt (``method="lm"``), Gauss-Newton (``"gn"``) or graduated non-convexity
    (``"gnc"``: loop edges under a truncated quadratic whose threshold is the *gnc_inlier_probability*
    χ² quantile, every other factor a known inlier) from *initial* poses.

    ``time_s`` is the optimiser's wall time only; building the factor graph is ``build_time_s``. The default
    relative tolerance (1e-6; GTSAM's own default is 1e-5) is the chordal solver's.
    """
    import gtsam

    t0 = time.perf_counter()
    P0 = np.asarray(graph.poses if initial is None else initial, dtype=float)
    if P0.shape != (graph.num_nodes, 4, 4) or not np.all(np.isfinite(P0)):
        raise GraphError(f"initial poses must be a finite ({graph.num_nodes}, 4, 4) array")
    fg = build_factor_graph(graph, use_kernels=use_kernels, robust=robust, robust_kinds=robust_kinds,
                            anchor=True, anchor_poses=P0)
    values = to_values(P0, graph.dim)
    t1 = time.perf_counter()
    if method == "lm":
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(max_iterations)
        params.setRelativeErrorTol(relative_error_tol)
        params.setAbsoluteErrorTol(absolute_error_tol)
        opt = gtsam.LevenbergMarquardtOptimizer(fg, values, params)
    elif method == "gn":
        params = gtsam.GaussNewtonParams()
        params.setMaxIterations(max_iterations)
        params.setRelativeErrorTol(relative_error_tol)
        params.setAbsoluteErrorTol(absolute_error_tol)
        opt = gtsam.GaussNewtonOptimizer(fg, values, params)
    elif method == "gnc":
        # Graduated non-convexity with the truncated-least-squares loss (Yang, Antonante, Tzoumas & Carlone,
        # "Graduated non-convexity for robust spatial perception", RA-L 2020) on the loop edges; every other
        # factor (odometry, priors, the gauge) is a known inlier. Kernels on the edges are not used: GNC is the
        # robust loss.
        fg = build_factor_graph(graph, use_kernels=False, anchor=True, anchor_poses=P0)
        kinds = graph.edge_kinds
        inliers = [f for f in range(fg.size()) if f >= len(kinds) or kinds[f] != "loop"]
        lm = gtsam.LevenbergMarquardtParams()
        lm.setMaxIterations(max_iterations)
        lm.setRelativeErrorTol(relative_error_tol)
        lm.setAbsoluteErrorTol(absolute_error_tol)
        params = gtsam.GncLMParams(lm)
        params.setKnownInliers(inliers)
        params.setLossType(gtsam.GncLossType.TLS)
        opt = gtsam.GncLMOptimizer(fg, values, params)
        opt.setInlierCostThresholdsAtProbability(gnc_inlier_probability)
    else:
        raise GraphError(f"unknown GTSAM method {method!r}; expected lm, gn or gnc")
    initial_error = float(fg.error(values))
    result = opt.optimize()
    t2 = time.perf_counter()
    poses = from_values(result, graph.num_nodes, graph.dim)
    iterations = int(opt.iterations()) if hasattr(opt, "iterations") else 0
    weights = np.asarray(opt.getWeights(), dtype=float)[: graph.num_edges] if method == "gnc" else None
    return GtsamResult(poses, float(fg.error(result)), initial_error, iterations, t2 - t1, t1 - t0, weights)


class IncrementalSmoother:
    """An iSAM2 session for the online pipeline: add nodes and edges, ``update()``, read poses and covariances.

    Node ids are the user's ids (used directly as GTSAM keys). The first node added is anchored with a tight
    prior unless ``anchor_first=False`` (then add priors yourself). Information matrices and returned
    covariances are in our tangent order (translation first, right perturbation).
    """

    def __init__(self, dim: int, *, anchor_first: bool = True, relinearize_threshold: float = 0.01,
                 relinearize_skip: int = 1, factorization: str = "cholesky") -> None:
        import gtsam

        if dim not in (2, 3):
            raise GraphError(f"dim must be 2 or 3, got {dim}")
        self.dim = dim
        self.dof = 3 if dim == 2 else 6
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(relinearize_threshold)
        params.relinearizeSkip = relinearize_skip
        # "qr" where Cholesky fails: it squares the condition number, and on a long odometry chain with
        # millimetre wheel edges GTSAM can declare the system indeterminate; QR factors the same chain
        # (a little slower with many loop closures; docs/ODOMETRY.md).
        params.setFactorization(factorization.upper())
        self._isam = gtsam.ISAM2(params)
        self._new_factors = gtsam.NonlinearFactorGraph()
        self._new_values = gtsam.Values()
        self._ids: list[int] = []
        self._known: set[int] = set()
        self._anchor_first = anchor_first
        self._estimate = None
        self._updated = False

    @property
    def node_ids(self) -> list[int]:
        return list(self._ids)

    def add_node(self, node_id: int, initial_pose: ArrayLike) -> None:
        """Add node *node_id* with its initial world_T_node guess (4×4)."""
        import gtsam

        node_id = int(node_id)
        if node_id in self._known:
            raise GraphError(f"node {node_id} already exists")
        T = np.asarray(initial_pose, dtype=float)
        self._new_values.insert(node_id, _to_pose(T, self.dim))
        if self._anchor_first and not self._ids:
            Prior = gtsam.PriorFactorPose2 if self.dim == 2 else gtsam.PriorFactorPose3
            self._new_factors.add(Prior(node_id, _to_pose(T, self.dim),
                                        gtsam.noiseModel.Isotropic.Sigma(self.dof, ANCHOR_SIGMA)))
        self._ids.append(node_id)
        self._known.add(node_id)

    def add_edge(self, i: int, j: int, measurement: ArrayLike, information: ArrayLike,
                 kernel: RobustKernel | None = None) -> None:
        """Add the relative measurement ``i_T_j`` (or a prior on *j* when ``i == PRIOR_NODE``)."""
        import gtsam

        for k in (i, j):
            if k != PRIOR_NODE and int(k) not in self._known:
                raise GraphError(f"edge ({i}, {j}): unknown node {k}")
        nm = noise_model(information, self.dim, kernel)
        Z = _to_pose(np.asarray(measurement, dtype=float), self.dim)
        if i == PRIOR_NODE:
            Prior = gtsam.PriorFactorPose2 if self.dim == 2 else gtsam.PriorFactorPose3
            self._new_factors.add(Prior(int(j), Z, nm))
        else:
            Between = gtsam.BetweenFactorPose2 if self.dim == 2 else gtsam.BetweenFactorPose3
            self._new_factors.add(Between(int(i), int(j), Z, nm))

    def update(self, extra_iterations: int = 0) -> None:
        """Push the new nodes and edges into iSAM2 and relinearise (plus *extra_iterations* updates)."""
        import gtsam

        self._isam.update(self._new_factors, self._new_values)
        for _ in range(extra_iterations):
            self._isam.update()
        self._new_factors = gtsam.NonlinearFactorGraph()
        self._new_values = gtsam.Values()
        self._updated = True
        self._estimate = None  # computed when asked: most keyframes read only the newest pose

    def _full_estimate(self):  # type: ignore[no-untyped-def]
        if not self._updated:
            raise GraphError("no estimate yet: call update() first")
        if self._estimate is None:
            self._estimate = self._isam.calculateEstimate()
        return self._estimate

    def estimate(self) -> tuple[list[int], Array]:
        """(node ids, ``(N, 4, 4)`` poses) of the current estimate (call :meth:`update` first)."""
        values = self._full_estimate()
        ids = self._ids[: values.size()]  # nodes added since the last update() are the newest ones
        return ids, from_values(values, len(ids), self.dim, ids)

    def pose(self, node_id: int) -> Array:
        """One node's current estimate: iSAM2's linearisation point retracted by that node's delta alone,
        the same value :meth:`estimate` gives it, without retracting every node (O(1) instead of O(N))."""
        key = int(node_id)
        if not self._updated or not self._isam.valueExists(key):
            raise GraphError(f"node {node_id} has no estimate yet")
        if self.dim == 2:
            p = self._isam.calculateEstimatePose2(key)
            return geo.xytheta_to_matrix(np.array([[p.x(), p.y(), p.theta()]]))[0]
        return np.asarray(self._isam.calculateEstimatePose3(key).matrix(), dtype=float)

    def marginal_covariance(self, node_id: int) -> Array:
        """Marginal covariance of node *node_id* in its own frame (right perturbation), translation first."""
        return from_gtsam_covariance(self._isam.marginalCovariance(int(node_id)), self.dim)
