"""Configuration models (pydantic) from and to YAML files: a bad file is one :class:`ConfigError` naming it."""

from __future__ import annotations

from pathlib import Path

from pydantic import BaseModel

from .errors import ConfigError

__all__ = ["load_yaml", "dump_yaml"]


def load_yaml(model: type[BaseModel], path: str | Path) -> BaseModel:
    """Load a config model from a YAML file (raises ConfigError naming the file)."""
    import yaml

    try:
        with open(path) as fh:
            data = yaml.safe_load(fh) or {}
        return model.model_validate(data)
    except (OSError, yaml.YAMLError, ValueError) as exc:
        raise ConfigError(f"{path}: {exc}") from exc


def dump_yaml(config: BaseModel, path: str | Path) -> None:
    """Write a config model as YAML, atomically."""
    import yaml

    from .atomic import atomic_open

    with atomic_open(path) as fh:
        yaml.safe_dump(config.model_dump(mode="json"), fh, sort_keys=False)
