"""SlamConfig: YAML round trip, unknown keys rejected with the file named, odometry source selection."""

from __future__ import annotations

import pytest

from core.errors import ConfigError
from registration.odometry import IcpOdometry
from registration.odometry_kiss import KissOdometry
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


def test_auto_odometry_is_our_icp_and_kiss_is_honoured():
    """method auto: our scan-to-map ICP for 2D lasers and 3D clouds, each with its own settings; kiss gives
    KISS-ICP for either."""
    cfg = SlamConfig()
    planar, spatial = make_odometry(cfg, planar=True), make_odometry(cfg, planar=False)
    assert isinstance(planar, IcpOdometry) and isinstance(spatial, IcpOdometry)
    assert planar.config == cfg.odometry.icp_2d and spatial.config == cfg.odometry.icp_3d
    kiss = SlamConfig.model_validate({"odometry": {"method": "kiss"}})
    assert isinstance(make_odometry(kiss, planar=True), KissOdometry)
    assert isinstance(make_odometry(kiss, planar=False), KissOdometry)


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


@pytest.mark.parametrize("section", ["icp_2d", "icp_3d", "kiss_2d", "kiss_3d"])
def test_a_partial_registration_section_changes_only_what_it_names(section):
    """The registration settings nested under ``odometry`` default to the pipeline's values, which differ
    from the registration models' own: a section that names one field keeps every other pipeline default
    (``icp_2d: {icp: {gates_m: [0.5]}}`` must not reset the planar map voxel or the correlative window)."""
    default = getattr(SlamConfig().odometry, section)
    nested = "icp" in type(default).model_fields
    given = {"icp": {"max_iterations": 7}} if nested else {"max_num_iterations": 7}
    got = getattr(SlamConfig.model_validate({"odometry": {section: given}}).odometry, section)
    changed = {k for k in type(default).model_fields if getattr(got, k) != getattr(default, k)}
    assert changed == ({"icp"} if nested else {"max_num_iterations"})
    if nested:
        assert got.icp.max_iterations == 7
        assert got.icp.model_copy(update={"max_iterations": default.icp.max_iterations}) == default.icp
    assert default != type(default)()  # the pipeline's defaults are not the model's own: the case that matters


# Float settings that are ratios, probabilities, counts of σ or model constants: no unit to name.
DIMENSIONLESS = {
    "trim_fraction", "chi2_factor", "false_rejection_rate", "alternative_start_min_gain", "unguided_escalation",
    "convergence_criterion", "edge_ambiguity_ratio", "wheel_gate_probability", "window_sigmas",
    "descriptor_max_distance", "min_relative_score", "min_relative_fitness", "max_relative_rmse",
    "max_free_space_violation", "unguided_max_contradiction", "consistency_probability", "ambiguity_ratio", "relocalise_sigmas", "robust_scale",
    "isam2_relinearize_threshold", "lone_odometry_kernel_sigmas", "squash_alpha", "squash_beta",
    "occupied_thresh", "free_thresh", "nu", "sigma_f", "sigma_n", "stop_before_hit", "region_a_mean",
    "region_a_variance", "l_occ", "l_free", "l_min", "l_max",
}
UNIT_SUFFIXES = ("_m", "_rad", "_s", "_deg", "_m_per_rad", "_per_m", "_per_rad")


def test_every_physical_setting_names_its_unit():
    """Every float (or tuple of floats) in the tree ends in its unit, unless it is a known dimensionless
    quantity; a new physical setting without a suffix fails here."""
    from pydantic import BaseModel

    def floats(model, prefix=""):  # type: ignore[no-untyped-def]
        for name, field in type(model).model_fields.items():
            value = getattr(model, name)
            if isinstance(value, BaseModel):
                yield from floats(value, f"{prefix}{name}.")
            elif "float" in str(field.annotation):
                yield prefix + name, name

    found = list(floats(SlamConfig()))
    assert len(found) > 80
    bare = [path for path, name in found if not name.endswith(UNIT_SUFFIXES) and name not in DIMENSIONLESS]
    assert bare == []
    assert not DIMENSIONLESS - {name for _, name in found}  # the list names no setting that no longer exists
