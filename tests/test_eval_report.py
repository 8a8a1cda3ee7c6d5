"""`slam eval report`: the HTML is self-contained, every image decodes, metrics.json holds the printed numbers."""

from __future__ import annotations

import base64
import io
import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from core import geometry as geo
from core import pose_formats
from core.trajectory import Trajectory, write_tum
from evaluation.report import flatten_metrics, resample_classes

RES = 0.1
GT_ORIGIN = np.array([-2.0, -2.0, 0.0])


def _world() -> np.ndarray:
    """A 20 m × 14 m room with a 4 m × 3 m block inside: classes 100 walls, 0 free, −1 outside."""
    h, w = 180, 240
    cls = np.full((h, w), -1, np.int8)
    cls[20:160, 20:220] = 100
    cls[22:158, 22:218] = 0
    cls[70:100, 100:140] = 100
    return cls


def _gt_traj(n_lap=150) -> Trajectory:
    th = np.linspace(0, 2 * np.pi, n_lap, endpoint=False)
    th = np.concatenate([th, th + 2 * np.pi])
    x, y = 10 + 7 * np.cos(th), 5 + 5 * np.sin(th)
    heading = np.arctan2(5 * np.cos(th), -7 * np.sin(th))
    return Trajectory(1000.0 + 0.2 * np.arange(len(th)), geo.xytheta_to_matrix(x, y, heading), "gt")


@pytest.fixture(scope="module")
def run_summary(tmp_path_factory) -> dict:
    """summary.json of a real `slam run` (a 60-scan simulated corridor): the report reads what the pipeline
    writes, not a guess of it."""
    from slam.cli import main
    from tests.cli_helpers import corridor_log

    d = tmp_path_factory.mktemp("real_run")
    corridor_log(d / "c.mcap", 60, seed=4)
    with pytest.raises(SystemExit) as ei:
        main(["run", str(d / "c.mcap"), "--out", str(d / "run"), "--quiet", "--map", "none"])
    assert (ei.value.code or 0) == 0
    return json.loads((d / "run" / "summary.json").read_text())


def make_result_dir(rd: Path, rng, summary: dict) -> tuple[Path, Path]:
    """A synthetic 'slam run' folder (estimate in its own frame, drifted odometry, graph with loops, map) with
    a real run's *summary* (its counts and loop statistics set to the synthetic folder's)."""
    from mapping.mapserver import write_map_server
    from slam.graph import PoseGraph, write_g2o

    rd.mkdir(parents=True, exist_ok=True)
    gt = _gt_traj()
    write_tum(rd.parent / "gt.tum", gt)
    write_map_server(rd.parent / "gt_map.yaml", _world(), RES, GT_ORIGIN)
    slam_T_gt = geo.inverse(gt.poses[0])  # the estimate starts at the identity
    est = slam_T_gt @ gt.poses @ geo.se2_exp(rng.normal(0, [0.03, 0.03, 0.005], (len(gt), 3)))
    steps = geo.relative(gt.poses[:-1], gt.poses[1:]) @ geo.xytheta_to_matrix(0.01, 0.0, 0.004)
    odo = [np.eye(4)]
    for s in steps:
        odo.append(odo[-1] @ s)
    write_tum(rd / "trajectory.tum", Trajectory(gt.stamps, est))
    write_tum(rd / "odometry.tum", Trajectory(gt.stamps, np.array(odo)))
    keys = np.arange(0, len(gt), 5)
    g = PoseGraph(2)
    for k in keys:
        g.add_node(int(k), est[k])
    info = np.diag([100.0, 100.0, 1000.0])
    for a, b in zip(keys[:-1], keys[1:]):
        g.add_edge(int(a), int(b), geo.relative(est[a], est[b]), info, "odometry")
    half = len(gt) // 2
    for k in keys[keys < half][::3]:
        C = geo.xytheta_to_matrix(0.5, 0, 0) if k % 9 == 0 else np.eye(4)  # every third closure is wrong
        g.add_edge(int(k), int(k + half), geo.relative(gt.poses[k], gt.poses[k + half]) @ C, info, "loop")
    write_g2o(g, rd / "graph.g2o")
    # map in the SLAM frame: the ground truth seen through slam_T_gt, blurred into probabilities
    h, w = 240, 180  # the room in the SLAM frame spans x ∈ [−5, 9] m, y ∈ [−3, 17] m
    origin = np.array([-7.0, -5.0, 0.0])
    cls = resample_classes(_world(), RES, GT_ORIGIN, (h, w), RES, origin, geo.inverse(slam_T_gt))
    prob = np.where(cls == 100, 0.85, np.where(cls == 0, 0.15, 0.5)) + rng.normal(0, 0.25, (h, w))
    prob = np.clip(prob, 0, 1)
    var = np.where(cls == -1, 0.25, 0.02) + rng.uniform(0, 0.01, (h, w))
    np.savez(rd / "map.npz", mean=2 * prob - 1, variance=var, probability=prob, resolution=RES, origin=origin)
    (rd / "summary.json").write_text(json.dumps(summary | {"scans": len(gt), "keyframes": len(keys),
                                                           "loop_stats": {"accepted": 15, "pruned": 5}}))
    return rd.parent / "gt.tum", rd.parent / "gt_map.yaml"


def test_report_images_decode_and_metrics_match_console(tmp_path, rng, run_summary):
    """Every inline PNG of report.html decodes with Pillow; each number printed on the console equals the one
    in metrics.json; the map scored in the ground-truth frame has a high AUC (the alignment is applied)."""
    PIL = pytest.importorskip("PIL.Image")
    pytest.importorskip("slam.graph")
    gt, gt_map = make_result_dir(tmp_path / "run", rng, run_summary)
    out = subprocess.run([str(Path(sys.executable).parent / "slam"), "eval", "report", str(tmp_path / "run"),
                          "--gt", str(gt), "--gt-map", str(gt_map)], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    page = (tmp_path / "run" / "report.html").read_text()
    assert "src=\"http" not in page and "<script" not in page  # self-contained
    imgs = re.findall(r'src="data:image/png;base64,([A-Za-z0-9+/=]+)"', page)
    assert len(imgs) >= 5
    for b64 in imgs:
        im = PIL.open(io.BytesIO(base64.b64decode(b64)))
        im.load()
        assert im.size[0] > 300 and im.size[1] > 200
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    flat = flatten_metrics(metrics)
    printed = {}
    for line in out.stdout.splitlines():
        k, _, v = line.partition(": ")
        if k in flat:
            printed[k] = v
    assert set(printed) == set(flat)
    for k, v in printed.items():
        if isinstance(flat[k], (int, float)) and not isinstance(flat[k], bool):
            assert float(v) == pytest.approx(flat[k], rel=1e-9, abs=1e-12), k
        else:
            assert v == str(flat[k]), k
    assert metrics["map"]["auc"] > 0.95
    assert metrics["ape_trans_m"]["estimate"]["rmse"] < 0.1 < metrics["ape_trans_m"]["odometry"]["rmse"]
    assert metrics["loops"]["n_loops"] == 10 and metrics["graph"]["loop_edges"] == 10
    assert metrics["loops_vs_truth"]["precision"] == pytest.approx(6 / 10)
    assert metrics["summary"]["scans"] == 300
    # every stage time slam run wrote, under its stage name (issue 27: the report found none of a real run's)
    assert metrics["timings_s"] == {k.removesuffix("_s"): v for k, v in run_summary["stage_times_s"].items()}
    assert len(metrics["timings_s"]) >= 5 and "Stage timings" in page
    # The closures the back end pruned are not in graph.g2o; they count against the verifier.
    lp = metrics["loops"]
    assert lp["pruned_by_back_end"] == 5 and lp["precision_counting_pruned"] == pytest.approx(lp["n_correct"] / 15)


def test_report_with_partial_outputs(tmp_path, rng):
    """A folder with only trajectory.tum still renders, and the notes name what is missing."""
    pytest.importorskip("PIL.Image")
    from evaluation.report import write_report

    rd = tmp_path / "run"
    rd.mkdir()
    write_tum(rd / "trajectory.tum", _gt_traj(30))
    rep = write_report(rd)
    assert (rd / "report.html").exists() and json.loads((rd / "metrics.json").read_text())["trajectories"]["estimate"]["poses"] == 60
    assert any("map.npz" in n for n in rep.notes) and any("graph.g2o" in n for n in rep.notes)


def test_resample_classes_identity_grid():
    """Resampling a grid onto itself (same origin, resolution, no transform) returns it unchanged."""
    cls = _world()
    out = resample_classes(cls, RES, GT_ORIGIN, cls.shape, RES, GT_ORIGIN[:2])
    assert np.array_equal(out, cls)


def test_report_relations_table_with_published_numbers(tmp_path):
    """With --relations named like a benchmark file, metrics hold our relation statistics (zero for the exact
    trajectory) beside the published Intel numbers, and the HTML shows them side by side."""
    pytest.importorskip("PIL.Image")
    from evaluation.report import write_report

    rd = tmp_path / "run"
    rd.mkdir()
    gt = _gt_traj(40)
    write_tum(rd / "trajectory.tum", gt)
    i = np.arange(0, 79)
    D = geo.relative(gt.poses[i], gt.poses[i + 1])
    rpy = pose_formats.rotation_to_rpy(D[:, :3, :3])
    rows = np.column_stack([gt.stamps[i], gt.stamps[i + 1], D[:, :3, 3], rpy])
    (tmp_path / "intel.relations").write_text("".join(" ".join(repr(float(v)) for v in r) + "\n" for r in rows))
    rep = write_report(rd, relations=tmp_path / "intel.relations")
    rel = json.loads((rd / "metrics.json").read_text())["relations"]
    assert rel["dataset"] == "intel" and rel["estimate"]["n_used"] == 79 and rel["estimate"]["n_missing"] == 0
    assert rel["estimate"]["trans_mean"] < 1e-9
    assert rel["published"]["cartographer"]["trans"] == {"mean": 0.0229, "std": 0.0239}
    page = (rd / "report.html").read_text()
    assert "Kümmerle relation metric" in page and "0.0229 ± 0.0239" in page and "0.031 ± 0.026" in page
    assert any(f.title.startswith("Relation error") for f in rep.figures)


def test_report_when_no_relation_joins_two_scans(tmp_path):
    """Relations all beyond the trajectory's stamps (a short run over the start of a log): the report is
    still written, every relation counts as missing, and a note says none was usable."""
    pytest.importorskip("PIL.Image")
    from evaluation.report import write_report

    rd = tmp_path / "run"
    rd.mkdir()
    gt = _gt_traj(40)
    write_tum(rd / "trajectory.tum", gt)
    later = gt.stamps[-1] + 100.0 + np.arange(5.0)
    rows = np.column_stack([later, later + 0.5, np.zeros((5, 6))])
    (tmp_path / "x.relations").write_text("".join(" ".join(repr(float(v)) for v in r) + "\n" for r in rows))
    rep = write_report(rd, relations=tmp_path / "x.relations")
    rel = json.loads((rd / "metrics.json").read_text())["relations"]["estimate"]
    assert rel["n_used"] == 0 and rel["n_missing"] == 5
    assert any("none of the 5 relations" in n for n in rep.notes)
    assert (rd / "report.html").stat().st_size > 0


def test_a_runs_summary_reads_back_typed_and_a_foreign_one_is_named(tmp_path, run_summary):
    """summary.json of a real run is a RunSummary (every key known, the types right, the stage timings include
    writing the outputs); a key the format does not have makes read_run_summary name it, and the report then
    says so in a note instead of failing."""
    from core.errors import MapFormatError
    from core.run_summary import RunSummary, read_run_summary
    from evaluation.report import build_report

    s = RunSummary.model_validate(run_summary)
    assert s.scans == 60 and s.dimension == 2 and "outputs_s" in s.stage_times_s
    assert s.peak_memory_mb == pytest.approx(sum(s.peak_memory_by_process_mb.values()))
    p = tmp_path / "run" / "summary.json"
    p.parent.mkdir()
    p.write_text(json.dumps(run_summary | {"wal_time_s": 1.0}))
    with pytest.raises(MapFormatError, match="wal_time_s: unknown key"):
        read_run_summary(p)
    rep = build_report(p.parent)
    assert any("wal_time_s: unknown key" in n for n in rep.notes) and "summary" not in rep.metrics
