"""Registration benchmark (issue 3): our SVD-ICP vs Open3D, covariance NEES, KISS-ICP odometry.

Prints one JSON object whose first key is ``summary`` (the keys the issue fixes), followed by
the per-dataset detail. Everything is measured in this one run:

1. Fixed point and time of our point-to-point ICP vs ``open3d.pipelines.registration.registration_icp``
   (point-to-point) on the same inputs, gate and initial guess, on the 36 consecutive pairs of
   ``../shared/data/kitti_mini`` (sequences 00, 01, 07, 10; voxel 0.2 m, identity guess, 1 m gate),
   consecutive Intel scans (``data/intel.clf.bz2``, wheel-odometry guess, 0.5 m gate) and simulated
   SICK scan pairs in the 'rooms' world (known truth, identity guess, 0.5 m gate). Both run to a
   fixed point (tolerances 1e-10, ≤ 300 iterations); Open3D's convergence is checked by one more
   iteration from its result. Times are the best of ``--reps`` calls; ours includes the covariance
   and χ² test, Open3D's only fitness/RMSE (the summary ratio); the detail also gives the ratio
   against Open3D plus its ``get_information_matrix_from_point_clouds`` (the same outputs as ours).
   Beside Open3D, small_gicp (Koide 2024; the ``bench`` extra, optional: null keys without it) runs the
   same pairs point-to-point, one thread, same start, gate and stopping rule, timed the same way
   (``*_time_ratio_vs_small_gicp`` = ours / small_gicp; no target, it shows how far the limit is).
2. Our point-to-plane ICP and Open3D's against kitti_mini's SemanticKITTI poses, every consecutive pair
   (voxel 0.3 m, 20-neighbour normals): the largest step error (and small_gicp's, with its time against
   ours); KISS-ICP odometry's largest step error
   and end-point drift per sequence. The old ``kitti_odometry_00_sample``, whose official
   ``poses/00.txt`` is a constant-velocity placeholder over its frames, stays in the detail
   (``kitti_00_sample_placeholder_poses``) as the record of that finding.
3. NEES Monte Carlo (200 trials each): 2D line model (scan-like points on walls, σ = 1 cm, dense
   noise-free target every 2 mm), 3D plane model (box room, σ = 3 cm, target every 1 cm), and the
   point model with known correspondences (σ = 1 cm), 2D/3D.
4. The compiled 2D point-to-line and point-to-point ICPs against the same iterations in numpy (Intel
   scan onto the previous four scans, loop-closure settings): median speed-up and largest pose
   difference. (Section 1's 2D pairs run the compiled point-to-point loop.)
   The correlative branch and bound against an exhaustive search of the same window (same scans,
   guess pushed 0.8 m / 4° off): median speed-up and whether both reach the same maximum.
5. KISS-ICP odometry: throughput and Kümmerle relation
   error on the Intel log (planar defaults); wheel odometry alone as the baseline; with
   ``--icp-odometry`` also our IcpOdometry on the whole log (slow: minutes).

Usage: ``.venv/bin/python benchmarks/registration.py [--intel-pairs 200] [--sim-pairs 100]
[--icp-odometry] [--out result.json]``
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from core import geometry as geo  # noqa: E402
from registration.config import IcpConfig, KissOdometryConfig  # noqa: E402
from registration.icp import icp  # noqa: E402
from registration.point_to_plane import icp_point_to_plane  # noqa: E402
from registration.target import IcpTarget  # noqa: E402
from registration.voxel import voxel_downsample  # noqa: E402

KITTI = REPO.parent / "shared" / "data" / "kitti_odometry_00_sample" / "sequences" / "00"
# Ten real frames of each sequence, with SemanticKITTI's poses as ground truth (its SOURCE.md).
KITTI_MINI = REPO.parent / "shared" / "data" / "kitti_mini" / "sequences"
KITTI_MINI_SEQUENCES = ("00", "01", "07", "10")
INTEL = REPO / "data" / "intel.clf.bz2"
INTEL_REL = REPO / "data" / "intel.relations"
FIXED = dict(max_iterations=300, tol_translation_m=1e-10, tol_rotation_rad=1e-10, robust="none")


def _err(A: np.ndarray, B: np.ndarray) -> tuple[float, float]:
    """(translation m, rotation deg) of A⁻¹B."""
    E = geo.relative(A, B)
    return float(np.linalg.norm(E[:3, 3])), float(np.degrees(np.linalg.norm(geo.so3_log(E[:3, :3]))))


def _pcd(P: np.ndarray):
    import open3d as o3d

    c = o3d.geometry.PointCloud()
    c.points = o3d.utility.Vector3dVector(P if P.shape[1] == 3 else np.column_stack([P, np.zeros(len(P))]))
    return c


def compare_open3d(src: np.ndarray, tgt: np.ndarray, init: np.ndarray, gate: float, reps: int,
                   truth: np.ndarray | None = None) -> dict:
    """One pair: both ICPs to their fixed points; times (best of *reps*), fixed-point gap, errors."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    ps, pt = _pcd(src), _pcd(tgt)
    crit = reg.ICPConvergenceCriteria(relative_fitness=1e-12, relative_rmse=1e-12, max_iteration=300)
    est = reg.TransformationEstimationPointToPoint()
    cfg = IcpConfig(gates_m=(gate,), **FIXED)
    t_o, t_oi, t_u = [], [], []
    ro = ru = None
    for _ in range(reps):
        t0 = time.perf_counter()
        ro = reg.registration_icp(ps, pt, gate, init, est, crit)
        t_o.append(time.perf_counter() - t0)
        # Open3D's own information matrix at its result: the same outputs as ours (pose + information).
        reg.get_information_matrix_from_point_clouds(ps, pt, gate, ro.transformation)
        t_oi.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        try:
            ru = icp(src, tgt, init, cfg)
        except Exception as exc:  # noqa: BLE001 - recorded, the pair is then not comparable
            ru = exc
        t_u.append(time.perf_counter() - t0)
    To = np.asarray(ro.transformation)
    one = reg.registration_icp(ps, pt, gate, To, est, reg.ICPConvergenceCriteria(1e-12, 1e-12, 1))
    o3d_conv = bool(np.abs(np.asarray(one.transformation) - To).max() < 1e-9) and ro.fitness > 0
    out = {"n_src": len(src), "n_tgt": len(tgt), "time_ours_s": min(t_u), "time_open3d_s": min(t_o),
           "time_ratio": min(t_u) / min(t_o), "time_ratio_vs_open3d_with_information": min(t_u) / min(t_oi),
           "open3d_converged": o3d_conv, "open3d_fitness": ro.fitness}
    Ts = None
    if _small_gicp() is not None:
        sg, Ts = small_gicp_point_to_point(src, tgt, init, gate, reps)
        out.update(sg, time_ratio_vs_small_gicp=min(t_u) / sg["small_gicp_time_s"])
    if isinstance(ru, Exception):
        out.update(ours_converged=False, error=str(ru))
        return out
    dt, dth = _err(To, ru.transform)
    out.update(ours_converged=ru.converged, ours_iterations=ru.iterations, ours_fitness=ru.fitness,
               fixed_point_dt_m=dt, fixed_point_dtheta_deg=dth, chi2_accepted=ru.accepted)
    if Ts is not None:
        out["small_gicp_fixed_point_dt_m"], out["small_gicp_fixed_point_dtheta_deg"] = _err(Ts, ru.transform)
    if truth is not None:
        out["ours_err_m"], out["ours_err_deg"] = _err(truth, ru.transform)
        out["open3d_err_m"], out["open3d_err_deg"] = _err(truth, To)
        if Ts is not None:
            out["small_gicp_err_m"], out["small_gicp_err_deg"] = _err(truth, Ts)
    return out


# ----------------------------------------------------------------------------- small_gicp

# Its stopping rule is ours: the pose increment below 1e-10 rad and 1e-10 m (FIXED), ≤ 300 iterations.
# One thread: our ICP runs in this one Python thread (see notes.threads for its k-d tree queries).
SMALL_GICP_THREADS = 1
_SMALL_GICP_FIXED = dict(num_threads=SMALL_GICP_THREADS, rotation_epsilon=1e-10, translation_epsilon=1e-10)


def _small_gicp():
    """The ``small_gicp`` module, or None when it is not installed (the ``bench`` extra pins it; its keys
    are then null). small_gicp: K. Koide, "small_gicp: Efficient and parallel algorithms for point cloud
    registration", JOSS 9(100):6948, 2024 (MIT); ICP and point-to-plane ICP by Levenberg–Marquardt on SE(3)
    over a nanoflann k-d tree."""
    try:
        import small_gicp
    except ImportError:
        return None
    return small_gicp


def _sg_cloud(P: np.ndarray):
    """small_gicp's PointCloud of an N×2 or N×3 array (2D scans at z = 0, as :func:`_pcd` does)."""
    P = P if P.shape[1] == 3 else np.column_stack([P, np.zeros(len(P))])
    return _small_gicp().PointCloud(np.ascontiguousarray(P, dtype=np.float64))


def small_gicp_point_to_point(src: np.ndarray, tgt: np.ndarray, init: np.ndarray, gate: float,
                              reps: int) -> tuple[dict, np.ndarray]:
    """small_gicp's point-to-point ICP (``registration_type='ICP'``) on one pair, from *init* with the same
    gate and stopping rule as ours: ``(record, target_T_source)``. Timed as Open3D's call: the best of
    *reps*, each building the target's k-d tree (Open3D's ``registration_icp`` builds its own inside) and
    aligning; the conversion to the library's cloud type is outside, as ``_pcd`` is for Open3D.

    Converged = stopped before the cap and one more iteration from its result moving < 1e-8, with inliers.
    Its Levenberg–Marquardt loop (``optimizer.hpp``) also stops, its own flag unset, when no damping lowers
    the error any more: at the minimum to rounding, where one more call moves the pose by ~1e-9 (measured on
    kitti_mini), a little above Open3D's 1e-9 check, so that stop counts as converged; its flag is kept."""
    sg = _small_gicp()
    ps, pt = _sg_cloud(src), _sg_cloud(tgt)
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        tree = sg.KdTree(pt, num_threads=SMALL_GICP_THREADS)
        res = sg.align(pt, ps, tree, init_T_target_source=init, registration_type="ICP",
                       max_correspondence_distance=gate, max_iterations=300, **_SMALL_GICP_FIXED)
        times.append(time.perf_counter() - t0)
    T = np.asarray(res.T_target_source)
    one = sg.align(pt, ps, tree, init_T_target_source=T, registration_type="ICP",
                   max_correspondence_distance=gate, max_iterations=1, **_SMALL_GICP_FIXED)
    last = float(np.abs(np.asarray(one.T_target_source) - T).max())
    iterations = res.iterations + 1  # its count is 0-based
    stopped = res.converged or iterations < 300
    return {"small_gicp_time_s": min(times), "small_gicp_iterations": iterations,
            "small_gicp_converged": bool(stopped and last < 1e-8 and res.num_inliers > 0),
            "small_gicp_own_flag": bool(res.converged), "small_gicp_one_more_step": last,
            "small_gicp_inliers": res.num_inliers}, T


def small_gicp_point_to_plane(src: np.ndarray, tgt: np.ndarray, reps: int) -> tuple[np.ndarray, float]:
    """small_gicp's point-to-plane ICP (``'PLANE_ICP'``) with the settings of ours and Open3D's on kitti_mini:
    target normals from 20 neighbours (its ``estimate_normals``, the same normals as Open3D's to 1e-15),
    gates 1.0 / 0.5 / 0.3 m with 60 iterations each, identity start: ``(target_T_source, best time of reps)``;
    timed: k-d tree, normals and the stages.

    Not the same objective as ours and Open3D's: its factor (``plane_icp_factor.hpp``) weighs the residual
    by the normal element-wise, Σ‖n ∘ (q − T p)‖², where ours and Open3D minimise Σ (n · (q − T p))²
    (Chen & Medioni 1992). Each is at its own fixed point (each gradient ~1e-11 at its own result, ~8 at
    the other's on a kitti_mini pair), so the poses differ by mm to cm; the summary reports how much."""
    sg = _small_gicp()
    ps, pt = _sg_cloud(src), _sg_cloud(tgt)
    best = np.inf
    for _ in range(reps):
        t0 = time.perf_counter()
        tree = sg.KdTree(pt, num_threads=SMALL_GICP_THREADS)
        sg.estimate_normals(pt, tree, num_neighbors=20, num_threads=SMALL_GICP_THREADS)
        T = np.eye(4)
        for gate in (1.0, 0.5, 0.3):
            T = np.asarray(sg.align(pt, ps, tree, init_T_target_source=T, registration_type="PLANE_ICP",
                                    max_correspondence_distance=gate, max_iterations=60,
                                    **_SMALL_GICP_FIXED).T_target_source)
        best = min(best, time.perf_counter() - t0)
    return T, best


def kitti_frames():
    from slam.logs import open_log

    return list(open_log(KITTI).frames())


def bench_kitti(frames, reps: int) -> dict:
    gt = np.array([f.ground_truth for f in frames])
    pairs, p2pl, estimates = [], [], []
    for i in range(len(frames) - 1):
        truth = geo.relative(gt[i], gt[i + 1])
        S, T = voxel_downsample(frames[i + 1].points, 0.2), voxel_downsample(frames[i].points, 0.2)
        pairs.append(compare_open3d(S, T, np.eye(4), 1.0, reps, truth))
        t0 = time.perf_counter()
        tgt = IcpTarget(frames[i].points, voxel_m=0.3, normal_neighbors=20)
        r = icp_point_to_plane(voxel_downsample(frames[i + 1].points, 0.3), tgt, np.eye(4),
                               IcpConfig(gates_m=(1.0, 0.5, 0.3), max_iterations=60))
        e_m, e_deg = _err(truth, r.transform)
        estimates.append(r.transform)
        p2pl.append({"pair": f"{i + 1}->{i + 2}", "err_m": e_m, "err_deg": e_deg,
                     "err_forward_m": float(geo.relative(truth, r.transform)[0, 3]),
                     "est_step_m": float(np.linalg.norm(r.transform[:3, 3])),
                     "gt_step_m": float(np.linalg.norm(truth[:3, 3])), "iterations": r.iterations,
                     "time_s": time.perf_counter() - t0})
    return {"point_to_point_vs_open3d": pairs, "point_to_plane_vs_gt": p2pl,
            "ground_truth_check": kitti_ground_truth_check(frames, estimates)}


def bench_kitti_mini(reps: int) -> dict:
    """Every consecutive pair of the four kitti_mini sequences against SemanticKITTI's poses: our
    point-to-plane ICP and Open3D's (voxel 0.3 m, 20-neighbour normals, gates 1.0 / 0.5 / 0.3 m, identity
    start), KISS-ICP odometry's steps over each sequence (its default 3D configuration) and the pipeline's
    default 3D odometry's (our scan-to-map ICP); plus the
    point-to-point pairs of the fixed-point and time comparison (voxel 0.2 m, 1 m gate, identity start)."""
    from registration.odometry_kiss import KissOdometry
    from slam.logs import open_log
    from slam.pipeline.config import SlamConfig
    from slam.pipeline.odometry_source import make_odometry

    p2pl, kiss, default, pairs = [], {}, {}, []
    for seq in KITTI_MINI_SEQUENCES:
        frames = list(open_log(KITTI_MINI / seq).frames())
        gt = np.array([f.ground_truth for f in frames])
        official = _official_kitti_poses(KITTI_MINI / seq)
        for i in range(len(frames) - 1):
            truth = geo.relative(gt[i], gt[i + 1])
            src, tgt = voxel_downsample(frames[i + 1].points, 0.3), voxel_downsample(frames[i].points, 0.3)
            T, t_ours = _ours_point_to_plane(src, tgt, reps if _small_gicp() is not None else 1)
            (e_m, e_deg), (o_m, o_deg) = _err(truth, T), _err(truth, _open3d_point_to_plane(src, tgt))
            rec = {"sequence": seq, "pair": f"{i}->{i + 1}", "err_m": e_m, "err_deg": e_deg,
                   "open3d_err_m": o_m, "open3d_err_deg": o_deg,
                   "gt_step_m": float(np.linalg.norm(truth[:3, 3]))}
            if official is not None:  # the second reference: ours against it, and the two references against each other
                step = geo.relative(official[i], official[i + 1])
                rec["official_err_m"], rec["official_err_deg"] = _err(step, T)
                rec["references_disagree_m"], rec["references_disagree_deg"] = _err(truth, step)
            if _small_gicp() is not None:
                Ts, t_sg = small_gicp_point_to_plane(src, tgt, reps)
                rec["small_gicp_err_m"], rec["small_gicp_err_deg"] = _err(truth, Ts)
                rec["small_gicp_vs_ours_m"], rec["small_gicp_vs_ours_deg"] = _err(Ts, T)
                rec.update(time_ours_s=t_ours, small_gicp_time_s=t_sg, time_ratio_vs_small_gicp=t_ours / t_sg)
            p2pl.append(rec)
            pairs.append(compare_open3d(voxel_downsample(frames[i + 1].points, 0.2),
                                        voxel_downsample(frames[i].points, 0.2), np.eye(4), 1.0, reps, truth))
        kiss[seq] = _odometry_vs_gt(KissOdometry(KissOdometryConfig(compute_covariance=False)), frames, gt)
        default[seq] = _odometry_vs_gt(make_odometry(SlamConfig(), planar=False), frames, gt)
    return {"point_to_plane_vs_gt": p2pl, "kiss": kiss, "default_odometry": default, "point_to_point_vs_open3d": pairs}


#: kitti_mini sequences whose official poses are KITTI's constant-velocity placeholder over these frames (SOURCE.md)
OFFICIAL_PLACEHOLDER_SEQUENCES = ("00",)


def _reference_keys(p2pl: list[dict]) -> dict:
    """How far kitti_mini's two references (SemanticKITTI's and KITTI's official poses) disagree per step, and
    our point-to-plane steps against the official ones, over the sequences whose official poses are real:
    a step error below the references' own disagreement cannot be told from them."""
    real = [p for p in p2pl if "official_err_m" in p and p["sequence"] not in OFFICIAL_PLACEHOLDER_SEQUENCES]
    if not real:
        return {}
    return {"kitti_mini_references_max_disagreement_m": max(p["references_disagree_m"] for p in real),
            "kitti_mini_references_max_disagreement_deg": max(p["references_disagree_deg"] for p in real),
            "kitti_mini_p2plane_max_step_err_vs_official_m": max(p["official_err_m"] for p in real),
            "kitti_mini_p2plane_max_step_err_vs_official_deg": max(p["official_err_deg"] for p in real)}


def _official_kitti_poses(sequence_dir: Path) -> np.ndarray | None:
    """kitti_mini's second reference, the official KITTI (OXTS) poses kept beside SemanticKITTI's
    (``poses_kitti_gt.txt``, SOURCE.md), in the Velodyne frame (``Tr⁻¹ · P_k · Tr``); None without it."""
    from slam.logs.kitti import read_calib, read_kitti_poses

    path = sequence_dir / "poses_kitti_gt.txt"
    if not path.is_file():
        return None
    Tr = read_calib(sequence_dir / "calib.txt")["Tr"]
    return geo.inverse(Tr) @ read_kitti_poses(path) @ Tr


def _odometry_vs_gt(odo, frames: list, gt: np.ndarray) -> dict:  # type: ignore[no-untyped-def]
    """Run the odometry *odo* over *frames*: its steps against the ground truth *gt* (largest error, m and °),
    its end-point drift (% of the distance travelled) and its time per scan."""
    t0 = time.perf_counter()
    odo.run(frames)
    per_scan = (time.perf_counter() - t0) / len(frames)
    P = np.array([st.world_T_sensor for st in odo.steps])
    steps = [_err(geo.relative(gt[k], gt[k + 1]), geo.relative(P[k], P[k + 1])) for k in range(len(P) - 1)]
    G = geo.relative(gt[0], gt)
    dist = float(np.sum(np.linalg.norm(np.diff(G[:, :3, 3], axis=0), axis=1)))
    return {"max_step_err_m": max(e for e, _ in steps), "max_step_err_deg": max(d for _, d in steps),
            "step_err_m": [e for e, _ in steps], "s_per_scan": per_scan,
            "drift_percent": 100.0 * _err(G[-1], geo.relative(P[0], P[-1]))[0] / dist, "distance_m": dist}


def _ours_point_to_plane(src: np.ndarray, tgt: np.ndarray, reps: int) -> tuple[np.ndarray, float]:
    """Our point-to-plane ICP on kitti_mini (voxel 0.3 m, 20-neighbour normals, gates 1.0 / 0.5 / 0.3 m,
    identity start): ``(target_T_source, best time of reps)``; timed: the target (k-d tree, normals) and
    the stages."""
    best = np.inf
    for _ in range(reps):
        t0 = time.perf_counter()
        target, T = IcpTarget(tgt, normal_neighbors=20), np.eye(4)
        # 60 iterations per gate, as Open3D's loop below (ours caps all stages at once)
        for gate in (1.0, 0.5, 0.3):
            T = icp_point_to_plane(src, target, T, IcpConfig(gates_m=(gate,), max_iterations=60)).transform
        best = min(best, time.perf_counter() - t0)
    return T, best


def _open3d_point_to_plane(src: np.ndarray, tgt: np.ndarray) -> np.ndarray:
    """Open3D's point-to-plane ICP (same voxel, normals, gates as ours): an independent estimate."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    ps, pt = _pcd(src), _pcd(tgt)
    pt.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(20))
    T = np.eye(4)
    for gate in (1.0, 0.5, 0.3):
        T = np.asarray(reg.registration_icp(ps, pt, gate, T, reg.TransformationEstimationPointToPlane(),
                                            reg.ICPConvergenceCriteria(1e-10, 1e-10, 60)).transformation)
    return T


def kitti_ground_truth_check(frames, ours: list[np.ndarray]) -> dict:
    """Do the sample's scans move as its ground-truth lines say?

    Compares the scan-to-scan motions measured by our point-to-plane ICP and, independently, by
    Open3D's, with every window of ``len(frames)`` consecutive lines of ``poses/00.txt``: the
    largest per-pair error at the window the sample claims (its frame numbers) and at the window
    that fits best. A best window elsewhere that both registrations fit to ~cm, while the claimed
    one misses by dm, says the scans are not the frames their file names claim."""
    from slam.logs.kitti import KittiReader

    reader = KittiReader(KITTI)
    gt = reader.ground_truth_velo()
    rel_gt = geo.relative(gt[:-1], gt[1:])  # line k → k+1
    o3d_est = [_open3d_point_to_plane(voxel_downsample(frames[i + 1].points, 0.3),
                                      voxel_downsample(frames[i].points, 0.3)) for i in range(len(frames) - 1)]
    claimed = reader.frame_number(0)  # the poses line of the first scan, by its file name
    out = {"claimed_first_line": claimed, "windows_tested": int(len(rel_gt) - len(ours) + 1)}
    for name, est in (("ours_point_to_plane", ours), ("open3d_point_to_plane", o3d_est)):
        n = len(est)
        E = np.array(est)
        err_t = np.empty((len(rel_gt) - n + 1, n))
        err_r = np.empty_like(err_t)
        for j in range(n):  # window start s: pair j is GT line s+j → s+j+1
            D = geo.relative(rel_gt[j:len(rel_gt) - n + 1 + j], E[j][None])
            err_t[:, j] = np.linalg.norm(D[:, :3, 3], axis=1)
            err_r[:, j] = np.degrees(np.arccos(np.clip((np.trace(D[:, :3, :3], axis1=1, axis2=2) - 1) / 2, -1, 1)))
        worst = err_t.max(axis=1)
        best = np.argsort(worst)[:3]
        out[name] = {
            "claimed_window_max_err_m": float(worst[claimed]), "claimed_window_max_err_deg": float(err_r[claimed].max()),
            "best_windows": [{"first_line": int(s), "max_err_m": float(worst[s]), "max_err_deg": float(err_r[s].max())}
                             for s in best],
            "step_m": [float(np.linalg.norm(T[:3, 3])) for T in est],
        }
    out["claimed_window_gt_step_m"] = [float(np.linalg.norm(T[:3, 3])) for T in rel_gt[claimed:claimed + len(ours)]]
    return out


def bench_intel(n_pairs: int, reps: int) -> tuple[dict, list]:
    from slam.logs import open_log

    frames = list(open_log(INTEL).frames())
    idx = np.linspace(0, len(frames) - 2, n_pairs).astype(int)
    pairs = []
    for k in idx:
        a, b = frames[k], frames[k + 1]
        pairs.append(compare_open3d(b.points, a.points, geo.relative(a.odom, b.odom), 0.5, reps))
    return {"pairs": pairs}, frames


def bench_compiled_point_to_line(frames, n_pairs: int, reps: int, point_to_point: bool = False) -> dict:
    """The compiled 2D point-to-line ICP (registration.kernels_icp) against the same iterations in numpy:
    scan k+1 onto the local map of scans k−3 … k (wheel-odometry placement), from the wheel guess,
    with the loop-closure settings (gates 1.0 / 0.4 / 0.15 m, Cauchy, 8-neighbour normals). Times
    are the best of *reps* calls, each including the target's construction (k-d tree or grid, normals).
    *point_to_point*: the same for the SVD point-to-point ICP (kernels_icp.point_icp_2d against icp()'s numpy
    iterations on the k-d tree)."""
    from registration import alignment
    from registration import point_to_plane as p2l
    from registration.config import IcpConfig

    align = icp if point_to_point else p2l.icp_point_to_plane

    cfg = IcpConfig(gates_m=(1.0, 0.4, 0.15), robust="cauchy", robust_scale_m=0.06, sigma_m=0.03, max_iterations=40,
                    tol_translation_m=1e-4, tol_rotation_rad=1e-4, normal_neighbors=8, workers=1)
    idx = np.linspace(3, len(frames) - 2, n_pairs).astype(int)
    times = {True: [], False: []}
    diffs = []
    for k in idx:
        ref = frames[k]
        tgt_pts = np.vstack([geo.transform_points(geo.relative(ref.odom, frames[m].odom), frames[m].points)
                             for m in range(k - 3, k + 1)])
        src, guess = frames[k + 1].points, geo.relative(ref.odom, frames[k + 1].odom)
        poses = {}
        for compiled in (True, False):
            alignment.COMPILED_2D = compiled
            best = np.inf
            for _ in range(reps):
                t0 = time.perf_counter()
                try:
                    poses[compiled] = align(src, IcpTarget(tgt_pts, normal_neighbors=8, workers=1), guess, cfg).transform
                except Exception:  # noqa: BLE001 - a degenerate pair fails in both; timed all the same
                    poses[compiled] = None
                best = min(best, time.perf_counter() - t0)
            times[compiled].append(best)
        alignment.COMPILED_2D = True
        if poses[True] is not None and poses[False] is not None:
            diffs.append(float(np.abs(poses[True] - poses[False]).max()))
    return {"pairs": len(idx), "both_aligned": len(diffs),
            "median_time_compiled_s": float(np.median(times[True])),
            "median_time_numpy_s": float(np.median(times[False])),
            "speedup_vs_numpy": float(np.median(np.array(times[False]) / np.array(times[True]))),
            "max_pose_difference": float(max(diffs, default=np.nan))}


def bench_correlative(frames, n_pairs: int, reps: int) -> dict:
    """The compiled depth-first branch and bound of ``registration.correlative.match`` against an
    exhaustive search of the same discretised window (every heading and offset scored at full
    resolution by the same compiled gather): scan k+1 onto the local map of scans k−3 … k (wheel-odometry
    placement) at the loop-closure settings (0.1 m field, ±2.5 m, ±10°), from the wheel guess pushed
    0.8 m / −0.6 m / 4° off. Times are the best of *reps* calls; the pyramid is built once per pair
    (loop closure caches it per place). Reports the median speed-up and whether both find the same
    maximum score."""
    from registration import correlative as C

    idx = np.linspace(3, len(frames) - 2, n_pairs).astype(int)
    push = geo.xytheta_to_matrix(0.8, -0.6, np.radians(4.0))
    win_m, win_rad = 2.5, np.radians(10.0)
    t_bnb, t_all, same, gap = [], [], 0, []
    for k in idx:
        ref = frames[k]
        tgt = np.vstack([geo.transform_points(geo.relative(ref.odom, frames[m].odom), frames[m].points)
                         for m in range(k - 3, k + 1)])
        src, guess = frames[k + 1].points, geo.relative(ref.odom, frames[k + 1].odom) @ push
        w = int(np.ceil(win_m / 0.1))
        pyr = C.LikelihoodPyramid(tgt, 0.1, 0.1, levels=int(np.ceil(np.log2(2 * w + 1))))
        best = np.inf
        for _ in range(reps):
            t0 = time.perf_counter()
            found = C.match(src, pyr, guess, win_m, win_rad)
            best = min(best, time.perf_counter() - t0)
        t_bnb.append(best)
        best = np.inf
        for _ in range(reps):
            t0 = time.perf_counter()
            g = C.search_grid(src, pyr, guess, win_m, win_rad)
            off = np.stack(np.meshgrid(np.arange(-g.w, g.w + 1), np.arange(-g.w, g.w + 1), indexing="ij"), -1).reshape(-1, 2)
            top = max(float(pyr.score_candidates(0, g.cells, np.full(len(off), r), off).max()) for r in range(len(g.thetas)))
            best = min(best, time.perf_counter() - t0)
        t_all.append(best)
        same += int(abs(found.score - max(top, found.guess_score)) <= 1e-12)
        gap.append(max(top, found.guess_score) - found.score)
    return {"pairs": len(idx), "same_maximum": same,
            "median_time_branch_and_bound_s": float(np.median(t_bnb)),
            "median_time_exhaustive_s": float(np.median(t_all)),
            "speedup_vs_exhaustive": float(np.median(np.array(t_all) / np.array(t_bnb))),
            "largest_score_shortfall": float(max(gap, default=np.nan))}


def bench_sim(n_pairs: int, reps: int) -> dict:
    from evaluation import sim

    world = sim.load_world("rooms")
    spec = sim.LASER_PRESETS["sick_lms"]
    ang = spec.angles()
    xs, ys = world.cell_centres()
    iy, ix = np.nonzero(world.free)
    rng = np.random.default_rng(2024)

    def pts(r):
        ok = np.isfinite(r)
        return np.column_stack([r[ok] * np.cos(ang[ok]), r[ok] * np.sin(ang[ok])])

    pairs = []
    while len(pairs) < n_pairs:
        k = rng.integers(len(iy))
        a = np.array([xs[ix[k]], ys[iy[k]], rng.uniform(-np.pi, np.pi)])
        d = geo.xytheta_to_matrix(*(rng.normal(size=3) * [0.1, 0.05, 0.03]))
        b = geo.matrix_to_xytheta(geo.xytheta_to_matrix(a) @ d)
        jy, jx = world.cell_of(b[None, :2])
        if not (0 <= jy[0] < world.shape[0] and 0 <= jx[0] < world.shape[1] and world.free[jy[0], jx[0]]):
            continue
        R = sim.cast_rays(world, np.stack([a, b]), spec, rng=rng, range_noise=spec.noise_std)
        Pa, Pb = pts(R[0]), pts(R[1])
        if len(Pa) < 30 or len(Pb) < 30:
            continue
        pairs.append(compare_open3d(Pb, Pa, np.eye(4), 0.5, reps, d))
    return {"pairs": pairs}


# ----------------------------------------------------------------------------- NEES

def _segments(segs, n, rng):
    L = np.hypot(segs[:, 2] - segs[:, 0], segs[:, 3] - segs[:, 1])
    k = rng.choice(len(segs), n, p=L / L.sum())
    u = rng.uniform(size=n)[:, None]
    return segs[k, :2] + u * (segs[k, 2:] - segs[k, :2])


def _dense(segs, step):
    return np.vstack([s[:2] + (np.arange(0, np.hypot(*(s[2:] - s[:2])), step)[:, None] / np.hypot(*(s[2:] - s[:2])))
                      * (s[2:] - s[:2]) for s in segs])


def _box(step, L=(3.0, 2.0, 2.0)):
    out = []
    for ax in range(3):
        a, b = [i for i in range(3) if i != ax]
        A, B = np.meshgrid(np.arange(0, L[a] + 1e-9, step), np.arange(0, L[b] + 1e-9, step))
        for v in (0.0, L[ax]):
            p = np.zeros((A.size, 3))
            p[:, a], p[:, b], p[:, ax] = A.ravel(), B.ravel(), v
            out.append(p)
    return np.vstack(out) - np.array(L) / 2


def _nees(T_est, T_true, cov):
    """δ = Log(T_est⁻¹ T_true): T_true = T_est · Exp(δ) (right perturbation, translation first)."""
    E = geo.relative(T_est, T_true)
    d = geo.se2_log(E) if cov.shape[0] == 3 else geo.se3_log(E)
    return float(d @ np.linalg.solve(cov, d))


def bench_nees(trials: int = 200, sigma: float = 0.01) -> dict:
    rng = np.random.default_rng(7)
    out = {}
    # 2D line model
    room = np.array([[0, 0, 8, 0], [8, 0, 8, 5], [8, 5, 0, 5], [0, 5, 0, 0], [3, 0, 3, 2.5], [5, 5, 6.5, 3.5]], float)
    tgt = IcpTarget(_dense(room, 0.002))
    cfg = IcpConfig(gates_m=(0.3, 0.1), sigma_m=sigma, tol_translation_m=1e-9, tol_rotation_rad=1e-9)
    v = []
    for _ in range(trials):
        T = geo.se2_exp(rng.normal(size=3) * [0.05, 0.05, 0.02])
        P = _segments(room, 300, rng) + rng.normal(scale=sigma, size=(300, 2))
        r = icp(geo.transform_points(geo.inverse(T), P), tgt, None, cfg)
        v.append(_nees(r.transform, T, r.covariance))
    out["2d_plane_model"] = float(np.mean(v) / 3)
    # 3D plane model: box room, source points away from the edges (normals there are undefined).
    # Point-to-point NN on a sampled surface equals the plane least-squares estimator (whose Fisher
    # information the covariance is) only when the sampling step is ≪ σ: the tangential offset to
    # the nearest grid point is extra, unmodelled noise ∝ (step/σ)². Measured with a 1 cm grid:
    # σ = 1 cm → NEES/dof 1.21, 2 cm → 1.10, 3 cm → 1.05; so 3D uses σ3 = 3 cm (2D: 2 mm vs 1 cm).
    t0 = time.perf_counter()
    sigma3 = 3.0 * sigma
    tgt = IcpTarget(_box(0.01))
    cand = _box(0.05)
    half = np.array([1.5, 1.0, 1.0])
    inner = (np.sum(np.abs(np.abs(cand) - half) < 0.1, axis=1) <= 1)
    cand = cand[inner]
    cfg = IcpConfig(gates_m=(0.3, 8.0 * sigma3), sigma_m=sigma3, tol_translation_m=1e-9, tol_rotation_rad=1e-9)
    v = []
    for _ in range(trials):
        T = geo.se3_exp(rng.normal(size=6) * [0.02, 0.02, 0.02, 0.01, 0.01, 0.01])
        P = cand[rng.choice(len(cand), 400, replace=False)]
        r = icp(geo.transform_points(geo.inverse(T), P + rng.normal(scale=sigma3, size=P.shape)), tgt, None, cfg)
        v.append(_nees(r.transform, T, r.covariance))
    out["3d_plane_model"] = float(np.mean(v) / 6)
    out["3d_plane_model_sigma_m"], out["3d_plane_model_target_step_m"] = sigma3, 0.01
    out["3d_plane_model_time_s"] = time.perf_counter() - t0
    # point model with known correspondences (well separated points, noise on both sides)
    for dim in (2, 3):
        cfg = IcpConfig(gates_m=(0.5,), covariance_model="point", sigma_m=sigma, tol_translation_m=1e-10, tol_rotation_rad=1e-10)
        v = []
        for _ in range(trials):
            T = (geo.se2_exp(rng.normal(size=3) * [0.05, 0.05, 0.02]) if dim == 2
                 else geo.se3_exp(rng.normal(size=6) * [0.05, 0.05, 0.05, 0.01, 0.01, 0.01]))
            base = rng.uniform(-5, 5, size=(150, dim))
            t = base + rng.normal(scale=sigma / np.sqrt(2), size=base.shape)
            s = geo.transform_points(geo.inverse(T), base) + rng.normal(scale=sigma / np.sqrt(2), size=base.shape)
            r = icp(s, t, None, cfg)
            v.append(_nees(r.transform, T, r.covariance))
        out[f"{dim}d_point_model"] = float(np.mean(v) / (3 if dim == 2 else 6))
    out["trials"] = trials
    return out


# ----------------------------------------------------------------------------- odometry

def bench_kiss_kitti(frames) -> dict:
    from registration.odometry_kiss import KissOdometry

    odo = KissOdometry(KissOdometryConfig())
    t0 = time.perf_counter()
    odo.run(frames)
    wall = time.perf_counter() - t0
    gt = np.array([f.ground_truth for f in frames])
    G = geo.relative(gt[0], gt)
    dist = float(np.sum(np.linalg.norm(np.diff(G[:, :3, 3], axis=0), axis=1)))
    e_m, e_deg = _err(G[-1], odo.world_T_sensor)
    steps = [float(np.linalg.norm(s.prev_T_curr[:3, 3])) for s in odo.steps[1:]]
    return {"distance_m": dist, "end_point_error_m": e_m, "end_point_error_deg": e_deg,
            "drift_percent": 100.0 * e_m / dist, "kiss_steps_m": steps,
            "gt_steps_m": [float(x) for x in np.linalg.norm(np.diff(G[:, :3, 3], axis=0), axis=1)],
            "time_s": wall}


def _relations(stamps, poses):
    from core.trajectory import Trajectory
    from evaluation.relations import evaluate_relations, read_relations

    r = evaluate_relations(Trajectory(stamps, poses), read_relations(INTEL_REL))
    return {"trans_mean_m": r.trans_mean, "trans_std_m": r.trans_std, "rot_mean_deg": r.rot_mean_deg,
            "rot_std_deg": r.rot_std_deg, "trans_median_m": float(np.median(r.trans_errors)),
            "rot_median_deg": float(np.median(r.rot_errors_deg)), "n_used": r.n_used, "n_missing": r.n_missing}


def bench_intel_odometry(frames, icp_odometry: bool) -> dict:
    from kiss_icp.kiss_icp import KissICP

    from registration.odometry import IcpOdometry
    from registration.odometry_kiss import KissOdometry

    out = {"scans": len(frames)}
    stamps = np.array([f.stamp for f in frames])
    out["wheel_odometry_relations"] = _relations(stamps, np.array([f.odom for f in frames]))
    base = KissOdometryConfig.planar_default()
    for name, cfg in (("kiss_odometry_with_covariance", base),
                      ("kiss_odometry_no_covariance", base.model_copy(update={"compute_covariance": False}))):
        odo = KissOdometry(cfg)
        c0, w0 = time.process_time(), time.perf_counter()
        odo.run(frames)
        cpu, wall = time.process_time() - c0, time.perf_counter() - w0
        out[name] = {"scans_per_s_cpu": len(frames) / cpu, "scans_per_s_wall": len(frames) / wall,
                     "relations": _relations(odo.stamps(), odo.poses(base=True))}
    # KissICP itself, points pre-built: the floor set by KISS-ICP's own per-frame cost.
    kiss = KissICP(base.to_kiss(planar=True))
    pts = [f.points_3d() for f in frames]
    z = np.zeros(0)
    c0, w0 = time.process_time(), time.perf_counter()
    for p in pts:
        kiss.register_frame(p, z)
    out["kiss_icp_register_frame_only"] = {"scans_per_s_cpu": len(pts) / (time.process_time() - c0),
                                           "scans_per_s_wall": len(pts) / (time.perf_counter() - w0)}
    out["config"] = base.model_dump()
    if icp_odometry:
        odo = IcpOdometry()
        c0, w0 = time.process_time(), time.perf_counter()
        odo.run(frames)
        out["icp_odometry"] = {"scans_per_s_cpu": len(frames) / (time.process_time() - c0),
                               "scans_per_s_wall": len(frames) / (time.perf_counter() - w0),
                               "relations": _relations(odo.stamps(), odo.poses(base=True))}
    return out


def _summarise_pairs(groups: dict[str, list]) -> dict:
    ratios, dts, dths, detail = [], [], [], {}
    for name, pairs in groups.items():
        both = [p for p in pairs if p.get("ours_converged") and p["open3d_converged"]]
        r = [p["time_ratio"] for p in pairs]
        ratios += r
        dts += [p["fixed_point_dt_m"] for p in both]
        dths += [p["fixed_point_dtheta_deg"] for p in both]
        agree = [p for p in both if p["fixed_point_dt_m"] <= 1e-3 and p["fixed_point_dtheta_deg"] <= 0.01]
        detail[name] = {"pairs": len(pairs), "both_converged": len(both), "fixed_point_agree": len(agree),
                        "median_time_ratio": float(np.median(r)),
                        "median_time_ratio_vs_open3d_with_information":
                            float(np.median([p["time_ratio_vs_open3d_with_information"] for p in pairs])),
                        "median_time_ours_s": float(np.median([p["time_ours_s"] for p in pairs])),
                        "median_time_open3d_s": float(np.median([p["time_open3d_s"] for p in pairs])),
                        "max_fixed_point_dt_m": float(max((p["fixed_point_dt_m"] for p in both), default=np.nan)),
                        "max_fixed_point_dtheta_deg": float(max((p["fixed_point_dtheta_deg"] for p in both), default=np.nan))}
        errs = [p for p in pairs if "ours_err_m" in p]
        if errs:
            detail[name]["median_err_ours_m"] = float(np.median([p["ours_err_m"] for p in errs]))
            detail[name]["median_err_open3d_m"] = float(np.median([p["open3d_err_m"] for p in errs]))
        detail[name].update(_summarise_small_gicp(pairs))
    every = [p for pairs in groups.values() for p in pairs]
    return {"median_time_ratio": float(np.median(ratios)), "max_dt": float(max(dts)), "max_dth": float(max(dths)),
            "per_dataset": detail, "small_gicp": _summarise_small_gicp(every)}


def _stat(f, values: list) -> float | None:
    return float(f(values)) if values else None


def _summarise_small_gicp(pairs: list) -> dict:
    """small_gicp's point-to-point beside ours on *pairs*: the median time ratio (ours / small_gicp, all
    pairs as for Open3D) and, where both converged, how far its fixed point is from ours; None without it."""
    timed = [p for p in pairs if "time_ratio_vs_small_gicp" in p]
    both = [p for p in timed if p.get("ours_converged") and p["small_gicp_converged"]]
    dts = [p["small_gicp_fixed_point_dt_m"] for p in both]
    dths = [p["small_gicp_fixed_point_dtheta_deg"] for p in both]
    agree = sum(dt <= 1e-3 and dth <= 0.01 for dt, dth in zip(dts, dths))  # Open3D's agreement bounds
    ratios = [p["time_ratio_vs_small_gicp"] for p in timed]
    out = {"median_time_ratio_vs_small_gicp": _stat(np.median, ratios),
           "median_time_small_gicp_s": _stat(np.median, [p["small_gicp_time_s"] for p in timed]),
           "small_gicp_both_converged": len(both) if timed else None,
           "small_gicp_fixed_point_agree": agree if timed else None,
           "median_small_gicp_fixed_point_dt_m": _stat(np.median, dts),
           "max_small_gicp_fixed_point_dt_m": _stat(max, dts),
           "median_small_gicp_fixed_point_dtheta_deg": _stat(np.median, dths),
           "max_small_gicp_fixed_point_dtheta_deg": _stat(max, dths)}
    errs = [p["small_gicp_err_m"] for p in timed if "small_gicp_err_m" in p]
    if errs:
        out["median_err_small_gicp_m"] = float(np.median(errs))
    return out


def _small_gicp_p2plane_summary(p2pl: list) -> dict:
    """The kitti_mini point-to-plane keys of small_gicp (None without it): largest step error against the
    SemanticKITTI poses, largest difference to ours, median time ratio ours / small_gicp."""
    sg = [p for p in p2pl if "small_gicp_err_m" in p]

    def col(key: str) -> list:
        return [p[key] for p in sg]

    name = "kitti_mini_small_gicp_p2plane_"
    return {f"{name}max_step_err_m": _stat(max, col("small_gicp_err_m")),
            f"{name}max_step_err_deg": _stat(max, col("small_gicp_err_deg")),
            f"{name}max_diff_to_ours_m": _stat(max, col("small_gicp_vs_ours_m")),
            f"{name}max_diff_to_ours_deg": _stat(max, col("small_gicp_vs_ours_deg")),
            "kitti_mini_p2plane_median_time_ratio_vs_small_gicp":
                _stat(np.median, col("time_ratio_vs_small_gicp"))}


def _version(dist: str) -> str | None:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(dist)
    except PackageNotFoundError:
        return None


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--intel-pairs", type=int, default=200)
    ap.add_argument("--sim-pairs", type=int, default=100)
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--nees-trials", type=int, default=200)
    ap.add_argument("--icp-odometry", action="store_true", help="also run IcpOdometry on the whole Intel log")
    ap.add_argument("--out", type=Path, default=None, help="also write the JSON here (atomically)")
    args = ap.parse_args(argv)
    import open3d as o3d

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    if _small_gicp() is None:
        print("warning: small_gicp is not installed (pip install -e '.[bench]'); its keys are null",
              file=sys.stderr)
    t_start = time.perf_counter()
    kf = kitti_frames()
    kitti = bench_kitti(kf, args.reps)
    mini = bench_kitti_mini(args.reps)
    intel, intel_frames = bench_intel(args.intel_pairs, args.reps)
    simr = bench_sim(args.sim_pairs, args.reps)
    compiled = bench_compiled_point_to_line(intel_frames, args.intel_pairs, args.reps)
    compiled_p2p = bench_compiled_point_to_line(intel_frames, args.intel_pairs, args.reps, point_to_point=True)
    corr = bench_correlative(intel_frames, args.intel_pairs, args.reps)
    pp = _summarise_pairs({"kitti_mini": mini["point_to_point_vs_open3d"], "intel": intel["pairs"], "sim": simr["pairs"]})
    nees = bench_nees(args.nees_trials)
    kk = bench_kiss_kitti(kf)
    io = bench_intel_odometry(intel_frames, args.icp_odometry)
    p2pl = kitti["point_to_plane_vs_gt"]
    summary = {
        "median_time_ratio_vs_open3d": pp["median_time_ratio"],
        "max_fixed_point_dt_m": pp["max_dt"],
        "max_fixed_point_dtheta_deg": pp["max_dth"],
        "kitti_mini_p2plane_max_step_err_m": max(p["err_m"] for p in mini["point_to_plane_vs_gt"]),
        "kitti_mini_p2plane_max_step_err_deg": max(p["err_deg"] for p in mini["point_to_plane_vs_gt"]),
        "kitti_mini_open3d_p2plane_max_step_err_m": max(p["open3d_err_m"] for p in mini["point_to_plane_vs_gt"]),
        "kitti_mini_open3d_p2plane_max_step_err_deg": max(p["open3d_err_deg"] for p in mini["point_to_plane_vs_gt"]),
        **_reference_keys(mini["point_to_plane_vs_gt"]),
        "kiss_kitti_mini_max_step_err_m": max(v["max_step_err_m"] for v in mini["kiss"].values()),
        "kiss_kitti_mini_max_drift_percent": max(v["drift_percent"] for v in mini["kiss"].values()),
        "default_odometry_kitti_mini_max_step_err_m": max(v["max_step_err_m"] for v in mini["default_odometry"].values()),
        "default_odometry_kitti_mini_max_drift_percent": max(v["drift_percent"] for v in mini["default_odometry"].values()),
        "nees_2d_over_dof": nees["2d_plane_model"],
        "nees_3d_over_dof": nees["3d_plane_model"],
        "kiss_intel_scans_per_s": io["kiss_odometry_with_covariance"]["scans_per_s_cpu"],
        "compiled_point_to_line_speedup_vs_numpy": compiled["speedup_vs_numpy"],
        "compiled_point_to_line_max_pose_difference": compiled["max_pose_difference"],
        "compiled_point_to_point_speedup_vs_numpy": compiled_p2p["speedup_vs_numpy"],
        "compiled_point_to_point_max_pose_difference": compiled_p2p["max_pose_difference"],
        "correlative_branch_and_bound_speedup_vs_exhaustive": corr["speedup_vs_exhaustive"],
        "correlative_branch_and_bound_same_maximum": f"{corr['same_maximum']} of {corr['pairs']}",
        # small_gicp beside Open3D (no target: how far the limit is); ratios are ours / small_gicp.
        "median_time_ratio_vs_small_gicp": pp["small_gicp"]["median_time_ratio_vs_small_gicp"],
        **{f"{name}_median_time_ratio_vs_small_gicp": d["median_time_ratio_vs_small_gicp"]
           for name, d in pp["per_dataset"].items()},
        "max_small_gicp_fixed_point_dt_m": pp["small_gicp"]["max_small_gicp_fixed_point_dt_m"],
        "max_small_gicp_fixed_point_dtheta_deg": pp["small_gicp"]["max_small_gicp_fixed_point_dtheta_deg"],
        **_small_gicp_p2plane_summary(mini["point_to_plane_vs_gt"]),
        "small_gicp_threads": SMALL_GICP_THREADS if _small_gicp() is not None else None,
    }
    import os

    result = {
        "summary": summary,
        "notes": {
            "nees": "summary NEES = default covariance model (plane/line); point-model values in nees.*_point_model",
            "kiss_intel_scans_per_s": "KissOdometry (planar defaults, with covariance) scans per CPU second of this "
                                      "single-threaded process; wall-clock rates are in intel_odometry (the machine "
                                      "is shared, so wall time measures its load too)",
            "time_ratio": "ours includes covariance + chi2 test; both include kd-tree construction",
            "time_ratio_vs_small_gicp":
                "ours / small_gicp on the same pairs, start, gate and stopping rule; small_gicp's time "
                "includes its k-d tree (and normals for point-to-plane), as Open3D's and ours do; ours includes "
                "covariance + chi2 test. Its point-to-plane minimises sum |n o r|^2 (element-wise), not "
                "sum (n . r)^2 as ours and Open3D: a nearby but different fixed point "
                "(kitti_mini_small_gicp_p2plane_max_diff_to_ours_*)",
            "threads": {"small_gicp": SMALL_GICP_THREADS,
                        "ours": "one Python thread; scipy cKDTree queries of >= 20000 points use all cores "
                                "(IcpConfig.workers = -1), as on kitti_mini's 0.2 m clouds",
                        "open3d": "its OpenMP default (all cores)", "cores": os.cpu_count()},
            "small_gicp_version": _version("small-gicp"),
            "load_average": os.getloadavg(),
        },
        "fixed_point_and_time": pp["per_dataset"],
        "compiled_point_to_line_intel": compiled,
        "compiled_point_to_point_intel": compiled_p2p,
        "correlative_intel": corr,
        "nees": nees,
        "kitti_mini_point_to_plane": mini["point_to_plane_vs_gt"],
        "kiss_kitti_mini": mini["kiss"],
        "default_odometry_kitti_mini": mini["default_odometry"],
        # The old 10-frame sample against its official poses/00.txt, a constant-velocity placeholder over
        # lines 0–14: kept as the record of that finding, not as a measure of the registration.
        "kitti_00_sample_placeholder_poses": {"kiss": kk, "point_to_plane": p2pl,
                                              "ground_truth_check": kitti["ground_truth_check"],
                                              "point_to_point_vs_open3d": kitti["point_to_point_vs_open3d"]},
        "intel_odometry": io,
        "pairs": {"kitti_mini": mini["point_to_point_vs_open3d"], "intel": intel["pairs"], "sim": simr["pairs"]},
        "runtime_s": time.perf_counter() - t_start,
    }
    text = json.dumps(result, indent=1, default=float)
    if args.out is not None:
        from core.atomic import atomic_open

        with atomic_open(args.out) as fh:
            fh.write(text + "\n")
    print(text)
    return result


if __name__ == "__main__":
    main()
