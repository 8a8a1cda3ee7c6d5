"""Fuzzing every reader through the command line (hypothesis, a bounded number of damaged files per format so
the suite stays fast; the campaign of thousands is benchmarks/fuzz_campaign.py): a damaged CARMEN log, g2o or
TORO graph, TUM or KITTI trajectory, relations file, MCAP or ROS 1 bag gives either a success whose counts
agree with the damaged file, or one error line with exit 2 — never a traceback, a hang or a silently
different size."""

from __future__ import annotations

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.fuzzing import ALLOWED, FORMATS, MUTATIONS, mutate, run_case, seeds


@pytest.fixture(scope="module")
def seed_files(tmp_path_factory):
    d = tmp_path_factory.mktemp("seeds")
    return d, seeds(d)


@pytest.mark.parametrize("fmt", FORMATS)
def test_the_seeds_are_read(fmt, seed_files):
    """Each undamaged seed is read with exit 0 and the counts its oracle expects (or the fuzzing proves nothing)."""
    d, s = seed_files
    for seed in s[fmt]:
        assert run_case(seed, seed.data, d).kind == "ok"


@pytest.mark.parametrize("fmt", FORMATS)
@settings(max_examples=25, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(variant=st.integers(0, 2), kind=st.sampled_from(MUTATIONS), where=st.floats(0.0, 1.0),
       payload=st.binary(min_size=1, max_size=8))
def test_a_damaged_file_is_read_or_refused_in_one_line(fmt, seed_files, variant, kind, where, payload):
    d, s = seed_files
    seed = s[fmt][variant % len(s[fmt])]
    outcome = run_case(seed, mutate(seed.data, kind, where, payload), d)
    assert outcome.kind in ALLOWED, (kind, where, payload, outcome.detail)


def test_a_quaternion_of_overflowing_size_is_refused_without_a_numpy_warning():
    """Found by the campaign (a flipped byte in an uncompressed bag's /odom): a quaternion component of 5.6e211
    made numpy print 'overflow encountered in dot' beside the error line; such a pose is now refused quietly."""
    import warnings
    from types import SimpleNamespace as NS

    from slam.logs.ros_msgs import pose_msg_vec

    pose = NS(position=NS(x=1.8, y=-0.6, z=0.0), orientation=NS(x=0.0, y=0.0, z=0.149, w=5.6e211))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(ValueError, match="invalid pose"):
            pose_msg_vec(pose)


def test_a_damaged_message_definition_is_an_error_naming_the_message(seed_files):
    """Found by the campaign (seed 2027, case 399): one flipped byte in the bag's Odometry definition renamed
    'orientation', the decoded /odom messages lacked it and an AttributeError escaped; now it is one line naming
    the message."""
    d, s = seed_files
    seed = s["bag"][0]
    damaged = mutate(seed.data, "flip", 0.8915335121937934, bytes.fromhex("36"))
    assert b"orientation" in seed.data and damaged.count(b"orientation") < seed.data.count(b"orientation")
    outcome = run_case(seed, damaged, d)
    assert outcome.kind == "error" and "/odom message 0" in outcome.detail, outcome.detail
