"""What the ``slam eval`` commands share: how numbers are printed, and the ``--json`` option's checks and writing."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import typer

__all__ = ["fmt_num", "echo_pairs", "check_json", "save_json", "JSON_OPTION"]

JSON_OPTION = typer.Option(None, "--json", help="Also write the full result as JSON to this path.")


def fmt_num(v: Any) -> str:
    """How numbers are printed: 10 significant digits (ints as ints)."""
    if isinstance(v, (bool, str)) or v is None:
        return str(v)
    if isinstance(v, int):
        return str(v)
    return f"{float(v):.10g}"


def echo_pairs(pairs: dict[str, Any]) -> None:
    for k, v in pairs.items():
        typer.echo(f"{k}: {fmt_num(v)}")


def check_json(path: Path | None) -> None:
    """Before any work: the --json path can be written."""
    if path is not None:
        from core.atomic import check_output_file

        check_output_file(path)


def save_json(path: Path | None, obj: Any) -> None:
    if path is None:
        return
    from core.atomic import atomic_open

    with atomic_open(path, "w", encoding="utf-8") as fh:
        json.dump(obj, fh, indent=2, default=float)
        fh.write("\n")
