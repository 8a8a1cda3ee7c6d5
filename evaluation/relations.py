"""The relation-based SLAM metric of Kümmerle et al. 2009.

R. Kümmerle et al., "On measuring the accuracy of SLAM algorithms", Autonomous Robots 27(4), 2009,
eq. (2)–(4): for each ground-truth relation (t1, t2, δ*) — the pose of the robot at t2 in its
frame at t1 — take the estimate's poses x_t1, x_t2 and form

    e = δ*⁻¹ ⊕ (x_t1⁻¹ ⊕ x_t2).

Reported: mean ± std of |trans(e)| [m] and of trans(e)² [m²], of |rot(e)| [deg] and rot(e)² [deg²]
(the official ``metricEvaluator`` with weights {1,1,1,0,0,0} / {0,0,0,1,1,1}; |rot(e)| is the
rotation angle of e, which for the planar relations of the benchmark is |yaw|). Standard
deviations are population (ddof = 0). A relation whose stamps the trajectory lacks (no stamp
within the tolerance) is counted in ``n_missing`` and left out of the statistics.

Relations file: one relation per line, ``t1 t2 x y z roll pitch yaw`` (metres, radians;
R = Rz(yaw) Ry(pitch) Rx(roll)).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from core import geometry as geo
from core import pose_formats
from core.errors import LogFormatError
from core.numbers import c_floats
from core.textfile import text_lines
from core.trajectory import Trajectory

from .trajectory import nearest_indices

Array = NDArray[np.float64]

__all__ = ["Relations", "RelationResult", "ReferenceNoise", "read_relations", "evaluate_relations", "errors_by_path",
           "reference_noise", "DEFAULT_STAMP_TOL"]

DEFAULT_STAMP_TOL = 1e-3  # seconds; the benchmark stamps equal the log's ipc_timestamps to < 1e-5 s


@dataclass(frozen=True, eq=False)
class Relations:
    """Ground-truth relative poses: ``t1, t2 (M,)`` seconds and ``deltas (M, 4, 4)`` = x_t1⁻¹ x_t2."""

    t1: Array
    t2: Array
    deltas: Array
    path: str = ""

    def __len__(self) -> int:
        return int(self.t1.shape[0])


@dataclass
class RelationResult:
    """Kümmerle et al. 2009 statistics over the matched relations (units in the names)."""

    trans_mean: float
    trans_std: float
    trans_sq_mean: float
    trans_sq_std: float
    rot_mean_deg: float
    rot_std_deg: float
    rot_sq_mean: float  # deg²
    rot_sq_std: float  # deg²
    n_used: int
    n_missing: int
    trans_max: float = float("nan")
    rot_max_deg: float = float("nan")
    trans_errors: Array = field(default_factory=lambda: np.zeros(0))  # (n_used,) m
    rot_errors_deg: Array = field(default_factory=lambda: np.zeros(0))  # (n_used,) deg
    used: NDArray[np.bool_] = field(default_factory=lambda: np.zeros(0, bool))  # (M,) relation matched
    stamp_tol: float = DEFAULT_STAMP_TOL

    def to_dict(self) -> dict[str, float | int]:
        """The scalar statistics (JSON-ready)."""
        keys = ("trans_mean", "trans_std", "trans_sq_mean", "trans_sq_std", "rot_mean_deg", "rot_std_deg",
                "rot_sq_mean", "rot_sq_std", "trans_max", "rot_max_deg", "n_used", "n_missing", "stamp_tol")
        return {k: getattr(self, k) for k in keys}


def read_relations(path: str | os.PathLike[str]) -> Relations:
    """Read a relations file ``t1 t2 x y z roll pitch yaw`` (``#`` comments and blank lines skipped).

    Raises:
        LogFormatError: naming the file and line when a line has not 8 finite numbers.
    """
    p = Path(path)
    rows: list[list[float]] = []
    for lineno, line in text_lines(p, LogFormatError, "a relations file"):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        fields = s.split()
        if len(fields) != 8:
            raise LogFormatError(p, f"line {lineno}", f"expected 8 fields 't1 t2 x y z roll pitch yaw', got {len(fields)}")
        try:
            vals = c_floats(fields)
        except ValueError as exc:
            raise LogFormatError(p, f"line {lineno}", f"{exc}, expected 't1 t2 x y z roll pitch yaw'") from None
        if not np.all(np.isfinite(vals)):
            raise LogFormatError(p, f"line {lineno}", "non-finite number")
        rows.append(vals)
    d = np.array(rows, dtype=np.float64).reshape(-1, 8)
    deltas = np.zeros((len(d), 4, 4))
    deltas[:, :3, :3] = pose_formats.rpy_to_rotation(d[:, 5], d[:, 6], d[:, 7])
    deltas[:, :3, 3] = d[:, 2:5]
    deltas[:, 3, 3] = 1.0
    return Relations(d[:, 0].copy(), d[:, 1].copy(), deltas, str(p))


def relation_errors(trajectory: Trajectory, relations: Relations, stamp_tol: float = DEFAULT_STAMP_TOL) -> tuple[Array, NDArray[np.bool_]]:
    """Error poses ``e = δ*⁻¹ (x_t1⁻¹ x_t2)`` of the matched relations, and the (M,) matched mask."""
    M = len(relations)
    i1 = np.full(M, -1, np.int64)
    i2 = np.full(M, -1, np.int64)
    a, b = nearest_indices(relations.t1, trajectory.stamps, stamp_tol)
    i1[a] = b
    a, b = nearest_indices(relations.t2, trajectory.stamps, stamp_tol)
    i2[a] = b
    used = (i1 >= 0) & (i2 >= 0)
    X = trajectory.poses
    est = geo.relative(X[i1[used]], X[i2[used]])
    return geo.relative(relations.deltas[used], est), used


def evaluate_relations(trajectory: Trajectory, relations: Relations, stamp_tol: float = DEFAULT_STAMP_TOL) -> RelationResult:
    """Kümmerle et al. 2009 metric of *trajectory* (stamps in seconds) against *relations*.

    Args:
        trajectory: estimated poses ``world_T_base`` at the scan stamps.
        relations: from :func:`read_relations`.
        stamp_tol: largest stamp difference (s) for a relation stamp to match a trajectory stamp.
    """
    E, used = relation_errors(trajectory, relations, stamp_tol)
    trans = np.linalg.norm(E[:, :3, 3], axis=1)
    rot = np.degrees(np.linalg.norm(geo.so3_log(E[:, :3, :3]), axis=1)) if len(E) else np.zeros(0)

    def ms(v: Array) -> tuple[float, float]:
        return (float(np.mean(v)), float(np.std(v))) if v.size else (float("nan"), float("nan"))

    tm, ts = ms(trans)
    tqm, tqs = ms(trans**2)
    rm, rs = ms(rot)
    rqm, rqs = ms(rot**2)
    return RelationResult(
        trans_mean=tm, trans_std=ts, trans_sq_mean=tqm, trans_sq_std=tqs,
        rot_mean_deg=rm, rot_std_deg=rs, rot_sq_mean=rqm, rot_sq_std=rqs,
        n_used=int(used.sum()), n_missing=int((~used).sum()),
        trans_max=float(trans.max()) if trans.size else float("nan"),
        rot_max_deg=float(rot.max()) if rot.size else float("nan"),
        trans_errors=trans, rot_errors_deg=rot, used=used, stamp_tol=stamp_tol,
    )


def errors_by_path(trajectory: Trajectory, relations: Relations,
                   stamp_tol: float = DEFAULT_STAMP_TOL) -> tuple[Array, Array, Array]:
    """Per matched relation: the trajectory's own path length between its two poses (m, along the
    trajectory's positions), the translation error (m) and the absolute heading error (°) — drift grows with
    the path travelled, not with the time between the stamps."""
    E, used = relation_errors(trajectory, relations, stamp_tol)
    P = trajectory.poses
    path = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(P[:, :2, 3], axis=0), axis=1))])
    _, i1 = nearest_indices(relations.t1[used], trajectory.stamps, np.inf)
    _, i2 = nearest_indices(relations.t2[used], trajectory.stamps, np.inf)
    heading = np.degrees(np.abs(np.arctan2(E[:, 1, 0], E[:, 0, 0])))
    return np.abs(path[i2] - path[i1]), np.linalg.norm(E[:, :2, 3], axis=1), heading


@dataclass(frozen=True)
class ReferenceNoise:
    """The relations' own error, from how well they close among themselves: per relation, the standard
    deviation of each translation axis (m) and of the heading (rad), from *triangles* closed loops."""

    sigma_translation_m: float
    sigma_rotation_rad: float
    triangles: int

    def covariance(self) -> Array:
        """``(3, 3)`` in the planar tangent order (x, y, θ)."""
        return np.diag([self.sigma_translation_m**2, self.sigma_translation_m**2, self.sigma_rotation_rad**2])


def reference_noise(relations: Relations, min_triangles: int = 20) -> ReferenceNoise | None:
    """The relations' noise from their triangles: wherever the file holds a → b, b → c and a → c, the closure
    ``(δ_ab δ_bc)⁻¹ δ_ac`` would be the identity for exact relations; with independent per-relation errors of
    σ_t per axis and σ_θ its translation has variance 3σ_t² per axis and its angle 3σ_θ² (first order,
    the lever arm of a heading error over a relation's length left out), so σ_t² = mean(|t|²) / 6 and
    σ_θ² = mean(θ²) / 3. Planar relations; None with fewer than *min_triangles* triangles (no estimate).

    A ground-truth relation file is a measurement too (Kümmerle et al. 2009 built theirs from manually
    checked scan matching): a consistency test of an estimate against it (NEES) must add this covariance,
    or the relations' error is charged to the estimate."""
    key = {(round(float(a), 6), round(float(b), 6)): k for k, (a, b) in enumerate(zip(relations.t1, relations.t2))}
    starting: dict[float, list[tuple[float, int]]] = {}
    for (a, b), k in key.items():
        starting.setdefault(a, []).append((b, k))
    closures = []
    for (a, b), k_ab in key.items():
        for c, k_bc in starting.get(b, ()):
            k_ac = key.get((a, c))
            if k_ac is not None:
                closures.append(geo.se2_log(geo.relative(relations.deltas[k_ab] @ relations.deltas[k_bc],
                                                        relations.deltas[k_ac])))
    if len(closures) < min_triangles:
        return None
    e = np.array(closures)
    return ReferenceNoise(float(np.sqrt(np.mean(e[:, 0] ** 2 + e[:, 1] ** 2) / 6.0)),
                          float(np.sqrt(np.mean(e[:, 2] ** 2) / 3.0)), len(e))
