"""The surroundings descriptor that orders the global search (slam.loops.surroundings): what the robot saw
over the last stretch of path, in the new keyframe's frame."""

from __future__ import annotations

import numpy as np
import pytest

from core import geometry as G
from slam.loops.descriptor import PolarDescriptorConfig, polar_descriptor, shift_distances
from slam.loops.surroundings import Surroundings
from tests.loop_scenes import keyframes, room


def _path(poses: np.ndarray) -> np.ndarray:
    steps = np.linalg.norm(np.diff(poses[:, :2, 3], axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(steps)])


def _all(kfs, poses) -> np.ndarray:
    """Every keyframe's descriptor, each from the keyframes up to it only."""
    s, path = Surroundings(), _path(poses)
    return np.array([s.descriptor(k, kfs[: k + 1], poses[: k + 1], path[: k + 1]) for k in range(len(kfs))])


def _there_and_back():
    """Through the room left to right along y = 4 (a 180° laser looking ahead), then back right to left."""
    out = [(x, 4.0, 0.0) for x in np.arange(1.0, 11.01, 0.5)]
    back = [(x, 4.0, np.pi) for x in np.arange(11.0, 0.99, -0.5)]
    return out + back


def test_a_descriptor_is_the_polar_histogram_of_the_scans_over_the_last_range_of_path():
    xyt = _there_and_back()
    kfs = keyframes(room(), xyt)
    poses = np.array([G.xytheta_to_matrix(*p) for p in xyt])
    cfg = PolarDescriptorConfig()
    path = _path(poses)
    j = 36
    inside = [i for i in range(j + 1) if path[j] - path[i] <= cfg.max_range]
    assert inside[0] > 0  # the stretch is shorter than the whole path so far
    sensor_j = G.inverse(poses[j])
    pts = np.vstack([G.transform_points(sensor_j @ poses[i], kfs[i].points[:, :2]) for i in inside])
    assert np.allclose(Surroundings().descriptor(j, kfs, poses, path), polar_descriptor(pts, cfg))
    assert np.allclose(_all(kfs, poses)[j], polar_descriptor(pts, cfg))  # the keyframes after j do not enter


def test_descriptors_do_not_depend_on_the_world_frame():
    xyt = _there_and_back()
    kfs = keyframes(room(), xyt)
    poses = np.array([G.xytheta_to_matrix(*p) for p in xyt])
    moved = np.einsum("ij,njk->nik", G.xytheta_to_matrix(-40.0, 17.0, 2.1), poses)
    a, b = _all(kfs, poses), _all(kfs, moved)
    # Equal but for the points that lie on a sector's edge (beams 1° apart, sectors 6°) and fall on
    # either side of it by rounding: each moves 2/N of the mass of a descriptor that sums to 1.
    moved_mass = np.abs(a - b).sum(axis=(1, 2))
    assert moved_mass.max() < 0.05 and np.median(moved_mass) < 0.01


def test_coming_back_the_other_way_the_place_passed_is_the_most_alike():
    """On the way back (the laser looks the other way) the place of the first pass the robot is in is
    nearer in surroundings than the first pass's places 3 m or more away."""
    xyt = _there_and_back()
    kfs = keyframes(room(), xyt)
    poses = np.array([G.xytheta_to_matrix(*p) for p in xyt])
    s, path = Surroundings(), _path(poses)
    first = len(xyt) // 2  # keyframes 0 … first−1 go out (x = 1 + 0.5 k)
    for j in (first + 6, first + 10, first + 14):  # x = 8, 6, 4 on the way back
        x = xyt[j][0]
        places = np.arange(0, first, 2)
        d = s.place_distances(j, places, 1, first, kfs, poses, path)
        truth = np.argmin(np.abs(1.0 + 0.5 * places - x))
        far = np.abs(1.0 + 0.5 * places - x) >= 3.0
        assert d[truth] < d[far].min()


def test_a_place_is_as_alike_as_its_most_alike_keyframe_before_the_last():
    xyt = _there_and_back()
    kfs = keyframes(room(), xyt)
    poses = np.array([G.xytheta_to_matrix(*p) for p in xyt])
    s, path = Surroundings(), _path(poses)
    j, half, last = 35, 2, 12
    places = np.array([3, 11, 20])
    d = s.place_distances(j, places, half, last, kfs, poses, path)
    each = shift_distances(s.descriptor(j, kfs, poses, path),
                           np.array([s.descriptor(k, kfs, poses, path) for k in range(last)])).min(axis=1)
    assert d[0] == pytest.approx(each[1:6].min())
    assert d[1] == pytest.approx(each[9:12].min())  # keyframes from `last` on are left out
    assert d[2] == np.inf  # nothing of place 20 is older than `last`
