"""SlamConfig: YAML round trip, unknown keys rejected with the file named, odometry source selection."""

from __future__ import annotations

import pytest

from core.errors import ConfigError
from registration.odometry import IcpOdometry, KissOdometry
from slam.pipeline.config import SlamConfig
from slam.pipeline.odometry_source import make_odometry


def test_yaml_round_trip(tmp_path):
    """to_yaml → from_yaml gives back an equal configuration (what config.yaml beside every run relies on)."""
    cfg = SlamConfig.model_validate({"loops": {"near_candidates": 7}, "mapping": {"max_range_m": 9.5}})
    p = tmp_path / "c.yaml"
    p.write_text(cfg.to_yaml())
    assert SlamConfig.from_yaml(p) == cfg


def test_unknown_key_names_the_file(tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text("loops:\n  no_such_option: 1\n")
    with pytest.raises(ConfigError, match="bad.yaml"):
        SlamConfig.from_yaml(p)


def test_auto_odometry_is_icp_for_planar_and_kiss_for_3d():
    """method auto: our scan-to-map ICP for 2D lasers, KISS-ICP for 3D clouds; explicit choices are honoured."""
    cfg = SlamConfig()
    assert isinstance(make_odometry(cfg, planar=True), IcpOdometry)
    assert isinstance(make_odometry(cfg, planar=False), KissOdometry)
    kiss = SlamConfig.model_validate({"odometry": {"method": "kiss"}})
    assert isinstance(make_odometry(kiss, planar=True), KissOdometry)
