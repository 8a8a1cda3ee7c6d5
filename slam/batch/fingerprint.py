"""What makes two runs the same, for ``slam batch --resume``: the log's content hash and the config hash.

A finished run folder holds ``batch.json`` (written into it before it is moved into place, see
:mod:`slam.cli.batch_task`) with the SHA-256 of the log's bytes, the config hash and the run's table
row. A run is skipped on resume when that file exists and both hashes equal the job's.

The config hash is the SHA-256 of the canonical JSON (sorted keys) of the effective configuration
without ``stage_processes`` (the results are the same either way), the sensor topic, the content
hashes of the reference files the run is evaluated against (a changed relations file reruns too) and
the hash of the code that computes the runs (:func:`code_sha256`): a batch resumed after an upgrade, or
after any edit of the project's packages, runs again instead of keeping rows another version made.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
from pathlib import Path
from typing import Any

__all__ = ["BATCH_FILE", "content_sha256", "code_sha256", "config_sha256", "completed_row"]

PACKAGES = ("core", "evaluation", "mapping", "registration", "slam")  # what pyproject installs

BATCH_FILE = "batch.json"
_CHUNK_BYTES = 1 << 20


def content_sha256(path: str | os.PathLike[str]) -> str:
    """SHA-256 of a file's bytes; of a folder (a KITTI sequence), of every file's relative path and bytes,
    in sorted order."""
    p = Path(path)
    h = hashlib.sha256()
    files = [p] if p.is_file() else sorted(f for f in p.rglob("*") if f.is_file())
    for f in files:
        if f is not p:
            h.update(str(f.relative_to(p)).encode() + b"\0")
        with open(f, "rb") as fh:
            while chunk := fh.read(_CHUNK_BYTES):
                h.update(chunk)
    return h.hexdigest()


@functools.lru_cache(maxsize=8)
def code_sha256(root: str | None = None) -> str:
    """SHA-256 of every ``.py`` file of the project's :data:`PACKAGES` under *root* (default: where this
    package is installed), each path relative to *root* and its bytes, in sorted order."""
    base = Path(root) if root is not None else Path(__file__).resolve().parents[2]
    h = hashlib.sha256()
    for f in sorted(f for pkg in PACKAGES for f in (base / pkg).rglob("*.py")):
        h.update(str(f.relative_to(base)).encode() + b"\0")
        h.update(f.read_bytes())
    return h.hexdigest()


def config_sha256(config: dict[str, Any], topic: str | None, reference_sha256: dict[str, str | None],
                  code: str | None = None) -> str:
    """Hash of what a run computes from its log (module docstring); *config* is ``SlamConfig.model_dump(mode="json")``,
    *code* the code's hash (default :func:`code_sha256`)."""
    cfg = {k: v for k, v in config.items() if k != "stage_processes"}
    doc = {"config": cfg, "topic": topic, "reference": reference_sha256, "code": code if code is not None else code_sha256()}
    return hashlib.sha256(json.dumps(doc, sort_keys=True, default=str).encode()).hexdigest()


def completed_row(run_dir: str | os.PathLike[str], log_sha256: str, config_sha256_: str) -> dict[str, Any] | None:
    """The table row stored in a finished run folder when it was made from the same log and config, else None."""
    f = Path(run_dir) / BATCH_FILE
    try:
        doc = json.loads(f.read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(doc, dict) or doc.get("log_sha256") != log_sha256 or doc.get("config_sha256") != config_sha256_:
        return None
    row = doc.get("row")
    if not isinstance(row, dict) or row.get("status") != "ok" or not (Path(run_dir) / "trajectory.tum").is_file():
        return None
    return row
