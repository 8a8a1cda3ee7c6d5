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


def _leaf_paths(model, prefix=()):  # type: ignore[no-untyped-def]
    """Every (section, …, field) path of a configuration tree, nested models walked through."""
    from pydantic import BaseModel

    for name in type(model).model_fields:
        value = getattr(model, name)
        if isinstance(value, BaseModel):
            yield prefix + (name,)  # a section: a misspelt key inside it must fail too
            yield from _leaf_paths(value, prefix + (name,))


@pytest.mark.parametrize("section", [".".join(p) for p in _leaf_paths(SlamConfig())])
def test_a_misspelt_key_anywhere_in_the_tree_is_an_error_naming_it(section, tmp_path):
    """Every model of the tree forbids unknown keys: a typo in a nested section (``mapping.params.resolutoin``)
    is reported with its whole path, never silently replaced by the default."""
    data: dict = {}
    node = data
    for key in section.split("."):
        node = node.setdefault(key, {})
    node["no_such_setting"] = 1
    import yaml

    p = tmp_path / "typo.yaml"
    p.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match=rf"typo.yaml: {section}\.no_such_setting: unknown key"):
        SlamConfig.from_yaml(p)


def test_print_config_reads_back_and_carries_the_options(tmp_path):
    """``slam run --print-config`` prints the effective tree (defaults, --config, options) as YAML, and that
    text read back with --config prints itself again: nothing is lost or renamed on the way."""
    import subprocess
    import sys

    def show(*args: str) -> str:
        res = subprocess.run([sys.executable, "-m", "slam", "run", "--print-config", *args],
                             capture_output=True, text=True, timeout=120)
        assert res.returncode == 0, res.stderr
        return res.stdout

    first = show("--map", "logodds", "--backend", "chordal")
    (tmp_path / "c.yaml").write_text(first)
    assert show("--config", str(tmp_path / "c.yaml")) == first
    cfg = SlamConfig.from_yaml(tmp_path / "c.yaml")
    assert cfg.mapping.params.method == "logodds" and cfg.backend.kind == "chordal"
    assert cfg.model_copy(update={"mapping": SlamConfig().mapping, "backend": SlamConfig().backend}) == SlamConfig()
