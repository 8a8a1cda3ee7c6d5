"""The chain model each run calibrates from its own closures, against the one its relations call for.

Every 2D run fits the walk share of its steps' covariance to its long closures (``summary.json`` ``chain_model``,
:mod:`evaluation.chain_model`); no ground truth goes in. This benchmark reads the runs of a finished
``slam batch`` (the development set: ``slam batch examples/devset.yaml --out DIR``) and, for every run whose log
has relations, puts beside each other in one process:

- the walk the closures gave (the run's summary) and the walk fitted the same way to the relations (the
  reference: ``slam eval nees RUN RELATIONS --fit-walk``), and the time the closures' fit takes;
- NEES/dof per chain length against the relations under the edges as stated (walk 1, no jitter, the loop
  closer's heading rate) and under the run's calibration (``slam eval nees RUN RELATIONS``, its default): how
  many bins of at least ``--min-n`` relations fall inside [0.5, 2] (the issue's consistency bar), and the
  bins themselves.

Prints ONE JSON object (also written to ``--out``). Usage:

    .venv/bin/python benchmarks/chain_model.py DIR [--spec examples/devset.yaml] [--min-n 10] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from core.run_summary import read_run_summary  # noqa: E402
from core.trajectory import read_node_stamps  # noqa: E402
from evaluation.chain_model import calibrate, fit_walk, split_jitter  # noqa: E402
from evaluation.nees import bin_by_length, chain_sample, closure_sample  # noqa: E402
from evaluation.relations import read_relations, reference_noise  # noqa: E402
from evaluation.trajectory import nearest_indices  # noqa: E402
from slam.batch.spec import load_spec  # noqa: E402
from slam.cli.run_eval import log_stem  # noqa: E402
from slam.graph import read_graph  # noqa: E402
from slam.pipeline.consistency import graph_chain, graph_closures  # noqa: E402
from slam.trajectory_io import read_trajectory  # noqa: E402

INSIDE = (0.5, 2.0)


def relation_sample(run: Path, relations: Path, drift_rad_per_m: float, tol_s: float = 1e-3):  # type: ignore[no-untyped-def]
    """The run's chains against *relations*, as ``slam eval nees RUN RELATIONS`` builds them."""
    graph = read_graph(run / "graph.g2o")
    mu, cov = graph_chain(graph)
    node_t = read_node_stamps(run / "node_stamps.txt", graph.node_ids)
    scans = read_trajectory(run / "odometry.tum")
    kf_scan = np.searchsorted(node_t, scans.stamps + tol_s, side="right") - 1
    _, sa = nearest_indices(node_t, scans.stamps, tol_s)
    rel = read_relations(relations)
    i1, s1 = nearest_indices(rel.t1, scans.stamps, tol_s)
    i2, s2 = nearest_indices(rel.t2, scans.stamps, tol_s)
    m1, m2 = dict(zip(i1, s1)), dict(zip(i2, s2))
    keep = [r for r in np.intersect1d(i1, i2) if kf_scan[m1[r]] >= 0 and kf_scan[m2[r]] >= 0]
    pairs = np.array([(m1[r], m2[r]) for r in keep], dtype=np.int64)
    return chain_sample(mu, cov, kf_scan, scans.poses, scans.poses[sa], pairs, rel.deltas[keep], drift_rad_per_m,
                        reference_noise(rel).covariance(), 0.0)


def _bins(rows: np.ndarray, min_n: int) -> tuple[list[dict], int, int]:
    """The bins as dicts, and how many of those with at least *min_n* chains are inside [0.5, 2], of how many."""
    bins = bin_by_length(rows)
    big = [b for b in bins if b.n >= min_n]
    return ([{"lo": b.lo, "hi": b.hi, "n": b.n, "nees_mean": round(b.nees_mean, 3), "nees_median": round(b.nees_median, 3)}
             for b in bins], sum(INSIDE[0] <= b.nees_mean <= INSIDE[1] for b in big), len(big))


def measure(run: Path, relations: Path, min_n: int) -> dict:
    """One run: the closures' and the relations' walk, and the relations' NEES under both models."""
    summary = read_run_summary(run / "summary.json")
    drift = float(np.radians(summary.config["loops"]["heading_drift_deg_per_m"]))
    graph = read_graph(run / "graph.g2o")
    mu, cov = graph_chain(graph)
    t0 = time.perf_counter()
    own = calibrate(closure_sample(mu, cov, graph_closures(graph)))
    fit_s = time.perf_counter() - t0
    calibrated = summary.chain_model
    assert calibrated is None or own is None or abs(own.walk - calibrated["walk"]) <= 1e-9 * calibrated["walk"]
    stated_bins, stated_in, n_big = _bins(relation_sample(run, relations, drift).rows(), min_n)
    plain = relation_sample(run, relations, 0.0)
    reference = fit_walk(plain)
    out = {"relations": len(plain), "closures": summary.loop_closures, "calibration_s": round(fit_s, 3),
           "walk_closures": None if own is None else round(own.walk, 4),
           "walk_relations": None if reference is None else round(reference[0], 4),
           "stated": {"bins_inside": stated_in, "bins": n_big, "table": stated_bins}}
    if own is not None:
        cal_bins, cal_in, _ = _bins(plain.rows(own.walk, split_jitter(own.walk)), min_n)
        out["calibrated"] = {"bins_inside": cal_in, "bins": n_big, "table": cal_bins}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("batch", type=Path, help="a slam batch output folder (runs/<log>/<setting>/)")
    ap.add_argument("--spec", type=Path, default=ROOT / "examples" / "devset.yaml", help="the batch's spec (for each log's relations)")
    ap.add_argument("--setting", default="default")
    ap.add_argument("--min-n", type=int, default=10, help="bins with fewer relations are shown, not counted")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    spec = load_spec(args.spec, log_stem)
    logs = {}
    for e in spec.logs:
        rel = e.relations or e.found_relations
        run = args.batch / "runs" / e.name / args.setting
        if rel is not None and (run / "summary.json").is_file():
            logs[e.name] = measure(run, rel, args.min_n)
    cal = [v["calibrated"] for v in logs.values() if "calibrated" in v]
    ratio = [v["walk_closures"] / v["walk_relations"] for v in logs.values() if v["walk_closures"] and v["walk_relations"]]
    result = {"logs": logs, "runs": len(logs), "min_n": args.min_n,
              "bins_inside_stated": sum(v["stated"]["bins_inside"] for v in logs.values()),
              "bins_inside_calibrated": sum(c["bins_inside"] for c in cal),
              "bins_counted": sum(v["stated"]["bins"] for v in logs.values()),
              "walk_closures_over_relations": [round(r, 3) for r in ratio],
              "max_calibration_s": max((v["calibration_s"] for v in logs.values()), default=0.0)}
    text = json.dumps(result, indent=1)
    if args.out:
        args.out.write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
