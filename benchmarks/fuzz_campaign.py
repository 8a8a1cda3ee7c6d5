"""Fuzz campaign over every file reader (issue 27): damaged files through the command line. Prints ONE JSON object.

For each format (CARMEN, g2o, TORO, TUM, KITTI, relations, MCAP, ROS 1 bag) it damages the seed file of
``tests/fuzzing.py`` ``--per-format`` times — bytes flipped, zeroed or inserted, or the file cut, at a random
place (seeded, so a campaign can be repeated exactly) — runs the command that reads it (``slam info``,
``slam solve``, ``slam eval ape`` / ``relations``) in this process, and counts the outcomes. Allowed are
``ok`` (exit 0 with counts that agree with the damaged file) and ``error`` (one ``error:`` line, exit 2);
``traceback``, ``bad`` (another exit or more lines), ``hang`` (no answer in ``--timeout`` s) and
``mismatch`` (a silently different graph size or scan count) are findings, listed with the mutation that
produced them. This is the campaign behind the issue's acceptance (≥ 1,000 mutations per format, 0 tracebacks,
0 hangs); the suite runs a few dozen per format (tests/test_fuzz_readers.py).

Usage: ``nice -n 10 .venv/bin/python benchmarks/fuzz_campaign.py [--per-format 1000] [--seed 27] [--formats carmen,g2o]``
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # the project's packages and tests/fuzzing.py


def campaign(per_format: int, seed: int, formats: list[str], timeout_s: int) -> dict:
    from tests.fuzzing import ALLOWED, MUTATIONS, mutate, run_case, seeds

    rng = np.random.default_rng(seed)
    result: dict = {"per_format": per_format, "seed": seed, "timeout_s": timeout_s, "formats": {}}
    with tempfile.TemporaryDirectory() as d:
        work = Path(d)
        all_seeds = seeds(work)
        for fmt in formats:
            variants = all_seeds[fmt]  # MCAP and bags: one seed per chunk compression, taken in turn
            counts: Counter = Counter()
            findings = []
            t0 = time.perf_counter()
            for case in range(per_format):
                kind = MUTATIONS[int(rng.integers(len(MUTATIONS)))]
                where = float(rng.random())
                payload = rng.integers(0, 256, int(rng.integers(1, 9)), dtype=np.uint8).tobytes()
                s = variants[case % len(variants)]
                outcome = run_case(s, mutate(s.data, kind, where, payload), work, timeout_s)
                counts[outcome.kind] += 1
                if outcome.kind not in ALLOWED:
                    findings.append({"case": case, "mutation": kind, "where": where, "payload": payload.hex(),
                                     "outcome": outcome.kind, "detail": outcome.detail[-2000:]})
            result["formats"][fmt] = {"cases": per_format, **{k: counts.get(k, 0) for k in
                                      ("ok", "error", "traceback", "bad", "hang", "mismatch")},
                                      "seconds": round(time.perf_counter() - t0, 1), "findings": findings[:20]}
    fm = result["formats"].values()
    result["summary"] = {"cases": sum(f["cases"] for f in fm), "findings": sum(len(f["findings"]) for f in fm),
                         **{k: sum(f[k] for f in fm) for k in ("ok", "error", "traceback", "bad", "hang", "mismatch")}}
    return result


def main() -> None:
    from tests.fuzzing import FORMATS

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--per-format", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=27)
    ap.add_argument("--formats", default=",".join(FORMATS))
    ap.add_argument("--timeout", type=int, default=30, help="seconds before a case counts as a hang")
    a = ap.parse_args()
    print(json.dumps(campaign(a.per_format, a.seed, a.formats.split(","), a.timeout), indent=1))


if __name__ == "__main__":
    main()
