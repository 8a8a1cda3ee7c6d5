"""The batch of ``slam batch``: the cartesian product logs × settings, from a spec file or the command line.

A spec is YAML. Relative paths are relative to the spec's folder; log paths may be globs::

    config: base.yaml            # base configuration: a YAML file, or inline values (optional)
    logs:
      - logs/floor2.clf.bz2      # a path or glob, or a mapping:
      - log: logs/campus_run3.bag
        name: campus             # the run folder's name (default: the log's stem)
        relations: logs/campus_run3.relations
        gt: null                 # or a ground-truth trajectory (default: <stem>.relations beside the log,
                                 # or the ground truth the log's frames carry)
        topic: null              # sensor topic (MCAP / ROS 1)
        config:                  # values for this log alone, applied after the setting's
          odometry.use_wheel_odometry: false
    sweep:                       # NAME=start:stop:count, the grammar of `slam loops` (slam.pipeline.loop_sweep):
      - exclude_recent_keyframes=10:20:3   # a bare name is a loops setting,
      - odometry.icp_2d.icp.tol_translation_m=4e-4:6e-4:3 # a dotted one any numeric config value
    settings:                    # explicit settings, each some config values and an optional id
      - {id: default}
      - {id: chordal, backend.kind: chordal}

The settings are the explicit ones (default: one that changes nothing) × the sweep grid; the batch is
every log × every setting, each run evaluated when it has a reference. Config values may be nested
(``keyframes: {max_range_m: 20}``) or dotted (``keyframes.max_range_m: 20``). Everything is checked before any
run: a mistake is one :class:`~core.errors.InputFileError` naming the spec and the entry
(``logs[2].config``).
"""

from __future__ import annotations

import copy
import glob
import hashlib
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from pydantic import ValidationError

from core.errors import ConfigError, InputFileError
from slam.pipeline.config import LoopConfig, SlamConfig

from .fingerprint import config_sha256, content_sha256

__all__ = ["LogEntry", "Setting", "Job", "BatchSpec", "load_spec", "spec_from_command_line"]

_GLOB_CHARS = "*?["
_CMDLINE = "command line"
_MAX_ID_CHARS = 80


@dataclass(frozen=True)
class LogEntry:
    """One log of the batch: where it is, its run-folder name, what it is evaluated against, its own config values."""

    path: Path
    name: str
    relations: Path | None = None
    gt: Path | None = None
    topic: str | None = None
    values: dict[str, Any] = field(default_factory=dict)  # dotted name → value, applied last
    found_relations: Path | None = None  # <stem>.relations beside the log, which the run's --eval finds itself


@dataclass(frozen=True)
class Setting:
    """One setting: an id (its folder name under ``runs/<log>/``) and the config values it changes."""

    id: str
    values: dict[str, Any]


@dataclass(frozen=True)
class Job:
    """One run: a log under one setting, as a Ray task receives it (paths absolute, config complete)."""

    log: str
    log_name: str
    setting: str
    values: dict[str, Any]  # what the setting changed (dotted name → value)
    config: dict[str, Any]  # the effective SlamConfig, model_dump(mode="json")
    relations: str | None
    gt: str | None
    topic: str | None
    out: str  # the run folder, <out>/runs/<log_name>/<setting>
    log_sha256: str
    config_sha256: str
    cpus_per_run: float


@dataclass
class BatchSpec:
    """Logs × settings over a base configuration; :meth:`jobs` expands them."""

    source: str  # the spec file, or "command line"
    base: dict[str, Any]  # SlamConfig.model_dump(mode="json")
    logs: list[LogEntry]
    settings: list[Setting]
    sweeps: dict[str, list[Any]]  # dotted name → values, for the report's per-setting plots

    @property
    def value_names(self) -> list[str]:
        """Every config value some setting changes, in first-seen order (the table's columns)."""
        return list(dict.fromkeys(k for s in self.settings for k in s.values))

    def jobs(self, out_dir: Path, cpus_per_run: float = 1.0) -> list[Job]:
        """One :class:`Job` per log × setting (log-major), with content and config hashes (reads every log once)."""
        out_dir = Path(out_dir).resolve()
        jobs = []
        for i, entry in enumerate(self.logs):
            log_sha = content_sha256(entry.path)
            ref = {"relations": _sha_or_none(entry.relations or entry.found_relations), "gt": _sha_or_none(entry.gt)}
            for setting in self.settings:
                data = _apply(_apply(self.base, setting.values, self.source, f"settings: {setting.id}"),
                              entry.values, self.source, f"logs[{i}].config")
                cfg = _validate(data, self.source, f"logs[{i}] ({entry.name}) × setting {setting.id}")
                dump = cfg.model_dump(mode="json")
                jobs.append(Job(
                    log=str(entry.path), log_name=entry.name, setting=setting.id, values=dict(setting.values),
                    config=dump, relations=_str_or_none(entry.relations), gt=_str_or_none(entry.gt),
                    topic=entry.topic, out=str(out_dir / "runs" / entry.name / setting.id), log_sha256=log_sha,
                    config_sha256=config_sha256(dump, entry.topic, ref), cpus_per_run=float(cpus_per_run)))
        return jobs


def _str_or_none(p: Path | None) -> str | None:
    return None if p is None else str(p)


def _sha_or_none(p: Path | None) -> str | None:
    return None if p is None else content_sha256(p)


# ----------------------------------------------------------------------------- config values


def _flatten(values: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """``{"keyframes": {"max_range_m": 20}, "loops.icp_tolerance_m": 2e-4}`` → ``{"keyframes.max_range_m": 20, "loops.icp_tolerance_m": 2e-4}``."""
    out: dict[str, Any] = {}
    for k, v in values.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict) and v:
            out |= _flatten(v, key + ".")
        else:
            out[key] = v
    return out


def _apply(data: dict[str, Any], values: dict[str, Any], source: str, where: str) -> dict[str, Any]:
    """A copy of the config dump *data* with the dotted *values* set; an unknown name is an error naming *where*."""
    out = copy.deepcopy(data)
    for key, v in values.items():
        *path, leaf = key.split(".")
        node = out
        for p in path:
            node = node.get(p) if isinstance(node, dict) else None
        if not isinstance(node, dict) or leaf not in node:
            raise InputFileError(source, where, f"{key!r} is not a configuration setting (see config.yaml of any run)")
        node[leaf] = v
    return out


def _validate(data: dict[str, Any], source: str, where: str) -> SlamConfig:
    try:
        return SlamConfig.model_validate(data)
    except ValidationError as exc:
        err = exc.errors()[0]
        loc = ".".join(str(p) for p in err["loc"])
        raise InputFileError(source, where, f"{loc}: {err['msg']}") from None


def _value_text(v: Any) -> str:
    if isinstance(v, str):
        return v.replace("/", "_")
    if isinstance(v, bool) or v is None:
        return json.dumps(v)
    if isinstance(v, (int, float)):
        return repr(v)
    return json.dumps(v, separators=(",", ":"))


def _setting_id(values: dict[str, Any]) -> str:
    """``loops.exclude_recent_keyframes=10,max_scans=300``; ``default`` for no change; long ones by hash."""
    if not values:
        return "default"
    text = ",".join(f"{k}={_value_text(v)}" for k, v in values.items())
    return text if len(text) <= _MAX_ID_CHARS else "setting-" + hashlib.sha256(text.encode()).hexdigest()[:10]


def _check_id(sid: str, source: str, where: str) -> str:
    if not sid or sid.startswith(".") or "/" in sid or os.sep in sid or any(c.isspace() for c in sid):
        raise InputFileError(source, where, f"setting id {sid!r} must be a folder name (no '/', spaces or leading '.')")
    return sid


# ----------------------------------------------------------------------------- settings


def _settings(explicit: list[Any] | None, sweeps: list[str], base: SlamConfig, source: str,
              key: str = "settings") -> tuple[list[Setting], dict[str, list[Any]]]:
    """Explicit settings × the sweep grid, each validated against *base*. On the command line a bad
    ``--sweep`` is the ConfigError of ``slam loops`` (it names the option); in a spec it names the entry."""
    from slam.pipeline.loop_sweep import numeric_fields, parse_sweep, sweep_grid

    fields = numeric_fields(SlamConfig)
    loop_fields = numeric_fields(LoopConfig)
    parsed = []
    for i, text in enumerate(sweeps):
        if not isinstance(text, str):
            raise InputFileError(source, f"sweep[{i}]", "expected NAME=start:stop:count")
        name = text.partition("=")[0].strip()
        if name in loop_fields and name not in fields:  # slam loops' bare names: the loops section
            text = "loops." + text.strip()
        try:
            parsed.append(parse_sweep(text, fields))
        except ConfigError as exc:
            if source == _CMDLINE:
                raise
            raise InputFileError(source, f"sweep[{i}]", str(exc)) from None
    try:
        grid = sweep_grid(base, parsed)
    except ConfigError as exc:
        if source == _CMDLINE:
            raise
        raise InputFileError(source, "sweep", str(exc)) from None
    heads: list[tuple[str | None, dict[str, Any]]] = []
    for i, item in enumerate(explicit if explicit is not None else [{}]):
        where = f"{key}[{i}]"
        if not isinstance(item, dict):
            raise InputFileError(source, where, "expected a mapping of config values (and an optional id)")
        item = dict(item)
        sid = item.pop("id", None)
        values = _flatten(item)
        _validate(_apply(base.model_dump(mode="json"), values, source, where), source, where)
        heads.append((None if sid is None else _check_id(str(sid), source, where), values))
    settings = []
    for sid, values in heads:
        head = sid if sid is not None else (_setting_id(values) if values else None)
        for point, _ in grid:
            parts = [p for p in (head, _setting_id(point) if point else None) if p]
            settings.append(Setting(_check_id(",".join(parts) or "default", source, key), values | point))
    seen: dict[str, int] = {}
    for s in settings:
        if s.id in seen:
            raise InputFileError(source, key, f"two settings have the id {s.id!r}: give them different ids")
        seen[s.id] = 1
    return settings, {s.name: list(s.values) for s in parsed}


# ----------------------------------------------------------------------------- logs


def _path(value: Any, root: Path, source: str, where: str) -> Path:
    if not isinstance(value, str) or not value:
        raise InputFileError(source, where, "expected a path")
    p = Path(os.path.expanduser(value))
    return p if p.is_absolute() else root / p


def _existing(value: Any, root: Path, source: str, where: str) -> Path | None:
    if value is None:
        return None
    p = _path(value, root, source, where)
    if not p.exists():
        raise InputFileError(source, where, f"no such file: {p}")
    return p.resolve()


def _logs(items: Any, root: Path, source: str, stem: Callable[[Path], str]) -> list[LogEntry]:
    if not isinstance(items, list) or not items:
        raise InputFileError(source, "logs", "expected a list of logs (paths, globs or mappings with log:)")
    out: list[LogEntry] = []
    for i, item in enumerate(items):
        where = f"LOG argument {i + 1}" if source == _CMDLINE else f"logs[{i}]"
        entry = {"log": item} if isinstance(item, str) else item
        if not isinstance(entry, dict) or "log" not in entry:
            raise InputFileError(source, where, "expected a path or a mapping with log:")
        unknown = set(entry) - {"log", "name", "relations", "gt", "topic", "config"}
        if unknown:
            raise InputFileError(source, where, f"unknown key(s) {', '.join(sorted(unknown))} "
                                                "(expected log, name, relations, gt, topic, config)")
        pattern = _path(entry["log"], root, source, where)
        if any(c in str(pattern) for c in _GLOB_CHARS):
            paths = [Path(p) for p in sorted(glob.glob(str(pattern)))]
            if not paths:
                raise InputFileError(source, where, f"no log matches {pattern}")
        else:
            if not pattern.exists():
                raise InputFileError(source, where, f"no such log: {pattern}")
            paths = [pattern]
        if entry.get("name") is not None and len(paths) > 1:
            raise InputFileError(source, where, f"name: given for a glob that matches {len(paths)} logs")
        values = entry.get("config") or {}
        if not isinstance(values, dict):
            raise InputFileError(source, f"{where}.config", "expected a mapping of config values")
        topic = entry.get("topic")
        for p in paths:
            p = p.resolve()
            name = str(entry["name"]) if entry.get("name") is not None else stem(p)
            _check_id(name, source, f"{where}.name")
            out.append(LogEntry(p, name, _existing(entry.get("relations"), root, source, f"{where}.relations"),
                                _existing(entry.get("gt"), root, source, f"{where}.gt"),
                                None if topic is None else str(topic), _flatten(values)))
    names: dict[str, Path] = {}
    for e in out:
        if e.name in names:
            raise InputFileError(source, "logs", f"two logs named {e.name!r} ({names[e.name]}, {e.path}): give one a name:")
        names[e.name] = e.path
    return out


def _beside(entries: list[LogEntry], stem: Callable[[Path], str]) -> list[LogEntry]:
    """Entries without a given reference note ``<stem>.relations`` beside the log, when it exists: the run
    finds it itself (as ``slam run --eval``), the config hash includes its content."""
    out = []
    for e in entries:
        rel = e.path.parent / f"{stem(e.path)}.relations"
        if e.relations is None and e.gt is None and rel.is_file():
            e = LogEntry(e.path, e.name, None, None, e.topic, e.values, rel.resolve())
        out.append(e)
    return out


# ----------------------------------------------------------------------------- entry points


def load_spec(path: str | os.PathLike[str], stem: Callable[[Path], str]) -> BatchSpec:
    """Read and check a spec file (module docstring). *stem* names a log's run folder (``floor2.clf.bz2`` → ``floor2``)."""
    import yaml

    spec = Path(path)
    source = str(spec)
    try:
        doc = yaml.safe_load(spec.read_text(encoding="utf-8"))
    except OSError as exc:
        raise InputFileError(source, None, f"cannot read: {exc.strerror or exc}") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        raise InputFileError(source, f"line {mark.line + 1}" if mark else None,
                             f"not YAML: {getattr(exc, 'problem', None) or exc}") from None
    if not isinstance(doc, dict):
        raise InputFileError(source, None, "expected a mapping with logs: (and config:, sweep:, settings:)")
    unknown = set(doc) - {"config", "logs", "sweep", "settings"}
    if unknown:
        raise InputFileError(source, None, f"unknown key(s) {', '.join(sorted(unknown))} (expected config, logs, sweep, settings)")
    root = spec.resolve().parent
    base = _base(doc.get("config"), root, source)
    sweeps = doc.get("sweep") or []
    if not isinstance(sweeps, list):
        raise InputFileError(source, "sweep", "expected a list of NAME=start:stop:count")
    explicit = doc.get("settings")
    if explicit is not None and not isinstance(explicit, list):
        raise InputFileError(source, "settings", "expected a list of mappings of config values")
    settings, sweep_values = _settings(explicit, sweeps, base, source)
    logs = _beside(_logs(doc.get("logs"), root, source, stem), stem)
    return BatchSpec(source, base.model_dump(mode="json"), logs, settings, sweep_values)


def _base(value: Any, root: Path, source: str) -> SlamConfig:
    if value is None:
        return SlamConfig()
    if isinstance(value, str):
        p = _existing(value, root, source, "config")
        return SlamConfig.from_yaml(p)
    if isinstance(value, dict):
        return _validate(_apply(SlamConfig().model_dump(mode="json"), _flatten(value), source, "config"), source, "config")
    raise InputFileError(source, "config", "expected a config file or a mapping of config values")


def spec_from_command_line(logs: list[str], sweeps: list[str], config: Path | None,
                           stem: Callable[[Path], str]) -> BatchSpec:
    """The short form ``slam batch LOG... [--sweep ...] [--config ...]``: paths or globs, relative to the current folder."""
    source = _CMDLINE
    base = SlamConfig.from_yaml(config) if config is not None else SlamConfig()
    settings, sweep_values = _settings(None, sweeps, base, source)
    entries = _beside(_logs(list(logs), Path.cwd(), source, stem), stem)
    return BatchSpec(source, base.model_dump(mode="json"), entries, settings, sweep_values)
