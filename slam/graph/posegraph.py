"""PoseGraph: nodes (id, world_T_node pose) and relative-pose edges with information matrices.

Conventions (docs/ARCHITECTURE.md): poses are 4×4 float64 ``world_T_node`` matrices; an edge
(i, j) measures ``Z_ij = i_T_j`` (metres, radians), perturbed on the right ``Z_true = Z·Exp(δ)``
with δ ordered translation first — 2D ``(x, y, θ)``, 3D ``(x, y, z, rx, ry, rz)`` — which is
exactly the order of g2o's ``EDGE_SE2`` / ``EDGE_SE3:QUAT`` information matrices.

A *prior* edge has ``i = PRIOR_NODE`` (−1, the fixed world frame) and measures ``world_T_j``.

Storage is columnar: adding a node or an edge appends one row to Python lists (amortised O(1)),
and the numpy views used by the solvers (:meth:`PoseGraph.edge_arrays`, :attr:`PoseGraph.poses`)
are stacked lazily and cached until the next change. Measurements and poses are stored in their
file parameterisation — ``(x, y, θ)`` in 2D, ``(x, y, z, qx, qy, qz, qw)`` in 3D — so that a
g2o/TORO read → write → read round trip is bit-exact; the 4×4 matrices are derived from them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from core import geometry as geo
from core import pose_formats
from core.errors import GeometryError, GpslamError

from .connectivity import component_labels, free_component_anchors

Array = NDArray[np.float64]
EdgeKind = Literal["odometry", "loop", "prior"]
KINDS: tuple[str, ...] = ("odometry", "loop", "prior")
KERNELS: tuple[str, ...] = ("huber", "cauchy", "geman_mcclure", "dcs")
PRIOR_NODE = -1

__all__ = ["PoseGraph", "Edge", "EdgeArrays", "RobustKernel", "EdgeKind", "KINDS", "KERNELS", "PRIOR_NODE",
           "GraphError"]


class GraphError(GpslamError, ValueError):
    """An invalid pose-graph operation (unknown node, duplicate id, wrong dimension)."""


@dataclass(frozen=True)
class RobustKernel:
    """An M-estimator applied to an edge's whitened error: ``name`` in :data:`KERNELS`, threshold ``k``
    (in units of the whitened residual, i.e. standard deviations)."""

    name: str
    k: float = 1.0

    def __post_init__(self) -> None:
        if self.name not in KERNELS:
            raise GraphError(f"unknown robust kernel {self.name!r}; expected one of {KERNELS}")
        if not (np.isfinite(self.k) and self.k > 0):
            raise GraphError(f"robust kernel threshold must be positive, got {self.k}")


@dataclass(frozen=True)
class Edge:
    """One edge: ``measurement = i_T_j`` (4×4), ``information`` (3×3 or 6×6, translation first)."""

    i: int
    j: int
    measurement: Array
    information: Array
    kind: str
    kernel: RobustKernel | None = None


@dataclass(frozen=True)
class EdgeArrays:
    """Stacked edge data for vectorised solvers. ``ii``/``jj`` are node *indices* (−1 for priors)."""

    ii: NDArray[np.int64]
    jj: NDArray[np.int64]
    measurements: Array  # (M, 4, 4)
    information: Array  # (M, d, d)
    kinds: NDArray[np.int8]  # index into KINDS


def _params_to_matrix(params: Array, dim: int) -> Array:
    if dim == 2:
        return geo.xytheta_to_matrix(params)
    return pose_formats.pose_from_quat(params[..., :3], params[..., 3:])


def _matrix_to_params(T: Array, dim: int) -> Array:
    if dim == 2:
        return geo.matrix_to_xytheta(T)
    t, q = pose_formats.pose_to_quat(T)
    return np.concatenate([t, q], -1)


class PoseGraph:
    """A 2D (``dim=2``) or 3D (``dim=3``) pose graph. Node ids are arbitrary ints ≥ 0."""

    def __init__(self, dim: int) -> None:
        if dim not in (2, 3):
            raise GraphError(f"dim must be 2 or 3, got {dim}")
        self.dim = dim
        self.dof = 3 if dim == 2 else 6
        self.npar = 3 if dim == 2 else 7
        self._index: dict[int, int] = {}
        self._ids: list[int] = []
        self._node_par: list[Array] = []
        self._has_pose: list[bool] = []
        self._e_i: list[int] = []
        self._e_j: list[int] = []
        self._e_par: list[Array] = []
        self._e_info: list[Array] = []
        self._e_kind: list[int] = []
        self._e_kernel: list[RobustKernel | None] = []
        self.fixed_ids: list[int] = []
        self._cache: dict[str, object] = {}

    # ------------------------------------------------------------------ building
    def add_node(self, node_id: int, pose: ArrayLike | None = None, *, params: ArrayLike | None = None) -> int:
        """Add node *node_id* with an optional initial ``world_T_node`` pose; returns its index."""
        node_id = int(node_id)
        if node_id < 0:
            raise GraphError(f"node ids must be ≥ 0, got {node_id}")
        if node_id in self._index:
            raise GraphError(f"node {node_id} already exists")
        if params is not None:
            par = np.asarray(params, dtype=float).reshape(self.npar)
        elif pose is not None:
            par = _matrix_to_params(self._check_pose(pose), self.dim)
        else:
            par = np.full(self.npar, np.nan)
        self._index[node_id] = len(self._ids)
        self._ids.append(node_id)
        self._node_par.append(par)
        self._has_pose.append(bool(np.all(np.isfinite(par))))
        self._cache.clear()
        return len(self._ids) - 1

    def add_edge(
        self,
        i: int,
        j: int,
        measurement: ArrayLike | None,
        information: ArrayLike,
        kind: str | None = None,
        kernel: RobustKernel | None = None,
        *,
        params: ArrayLike | None = None,
    ) -> int:
        """Add the edge ``i_T_j = measurement`` (4×4) with *information* (translation first).

        *kind* defaults to ``odometry`` when ``j == i + 1`` and ``loop`` otherwise; ``i == PRIOR_NODE``
        makes a prior on node *j* (use :meth:`add_prior`). Returns the edge index.
        """
        i, j = int(i), int(j)
        if i != PRIOR_NODE and i not in self._index:
            raise GraphError(f"edge ({i}, {j}): unknown node {i}")
        if j not in self._index:
            raise GraphError(f"edge ({i}, {j}): unknown node {j}")
        if kind is None:
            kind = "prior" if i == PRIOR_NODE else ("odometry" if j == i + 1 else "loop")
        if kind not in KINDS:
            raise GraphError(f"edge ({i}, {j}): unknown kind {kind!r}; expected one of {KINDS}")
        if (kind == "prior") != (i == PRIOR_NODE):
            raise GraphError(f"edge ({i}, {j}): kind 'prior' must go with i = {PRIOR_NODE} and vice versa")
        if params is not None:
            par = np.asarray(params, dtype=float).reshape(self.npar)
        else:
            par = _matrix_to_params(self._check_pose(measurement), self.dim)
        info = np.asarray(information, dtype=float)
        if info.shape != (self.dof, self.dof):
            raise GraphError(f"edge ({i}, {j}): information must be {self.dof}×{self.dof}, got {info.shape}")
        self._e_i.append(i)
        self._e_j.append(j)
        self._e_par.append(par)
        self._e_info.append(info)
        self._e_kind.append(KINDS.index(kind))
        self._e_kernel.append(kernel)
        self._cache.clear()
        return len(self._e_i) - 1

    def add_prior(self, j: int, pose: ArrayLike, information: ArrayLike, kernel: RobustKernel | None = None) -> int:
        """Add a prior ``world_T_j = pose`` with *information* (translation first)."""
        return self.add_edge(PRIOR_NODE, j, pose, information, "prior", kernel)

    def set_kernel(self, kernel: RobustKernel | None, kinds: Sequence[str] = ("loop",)) -> None:
        """Set (or clear, with ``None``) the robust kernel of every edge whose kind is in *kinds*."""
        codes = {KINDS.index(k) for k in kinds}
        for e, code in enumerate(self._e_kind):
            if code in codes:
                self._e_kernel[e] = kernel

    def _check_pose(self, T: ArrayLike) -> Array:
        T = np.asarray(T, dtype=float)
        if T.shape != (4, 4) or not geo.is_pose(T, tol=1e-6):
            raise GeometryError(f"expected a 4×4 rigid transform, got {T.shape if T.shape != (4, 4) else T}")
        if self.dim == 2 and (abs(T[2, 3]) > 1e-9 or abs(T[2, 2] - 1.0) > 1e-9):
            raise GeometryError("a 2D pose graph needs planar poses (z = 0, rotation about z only)")
        return T

    # ------------------------------------------------------------------ nodes
    @property
    def num_nodes(self) -> int:
        return len(self._ids)

    @property
    def num_edges(self) -> int:
        return len(self._e_i)

    @property
    def node_ids(self) -> NDArray[np.int64]:
        return self._cached("ids", lambda: np.asarray(self._ids, dtype=np.int64))

    def index_of(self, node_id: int) -> int:
        try:
            return self._index[int(node_id)]
        except KeyError:
            raise GraphError(f"unknown node {node_id}") from None

    @property
    def has_initial_guess(self) -> bool:
        """True when every node has a pose (e.g. the file had VERTEX lines for all nodes)."""
        return bool(self._has_pose) and all(self._has_pose)

    @property
    def node_params(self) -> Array:
        """``(N, 3)`` (x, y, θ) or ``(N, 7)`` (t, q) node parameters; NaN rows for nodes without pose."""
        return self._cached("npar", lambda: np.asarray(self._node_par, dtype=float).reshape(-1, self.npar))

    @property
    def poses(self) -> Array:
        """``(N, 4, 4)`` ``world_T_node`` poses (NaN for nodes that have none)."""
        def build() -> Array:
            par = self.node_params
            out = np.full((len(par), 4, 4), np.nan)
            ok = np.all(np.isfinite(par), axis=1)
            if ok.any():
                out[ok] = _params_to_matrix(par[ok], self.dim)
            return out
        return self._cached("poses", build)

    def set_poses(self, poses: ArrayLike) -> None:
        """Replace all node poses by ``(N, 4, 4)`` *poses* (in node order)."""
        P = np.asarray(poses, dtype=float)
        if P.shape != (self.num_nodes, 4, 4):
            raise GraphError(f"expected ({self.num_nodes}, 4, 4) poses, got {P.shape}")
        par = _matrix_to_params(P, self.dim)
        self._node_par = list(par)
        self._has_pose = [True] * len(par)
        self._cache.clear()

    def pose(self, node_id: int) -> Array:
        return self.poses[self.index_of(node_id)].copy()

    # ------------------------------------------------------------------ edges
    @property
    def edge_params(self) -> Array:
        return self._cached("epar", lambda: np.asarray(self._e_par, dtype=float).reshape(-1, self.npar))

    @property
    def edge_kinds(self) -> list[str]:
        return [KINDS[k] for k in self._e_kind]

    @property
    def edge_kernels(self) -> list[RobustKernel | None]:
        return list(self._e_kernel)

    @property
    def edge_ids(self) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """Node ids ``(i, j)`` of every edge (i = −1 for priors)."""
        return (np.asarray(self._e_i, dtype=np.int64), np.asarray(self._e_j, dtype=np.int64))

    def edge_arrays(self) -> EdgeArrays:
        """Stacked edge data (cached until the graph changes)."""
        def build() -> EdgeArrays:
            idx = self._index
            ii = np.fromiter((idx[i] if i != PRIOR_NODE else -1 for i in self._e_i), np.int64, len(self._e_i))
            jj = np.fromiter((idx[j] for j in self._e_j), np.int64, len(self._e_j))
            meas = _params_to_matrix(self.edge_params, self.dim) if self._e_i else np.zeros((0, 4, 4))
            info = np.asarray(self._e_info, dtype=float).reshape(-1, self.dof, self.dof)
            return EdgeArrays(ii, jj, meas, info, np.asarray(self._e_kind, dtype=np.int8))
        return self._cached("edges", build)

    def indefinite_edges(self) -> NDArray[np.int64]:
        """Indices of the edges whose information matrix is not positive definite (usable by the chordal
        back end through its SE-Sync weights, not as a Gaussian noise model)."""
        def build() -> NDArray[np.int64]:
            info = self.edge_arrays().information
            if not len(info):
                return np.zeros(0, dtype=np.int64)
            return np.flatnonzero(~(np.linalg.eigvalsh(info)[:, 0] > 0)).astype(np.int64)
        return self._cached("indefinite", build)

    def edge(self, e: int) -> Edge:
        a = self.edge_arrays()
        return Edge(self._e_i[e], self._e_j[e], a.measurements[e].copy(), a.information[e].copy(),
                    KINDS[self._e_kind[e]], self._e_kernel[e])

    def edges(self) -> list[Edge]:
        return [self.edge(e) for e in range(self.num_edges)]

    # ------------------------------------------------------------------ misc
    def copy(self) -> "PoseGraph":
        g = PoseGraph(self.dim)
        g._index = dict(self._index)
        g._ids = list(self._ids)
        g._node_par = [p.copy() for p in self._node_par]
        g._has_pose = list(self._has_pose)
        g._e_i, g._e_j = list(self._e_i), list(self._e_j)
        g._e_par = list(self._e_par)
        g._e_info = list(self._e_info)
        g._e_kind = list(self._e_kind)
        g._e_kernel = list(self._e_kernel)
        g.fixed_ids = list(self.fixed_ids)
        return g

    def with_poses(self, poses: ArrayLike) -> "PoseGraph":
        """A copy of this graph whose nodes carry *poses*."""
        g = self.copy()
        g.set_poses(poses)
        return g

    def component_labels(self) -> NDArray[np.int64]:
        """``(N,)`` connected component of each node (0 for the component of node index 0, …)."""
        a = self.edge_arrays()
        return self._cached("components", lambda: component_labels(self.num_nodes, a.ii, a.jj))

    def free_anchor_indices(self) -> NDArray[np.int64]:
        """The first node index of every component that no prior and no FIX holds (sorted)."""
        a = self.edge_arrays()
        held = np.concatenate([np.asarray([self.index_of(i) for i in self.fixed_ids], dtype=np.int64),
                               a.jj[a.ii < 0]])
        return free_component_anchors(self.component_labels(), held)

    def anchor_indices(self) -> NDArray[np.int64]:
        """Node indices held fixed to fix the gauge: FIX'ed nodes, and the first node of every component
        that neither a FIX nor a prior holds (:mod:`slam.graph.connectivity`). For a connected graph: the
        FIX'ed nodes, else none when priors exist, else node 0."""
        fixed = np.asarray([self.index_of(i) for i in self.fixed_ids], dtype=np.int64)
        return np.concatenate([fixed, self.free_anchor_indices()]) if self.num_nodes else fixed

    def disconnection(self) -> str | None:
        """Why the graph leaves the relative placement of some components open, or None when it does not:
        more than one component is free (no prior, no FIX), or one is free beside held ones."""
        free = self.free_anchor_indices()
        held_elsewhere = bool(self.fixed_ids) or "prior" in self.edge_kinds
        if len(free) <= (0 if held_elsewhere else 1):
            return None
        sizes = np.bincount(self.component_labels())
        ids = ", ".join(str(int(v)) for v in self.node_ids[free][:10]) + (", …" if len(free) > 10 else "")
        shown = " and ".join(str(int(s)) for s in sizes[:10]) + (" …" if len(sizes) > 10 else "")
        return (f"the graph is not connected: {len(sizes)} components ({shown} nodes), {len(free)} of them held by "
                f"no prior or FIX (first nodes {ids})")

    def _cached(self, key: str, fn):  # type: ignore[no-untyped-def]
        if key not in self._cache:
            self._cache[key] = fn()
        return self._cache[key]

    def __repr__(self) -> str:
        return f"PoseGraph(dim={self.dim}, nodes={self.num_nodes}, edges={self.num_edges})"
