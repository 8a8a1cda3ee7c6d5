"""Pose-graph back end of the pipeline: online iSAM2 (GTSAM) or periodic batch chordal solves.

Every keyframe, odometry edge and loop closure is recorded in a :class:`~slam.graph.posegraph.PoseGraph`
(written to ``graph.g2o``) and mirrored into the online solver. ``finish()`` runs the final batch
optimisation (GTSAM Levenberg–Marquardt with robust kernels on loop edges and on the odometry edges
of steps no wheel odometry measured, or our chordal solver), then drops loop closures the solution still
violates by more than Cartographer's criterion (Hess et al. 2016, §VII-B: 20 cm / 1°) and solves
again, for a few rounds. With enough closures left, the registration, wheel and closure edges then take the
scales of their covariances that the solution's residuals call for (variance components,
:mod:`slam.backends.variance_components`), and the graph is solved once more under them, as plain least
squares (the closures that remain are the inliers), and pruned the same way.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from core import geometry as G
from slam.graph.posegraph import KINDS, PoseGraph, RobustKernel

from .config import BackendConfig, LoopConfig
from slam.backends.variance_components import VarianceComponents
from slam.loops import LoopClosure

Array = NDArray[np.float64]

_KERNEL_NAMES = {"huber": "huber", "cauchy": "cauchy", "gm": "geman_mcclure"}


@dataclass(frozen=True)
class PrunedClosure:
    """A loop closure the final solve dropped: keyframes *i* → *j*, and by how much the solution it was
    dropped from violated it (the closure's measurement against the solution's relative pose)."""

    i: int
    j: int
    translation_m: float
    rotation_deg: float
    round: int  # the pruning round (1 = after the first batch solve)


class PipelineBackend:
    """Keeps the pose graph and the current estimate of every keyframe pose (``world_T_base``)."""

    def __init__(self, config: BackendConfig, loops: LoopConfig, planar: bool) -> None:
        self.config = config
        self.loop_config = loops
        self.dim = 2 if planar else 3
        self.graph = PoseGraph(self.dim)
        self.kernel = (RobustKernel(_KERNEL_NAMES[loops.robust_kernel], loops.robust_scale)
                       if loops.robust_kernel != "none" else None)
        self.lone_kernel = (RobustKernel("cauchy", config.lone_odometry_kernel_sigmas)
                            if config.lone_odometry_kernel_sigmas is not None else None)
        self._buf = np.zeros((64, 4, 4))  # current estimates of keyframes 0 … _n − 1, doubling when full
        self._n = 0
        self._since_solve = 0
        self.solve_time_s = 0.0
        self.pruned: list[PrunedClosure] = []  # the closures the final solve dropped, in the order it did
        self.groups: list[str] = []  # per edge of the graph: "registration", "wheel" or "loop"
        self.variance_components: VarianceComponents | None = None  # the final solve's, when it ran
        self.smoother_restarts = 0
        self._factorization = config.isam2_factorization  # becomes "qr" after a Cholesky failure
        self._smoother = self._new_smoother() if config.kind == "gtsam" else None

    @property
    def pruned_loops(self) -> int:
        """How many loop closures the final solve dropped."""
        return len(self.pruned)

    @property
    def poses(self) -> Array:
        """``(K, 4, 4)`` current estimates of the keyframe poses."""
        return self._buf[: self._n].copy()

    def _set_poses(self, poses: Array) -> None:
        P = np.asarray(poses, dtype=float).reshape(-1, 4, 4)
        self._buf[: len(P)] = P
        self._n = len(P)

    def add_keyframe(self, node_id: int, initial_pose: Array) -> None:
        self.graph.add_node(node_id, initial_pose)
        if self._n == len(self._buf):
            self._buf = np.concatenate([self._buf, np.zeros_like(self._buf)])
        self._buf[self._n] = initial_pose
        self._n += 1
        if self._smoother is not None:
            self._smoother.add_node(node_id, initial_pose)

    def add_odometry(self, i: int, j: int, measurement: Array, covariance: Array, alone: bool = False,
                     group: str = "registration") -> None:
        """An odometry edge of *group* (``registration`` or ``wheel``); *alone*: the step's only measurement
        (no wheel odometry measured it), which then carries the Cauchy kernel of ``lone_odometry_kernel_sigmas``."""
        info = np.linalg.inv(covariance)
        kernel = self.lone_kernel if alone else None
        self.graph.add_edge(i, j, measurement, info, "odometry", kernel)
        self.groups.append(group)
        if self._smoother is not None:
            self._smoother.add_edge(i, j, measurement, info, kernel)

    def add_loop(self, lc: LoopClosure) -> None:
        info = np.linalg.inv(lc.covariance)
        self.graph.add_edge(lc.i, lc.j, lc.measurement, info, "loop", self.kernel)
        self.groups.append("loop")
        if self._smoother is not None:
            self._smoother.add_edge(lc.i, lc.j, lc.measurement, info, self.kernel)

    def update(self, loop_added: bool) -> None:
        """Refresh the estimate after a keyframe (iSAM2 step, or a periodic chordal batch solve)."""
        t0 = time.perf_counter()
        if self._smoother is not None:
            try:
                self._smoother.update()
            except RuntimeError:
                # GTSAM's "indeterminant linear system": iSAM2's incremental factorisation can lose
                # definiteness numerically (with every edge finite and well conditioned: a long chain
                # of millimetre wheel edges in turns in place). Recover: batch-solve the whole graph
                # and restart iSAM2 from that solution, with QR from now on (it does not square the
                # condition number; Cholesky kept failing there, docs/ODOMETRY.md).
                self._factorization = "qr"
                self._restart_smoother()
                loop_added = True
            if loop_added:
                self._set_poses(self._smoother.estimate()[1])
            else:
                self._buf[self._n - 1] = self._smoother.pose(self._n - 1)
        else:
            self._since_solve += 1
            if loop_added and self._since_solve >= self.config.chordal_every_keyframes:
                self._set_poses(self._solve_chordal(self.poses))
                self._since_solve = 0
        self.solve_time_s += time.perf_counter() - t0

    def relocalise(self) -> None:
        """Re-solve after closures that say the estimate is metres off (a global-search group, see
        :class:`~slam.loops.closer.LoopCloser`): robust kernels weigh a closure by its residual at
        the current estimate, so a Cauchy-weighted closure 45 m away pulls with ~10⁻⁷ of its weight
        and iSAM2 stays where it is. A batch solve without kernels first moves the graph onto the
        closures; the kernelled batch solve from there (and iSAM2 restarted at it) keeps its robustness
        to the residuals that remain (graduated robustness, cf. Yang et al., "Graduated non-convexity
        for robust spatial perception", RA-L 2020)."""
        t0 = time.perf_counter()
        if self.config.kind == "chordal":
            self._set_poses(self._solve_chordal(self.poses))
        else:
            from slam.backends.gtsam_backend import optimize

            self._set_poses(optimize(self.graph, self.poses, method="lm", use_kernels=False).poses)
            self._restart_smoother()
            self._set_poses(self._smoother.estimate()[1])
        self.solve_time_s += time.perf_counter() - t0

    def _new_smoother(self):  # type: ignore[no-untyped-def]
        from slam.backends.gtsam_backend import IncrementalSmoother

        return IncrementalSmoother(self.dim, relinearize_threshold=self.config.isam2_relinearize_threshold,
                                   factorization=self._factorization)

    def _restart_smoother(self) -> None:
        """A fresh iSAM2 holding the whole graph, initialised at its batch LM solution."""
        self.smoother_restarts += 1
        P = self._solve_batch(self.poses)
        while True:
            self._smoother = self._new_smoother()
            for nid, T in zip(self.graph.node_ids, P):
                self._smoother.add_node(int(nid), T)
            for edge in self.graph.edges():
                self._smoother.add_edge(edge.i, edge.j, edge.measurement, edge.information, edge.kernel)
            try:
                self._smoother.update()
                return
            except RuntimeError:
                if self._factorization == "qr":
                    raise
                self._factorization = "qr"  # Cholesky lost definiteness on the fresh graph too: QR from now on

    def _solve_chordal(self, initial: Array) -> Array:
        from slam.backends.chordal import solve_chordal

        return solve_chordal(self.graph, initial).poses

    def _solve_batch(self, initial: Array, kernels: bool = True) -> Array:
        if self.config.kind == "chordal":
            return self._solve_chordal(initial)
        from slam.backends.gtsam_backend import optimize

        return optimize(self.graph, initial, method="lm", use_kernels=kernels).poses

    def _violated_loops(self, poses: Array) -> list[int]:
        """Indices of loop edges the solution violates by more than the pruning thresholds."""
        return [e for e, _, _ in self._violations(poses)]

    def _violations(self, poses: Array) -> list[tuple[int, float, float]]:
        """(edge index, translation m, rotation °) of each loop edge the solution *poses* violates by more than
        the pruning thresholds."""
        c = self.loop_config
        a = self.graph.edge_arrays()
        loops = np.flatnonzero(a.kinds == KINDS.index("loop"))
        if len(loops) == 0:
            return []
        err = G.relative(a.measurements[loops], G.relative(poses[a.ii[loops]], poses[a.jj[loops]]))
        dt = np.linalg.norm(err[:, :3, 3], axis=1)
        dth = np.degrees(G.rotation_angles(err[:, :3, :3]))
        bad = np.flatnonzero((dt > c.prune_translation_m) | (dth > c.prune_rotation_deg))
        return [(int(loops[b]), float(dt[b]), float(dth[b])) for b in bad]

    def finish(self) -> Array:
        """Final batch solve, then up to ``prune_rounds`` rounds of: drop the closures the solution
        violates, solve again (a closure pulled into line by an outlier shows only once that outlier
        is gone). Then, with ``variance_components``, the edge groups' covariances scaled to the solution's
        residuals and the graph solved again under them without kernels, pruned the same way. Returns the
        keyframe poses."""
        t0 = time.perf_counter()
        P = self.poses
        if self.config.final_batch and self.graph.num_edges > 0:
            P = self._prune(self._solve_batch(P), kernels=True)
            if self.config.variance_components:
                P = self._calibrate(P)
        self._set_poses(P)
        self.graph.set_poses(P)
        self.solve_time_s += time.perf_counter() - t0
        return P

    def _prune(self, P: Array, kernels: bool) -> Array:
        """Up to ``prune_rounds`` rounds of dropping the closures the solution *P* violates and solving again."""
        first = max((p.round for p in self.pruned), default=0) + 1
        for rnd in range(first, first + self.loop_config.prune_rounds):
            bad = self._violations(P)
            if not bad:
                break
            self.pruned += [PrunedClosure(int(self.graph.edge(e).i), int(self.graph.edge(e).j), dt, dth, rnd)
                            for e, dt, dth in bad]
            drop = {e for e, _, _ in bad}
            self.graph = _without_edges(self.graph, drop)
            self.groups = [g for e, g in enumerate(self.groups) if e not in drop]
            P = self._solve_batch(P, kernels)
        return P

    def _calibrate(self, P: Array) -> Array:
        """The variance components of the edge groups at the solution *P*; when the closures give them
        enough redundancy, the graph takes the scaled covariances, loses its kernels, and is solved again."""
        from slam.backends.linsolve import SingularSystemError
        from slam.backends.variance_components import (MIN_REDUNDANCY, estimate_variance_components,
                                                       scaled_graph)

        if "loop" not in self.groups:
            return P
        try:
            vc = estimate_variance_components(self.graph, P, self.groups)
        except (np.linalg.LinAlgError, SingularSystemError):
            return P  # an information matrix not positive definite, or a graph in pieces: the model stands
        if min(r for (g, _), r in vc.redundancy.items() if g == "loop") < MIN_REDUNDANCY:
            return P  # too few closures to say how sure any edge is
        self.variance_components = vc
        self.graph = scaled_graph(self.graph, self.groups, vc.scales)
        self.graph.set_kernel(None, kinds=("odometry", "loop"))
        return self._prune(self._solve_batch(vc.poses, kernels=False), kernels=False)


def _without_edges(graph: PoseGraph, drop: set[int]) -> PoseGraph:
    g = PoseGraph(graph.dim)
    for nid, T in zip(graph.node_ids, graph.poses):
        g.add_node(int(nid), T)
    for e, edge in enumerate(graph.edges()):
        if e not in drop:
            g.add_edge(edge.i, edge.j, edge.measurement, edge.information, edge.kind, edge.kernel)
    return g
