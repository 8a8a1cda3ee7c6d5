"""Keyframe thresholds: a keyframe exactly when distance, angle or time crosses its threshold."""

import numpy as np

from core import geometry as G
from slam.keyframes import KeyframeConfig, KeyframeSelector


def test_keyframes_on_straight_line_are_evenly_spaced():
    """Driving straight at 0.01 m per scan gives a keyframe every distance_m (±1 scan)."""
    sel = KeyframeSelector(KeyframeConfig(distance_m=0.5, angle_rad=1.0, time_s=1e9))
    kf = [i for i in range(1000) if sel.is_keyframe(i * 0.1, G.xytheta_to_matrix(i * 0.01, 0.0, 0.0))]
    gaps = np.diff(kf)
    assert kf[0] == 0 and np.all(np.abs(gaps - 50) <= 1)


def test_rotation_and_time_thresholds():
    """Turning in place triggers on angle; standing still triggers on time only."""
    sel = KeyframeSelector(KeyframeConfig(distance_m=1.0, angle_rad=0.28, time_s=5.0))
    turns = [i for i in range(100) if sel.is_keyframe(i * 0.01, G.xytheta_to_matrix(0, 0, i * 0.05))]
    assert np.all(np.diff(turns) == 6)
    sel = KeyframeSelector(KeyframeConfig(distance_m=1.0, angle_rad=0.3, time_s=5.0))
    still = [i for i in range(100) if sel.is_keyframe(i * 1.0, np.eye(4))]
    assert np.all(np.diff(still) == 5)
