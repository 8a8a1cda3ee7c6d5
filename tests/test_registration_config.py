"""Registration configuration: YAML round trip, validation, mapping onto KISS-ICP's config."""

from __future__ import annotations

import pytest

from core.errors import ConfigError
from core.yaml_config import dump_yaml, load_yaml
from registration.config import IcpConfig, IcpOdometryConfig, KissOdometryConfig


@pytest.mark.parametrize("model", [IcpConfig(gates_m=(2.0, 0.5), robust="huber", sigma_m=0.02),
                                   KissOdometryConfig.planar_default(), IcpOdometryConfig()])
def test_yaml_round_trip(tmp_path, model):
    """dump_yaml then load_yaml gives back an equal model (configs are dumped next to outputs)."""
    p = tmp_path / "cfg.yaml"
    dump_yaml(model, p)
    assert load_yaml(type(model), p) == model


def test_bad_yaml_values_raise_config_error_naming_the_file(tmp_path):
    """An invalid value (negative gate, unknown key) raises ConfigError with the file name."""
    p = tmp_path / "bad.yaml"
    p.write_text("gates: [1.0, -0.5]\n")
    with pytest.raises(ConfigError, match="bad.yaml"):
        load_yaml(IcpConfig, p)
    p.write_text("gatez: [1.0]\n")
    with pytest.raises(ConfigError, match="bad.yaml"):
        load_yaml(IcpConfig, p)


def test_kiss_mapping_turns_deskew_off_for_planar_scans():
    """to_kiss maps every field; deskew is forced off for planar scans and the voxel size defaults
    to KISS-ICP's own max_range / 100."""
    c = KissOdometryConfig(max_range_m=50.0, deskew=True)
    k3, k2 = c.to_kiss(planar=False), c.to_kiss(planar=True)
    assert k3.data.deskew and not k2.data.deskew
    assert k3.mapping.voxel_size == pytest.approx(0.5)
    p = KissOdometryConfig.planar_default().to_kiss(planar=True)
    assert p.data.max_range == 20.0 and p.mapping.voxel_size == 0.1 and p.registration.max_num_threads == 1
    with pytest.raises(ValueError):
        KissOdometryConfig(min_range_m=5.0, max_range_m=1.0)
