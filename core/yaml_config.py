"""Configuration models (pydantic) from and to YAML files: a bad file is one :class:`ConfigError` naming it."""

from __future__ import annotations

from pathlib import Path

from pydantic import BaseModel

from .errors import ConfigError

__all__ = ["load_yaml", "dump_yaml", "describe_validation_error"]


def load_yaml(model: type[BaseModel], path: str | Path) -> BaseModel:
    """Load a config model from a YAML file (raises ConfigError naming the file)."""
    import yaml

    from pydantic import ValidationError

    try:
        with open(path) as fh:
            data = yaml.safe_load(fh) or {}
        return model.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(f"{path}: {describe_validation_error(exc)}") from None
    except (OSError, yaml.YAMLError, ValueError) as exc:
        raise ConfigError(f"{path}: {exc}") from exc


def describe_validation_error(exc) -> str:  # type: ignore[no-untyped-def]
    """One line per pydantic ValidationError: ``a.b.c: what is wrong`` for each failing setting, joined by ``; ``
    (a key the model does not have reads "unknown key")."""
    parts = []
    for e in exc.errors():
        where = ".".join(map(str, e["loc"])) or "(top level)"
        parts.append(f"{where}: {'unknown key' if e['type'] == 'extra_forbidden' else e['msg']}")
    return "; ".join(parts)


def dump_yaml(config: BaseModel, path: str | Path) -> None:
    """Write a config model as YAML, atomically."""
    import yaml

    from .atomic import atomic_open

    with atomic_open(path) as fh:
        yaml.safe_dump(config.model_dump(mode="json"), fh, sort_keys=False)
