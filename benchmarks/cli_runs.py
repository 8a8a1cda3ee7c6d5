"""What the benchmarks on simulated logs share: the CLI run one command at a time, and one JSON out."""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from slam.cli.eval_io import check_json, save_json  # noqa: E402


def slam(*args: str) -> None:
    """Run ``python -m slam ARGS`` in the repository; a failure stops the benchmark with its own message."""
    done = subprocess.run([sys.executable, "-m", "slam", *args], cwd=REPO, capture_output=True, text=True)
    if done.returncode != 0:
        last = (done.stderr.strip().splitlines() or ["no message"])[-1]
        sys.exit(f"slam {' '.join(args)} failed ({done.returncode}): {last}")


def run_and_report(folder: Path | None, out: Path | None, collect: Callable[[Path], list[dict]],
                   summarise: Callable[[list[dict]], dict], rows_key: str) -> dict:
    """``collect(folder)`` (a temporary folder when None) into ``{"summary", rows_key, "runtime_s"}``,
    written to *out* (checked before the work) and printed."""
    check_json(out)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        where = folder or Path(tmp)
        where.mkdir(parents=True, exist_ok=True)
        rows = collect(where)
    result = {"summary": summarise(rows), rows_key: rows, "runtime_s": time.perf_counter() - t0}
    save_json(out, result)
    print(json.dumps(result, indent=1))
    return result
