"""Polar (Scan Context) descriptor, 2D occupancy and 3D heights: rotation invariance of the ring key,
heading recovery, retrieval."""

from __future__ import annotations

import numpy as np
import pytest

from core import geometry as G
from slam.loops.descriptor import (
    SCAN_CONTEXT_3D,
    DescriptorIndex,
    PolarDescriptorConfig,
    best_shift,
    polar_descriptor,
    ring_key,
    shift_distances,
)
from tests.conftest import shared_path


def room_scan(rng, n=720, noise=0.0):
    """Hit points of a 360° laser inside an asymmetric polygonal room, sensor frame = world."""
    ang = np.linspace(-np.pi, np.pi, n, endpoint=False)
    # Room: box [-3, 5] x [-2, 4] plus a pillar; cast analytically against the box walls.
    d = np.stack([np.cos(ang), np.sin(ang)], 1)
    with np.errstate(divide="ignore"):
        tx = np.where(d[:, 0] > 0, 5.0 / d[:, 0], -3.0 / d[:, 0])
        ty = np.where(d[:, 1] > 0, 4.0 / d[:, 1], -2.0 / d[:, 1])
    r = np.minimum(np.abs(tx), np.abs(ty))
    r = r + noise * rng.normal(size=n)
    return np.c_[r * np.cos(ang), r * np.sin(ang)]


def test_ring_key_is_rotation_invariant(rng):
    """Rotating the sensor about its origin leaves the ring key unchanged (up to binning noise)."""
    p = room_scan(rng)
    cfg = PolarDescriptorConfig()
    k0 = ring_key(polar_descriptor(p, cfg))
    for yaw in (0.3, 1.7, -2.5):
        k1 = ring_key(polar_descriptor(G.transform_points(G.xytheta_to_matrix(0, 0, yaw), p), cfg))
        # Only points lying exactly on a ring boundary may change ring under rounding: ≤ 1 point.
        np.testing.assert_allclose(k1, k0, atol=1.01 / len(p))
    np.testing.assert_allclose(k0.sum(), 1.0)


def test_best_shift_recovers_heading(rng):
    """For a scan seen from a frame rotated by φ, best_shift returns yaw with candidate_T_query = Rot(yaw)."""
    cfg = PolarDescriptorConfig(n_sectors=120)
    q_pts = room_scan(rng, noise=0.01)
    q = polar_descriptor(q_pts, cfg)
    step = 2 * np.pi / cfg.n_sectors
    for phi in (0.0, 0.5, -1.2, 3.0):
        # Candidate frame C with query_T_C = Rot(phi): p_C = Rot(-phi) p_Q.
        c_pts = G.transform_points(G.xytheta_to_matrix(0, 0, -phi), room_scan(rng, noise=0.01))
        dist, yaw = best_shift(q, polar_descriptor(c_pts, cfg))
        assert abs(G.wrap_angle(yaw[0] - (-phi))) <= step
        assert dist[0] < 0.2


def test_index_ranks_true_place_first(rng):
    """Among scans of other places, the same place (rotated) is retrieved first."""
    idx = DescriptorIndex()
    for k in range(30):
        shift = G.xytheta_to_matrix(rng.uniform(-2, 2), rng.uniform(-1, 1), 0.0)
        pts = G.transform_points(G.inverse(shift), room_scan(rng, noise=0.02))
        idx.add(k, pts if k != 17 else room_scan(rng, noise=0.02))
    query = polar_descriptor(G.transform_points(G.xytheta_to_matrix(0, 0, 0.9), room_scan(rng, noise=0.02)))
    hits = idx.query(query, k=5)
    assert hits[0][0] == 17
    assert idx.query(query, k=5, exclude_after=17)[0][0] != 17


def test_partial_overlap_cannot_score_better_than_its_share_of_columns():
    """A 180° scan fills half the sectors; at a shift where two such scans share k columns of the u either
    fills, the distance is at least 1 − k/u (cosine ≤ 1 per shared column, 0 for the others), so a
    shift that overlaps one column cannot look like a perfect match."""
    rng = np.random.default_rng(3)
    n_rings, n_sectors = 20, 60
    for _ in range(20):
        q = np.zeros((n_rings, n_sectors))
        c = np.zeros((n_rings, n_sectors))
        q[:, :30] = rng.random((n_rings, 30))
        c[:, (rng.integers(0, 60) + np.arange(30)) % 60] = rng.random((n_rings, 30))
        D = shift_distances(q, c)[0]
        for s in range(n_sectors):
            cs = np.roll(c, s, axis=1)  # the candidate's columns that meet the query's at shift s
            qn, cn = np.linalg.norm(q, axis=0) > 0, np.linalg.norm(cs, axis=0) > 0
            both, union = (qn & cn).sum(), (qn | cn).sum()
            assert D[s] >= 1.0 - both / union - 1e-9


# ------------------------------------------------------------------------------ 3D (heights, real LiDAR)


def _kitti(seq: str):
    from slam.logs import open_log

    return list(open_log(shared_path("kitti_mini", "sequences", seq)).frames())


def test_3d_bins_hold_the_highest_point_above_the_ground_level():
    """Scan Context eq. 1: a bin's value is the maximum height of its points, here above the scan's ground
    level (its low height percentile); bins of ground alone and empty bins hold 0."""
    rng = np.random.default_rng(1)
    ground = np.c_[rng.uniform(-40, 40, (20000, 2)), np.full(20000, -1.73)]
    pole = np.c_[np.full(50, 10.0), np.zeros(50), np.linspace(-1.73, 1.0, 50)]  # 2.73 m tall, at 10 m ahead
    desc = polar_descriptor(np.vstack([ground, pole]), SCAN_CONTEXT_3D)
    ring = int(10.0 / SCAN_CONTEXT_3D.max_range * SCAN_CONTEXT_3D.n_rings)
    assert desc[ring, 0] == pytest.approx(2.73)
    assert np.count_nonzero(desc) == 1


def test_3d_scan_context_of_a_real_scan_recovers_the_heading_and_keeps_its_ring_key():
    """A real Velodyne scan (KITTI 01) seen from a frame turned by φ about z: the best shift gives
    candidate_T_query = Rot(yaw) with yaw = −φ to within one sector, at a small distance; the ring key
    (occupied share of each ring) changes only by the sectors whose points cross a sector border."""
    cfg = SCAN_CONTEXT_3D
    pts = _kitti("01")[5].points
    q = polar_descriptor(pts, cfg)
    sector = 2 * np.pi / cfg.n_sectors
    for phi in (0.3, 1.7, -2.5):
        c = polar_descriptor(G.transform_points(G.xytheta_to_matrix(0, 0, -phi), pts), cfg)
        dist, yaw = best_shift(q, c)
        assert abs(G.wrap_angle(yaw[0] + phi)) <= sector
        assert dist[0] < 0.1
        assert np.abs(ring_key(c, cfg) - ring_key(q, cfg)).max() <= 6 / cfg.n_sectors


def test_3d_index_finds_the_place_among_other_streets():
    """All 40 kitti_mini scans (four streets) indexed whole, as the loop closer describes 3D keyframes: a
    scan of one street seen turned by 1 rad (and thinned to 0.5 m voxels, so not the same points) retrieves
    scans of its own street first, with the heading; and every other street is beyond the descriptor
    threshold."""
    from registration.voxel import voxel_downsample
    from slam.loops.config import LoopConfig

    idx = DescriptorIndex(SCAN_CONTEXT_3D)
    street = []
    scans = {s: _kitti(s) for s in ("00", "01", "07", "10")}
    for s, frames in scans.items():
        for f in frames:
            idx.add(len(street), f.points)
            street.append(s)
    sector = 2 * np.pi / SCAN_CONTEXT_3D.n_sectors
    threshold = LoopConfig().descriptor_max_distance
    for s in ("00", "01", "10"):
        q = voxel_downsample(G.transform_points(G.xytheta_to_matrix(0, 0, 1.0), scans[s][5].points), 0.5)
        hits = idx.query(polar_descriptor(q, SCAN_CONTEXT_3D), k=3)
        assert all(d > threshold for i, d, _ in idx.query(polar_descriptor(q, SCAN_CONTEXT_3D), k=40)
                   if street[i] != s)
        assert all(street[i] == s for i, _, _ in hits)
        assert abs(G.wrap_angle(hits[0][2] + 1.0)) <= 1.5 * sector
