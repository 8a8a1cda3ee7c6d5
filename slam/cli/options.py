"""Checks of option values, run by click while it parses the command line.

A bad value is then a usage error naming the option (printed in one line by :func:`slam.cli.main`),
before any work, instead of a pydantic ValidationError or a numpy ValueError halfway through a run.
Integer bounds use typer's ``min=``; floats use :func:`real` (click's FloatRange lets ``nan`` through).
"""

from __future__ import annotations

import math
from enum import Enum
from typing import Callable

__all__ = ["real", "alphas", "scan_count", "AUTO", "Backend"]

AUTO = 0  # scan_count's value for "auto"


class Backend(str, Enum):
    """The pose-graph back ends (slam run --backend, slam solve --backend)."""

    gtsam = "gtsam"
    chordal = "chordal"


def real(low: float | None = None, *, above: bool = False) -> Callable[[str], float]:
    """A typer ``parser=`` for a finite float option, ``>= low`` (``> low`` with *above*)."""

    def parse(text: str | float) -> float:
        try:
            v = float(text)
        except ValueError:
            raise ValueError(f"{text!r} is not a number") from None
        if not math.isfinite(v):
            raise ValueError(f"{text!r} is not a finite number")
        if low is not None and (v <= low if above else v < low):
            raise ValueError(f"{v:g} is not {'>' if above else '>='} {low:g}")
        return v

    parse.__name__ = "float"  # click shows it as the FLOAT metavar
    return parse


def scan_count(text: str | int) -> int:
    """``auto`` (→ :data:`AUTO`) or an integer ≥ 1."""
    if str(text).strip().lower() == "auto":
        return AUTO
    try:
        v = int(str(text))
    except ValueError:
        raise ValueError(f"{text!r} is neither 'auto' nor a whole number") from None
    if v < 1:
        raise ValueError(f"{v} is not >= 1")
    return v


scan_count.__name__ = "INTEGER|auto"


def alphas(text: str) -> tuple[float, ...]:
    """Four finite, non-negative comma-separated numbers (odometry noise α1..α4)."""
    parts = text.split(",")
    if len(parts) != 4:
        raise ValueError(f"{text!r} is not four comma-separated numbers")
    return tuple(real(0.0)(p) for p in parts)
