"""Scan-pose interpolation: keyframes keep their optimised poses; a rigid correction is reproduced exactly."""

import numpy as np

from core import geometry as G
from slam.pipeline.trajectory import interpolate_scan_poses


def _odometry(n):
    return G.xytheta_to_matrix(np.c_[np.linspace(0, 5, n), np.sin(np.linspace(0, 3, n)), np.linspace(0, 1, n)])


def test_rigid_correction_is_applied_to_every_scan():
    """If the optimiser moved every keyframe by the same world transform W, every scan moves by W."""
    n = 50
    stamps = np.arange(n) * 0.1
    O = _odometry(n)
    kf_idx = np.arange(0, n, 7)
    scan_kf = np.searchsorted(kf_idx, np.arange(n), side="right") - 1
    W = G.xytheta_to_matrix(2.0, -1.0, 0.4)
    out = interpolate_scan_poses(stamps, O, scan_kf, stamps[kf_idx], O[kf_idx], W @ O[kf_idx], planar=True)
    np.testing.assert_allclose(out, W @ O, atol=1e-12)


def test_keyframes_keep_their_optimised_pose_and_corrections_blend():
    """Keyframe scans get exactly X_k; a scan halfway between gets the halfway correction."""
    n = 11
    stamps = np.arange(n) * 1.0
    O = G.xytheta_to_matrix(np.c_[np.arange(n) * 1.0, np.zeros(n), np.zeros(n)])
    kf_idx = np.array([0, 10])
    X = O[kf_idx].copy()
    X[1] = G.xytheta_to_matrix(10.0, 1.0, 0.0)  # the end moved 1 m sideways
    scan_kf = np.where(np.arange(n) < 10, 0, 1)
    out = interpolate_scan_poses(stamps, O, scan_kf, stamps[kf_idx], O[kf_idx], X, planar=True)
    np.testing.assert_allclose(out[kf_idx], X, atol=1e-12)
    np.testing.assert_allclose(out[5, :2, 3], [5.0, 0.5], atol=1e-12)
    # 3D path gives the same result for a planar problem
    out3 = interpolate_scan_poses(stamps, O, scan_kf, stamps[kf_idx], O[kf_idx], X, planar=False)
    np.testing.assert_allclose(out3, out, atol=1e-12)


def test_cap_range_turns_far_beams_into_free_space():
    """Beams beyond the cap become no-return beams of the cap's length; nearer hits are unchanged."""
    from core.frame import Frame
    from slam.pipeline.mapping_stage import cap_range

    ang = np.linspace(-1.0, 1.0, 5)
    r = np.array([1.0, 20.0, np.inf, 5.0, 11.9])
    fin = np.isfinite(r)
    f = Frame(0.0, np.c_[r[fin] * np.cos(ang[fin]), r[fin] * np.sin(ang[fin])], angles=ang, ranges=r, max_range=80.0)
    g = cap_range(f, 12.0)
    np.testing.assert_array_equal(g.no_return, [False, True, True, False, False])
    assert g.max_range == 12.0 and len(g.points) == 3
    np.testing.assert_allclose(np.hypot(*g.free_endpoints().T), [1.0, 12.0, 12.0, 5.0, 11.9])
