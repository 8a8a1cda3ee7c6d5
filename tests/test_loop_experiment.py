"""`slam loops`: one front-end pass, loop closure replayed per setting of a sweep grid, scored and written.

Properties checked: recall cannot rise when verification gets stricter; the replay accepts exactly what
`run_slam` accepts with the same setting; CSV and JSON hold the same rows, one per grid point; the relation
error found beside the log is the SLAM trajectory's (small on a simulated log); bad sweeps fail in one line
with exit 2 and leave no output folder.
"""

from __future__ import annotations

import csv
import json
from dataclasses import replace

import numpy as np
import pytest

from core import geometry as G
from core.errors import ConfigError
from evaluation.sim import LASER_PRESETS, load_world, simulate
from slam.cli import main
from slam.logs import open_log
from slam.logs.simulated import write_simulated_log
from slam.pipeline.config import LoopConfig, SlamConfig
from slam.pipeline.loop_replay import record_front_end
from slam.pipeline.loop_sweep import COLUMNS_SELF, parse_sweep, sweep_grid, sweep_recorded
from slam.pipeline.run import run_slam

pytestmark = pytest.mark.xdist_group("pipeline")

SWEEP = "consistency_probability=0.2:0.95:3"  # includes the default 0.95; at 0.2 the gate refuses every closure


@pytest.fixture(scope="module")
def sim_log(tmp_path_factory):
    """250 scans in the corridor world with a SICK LMS (fast to register, with revisits), relations beside it."""
    d = tmp_path_factory.mktemp("loops")
    sim = simulate(load_world("corridor"), n_scans=250, spec=LASER_PRESETS["sick_lms"], seed=7)
    path = d / "corridor.mcap"
    write_simulated_log(sim, path)
    # Kümmerle-style relations from the ground truth: scan i to scan i + 25 (t1 t2 x y z roll pitch yaw).
    i = np.arange(0, len(sim) - 25, 5)
    rel = G.relative(sim.ground_truth[i], sim.ground_truth[i + 25])
    xyt = G.matrix_to_xytheta(rel)
    rows = np.column_stack([sim.stamps[i], sim.stamps[i + 25], xyt[:, 0], xyt[:, 1], np.zeros((len(i), 3)), xyt[:, 2]])
    np.savetxt(d / "corridor.relations", rows, fmt="%.9f")
    return path


@pytest.fixture(scope="module")
def cli_run(sim_log, tmp_path_factory):
    """`slam loops LOG --sweep consistency_probability=0.2:0.95:3` (relations found beside the log)."""
    out = tmp_path_factory.mktemp("out") / "sweep"
    with pytest.raises(SystemExit) as exc:
        main(["loops", str(sim_log), "--sweep", SWEEP, "--out", str(out), "--quiet"])
    assert exc.value.code in (0, None)
    return out


def _csv_rows(out):
    with open(out / "loops.csv", newline="") as fh:
        return list(csv.DictReader(fh))


def test_recall_does_not_fall_as_the_consistency_gate_widens(cli_run):
    """A wider χ² gate for closures the estimate vouches for (a higher consistency_probability) accepts no fewer
    closures and closes no fewer revisits; the recall denominator (true revisits) is the same for every setting."""
    rows = json.loads((cli_run / "loops.json").read_text())["rows"]
    p = [r["consistency_probability"] for r in rows]
    assert p == sorted(p) and len(p) == 3
    recall = [r["recall"] for r in rows]
    assert all(a <= b for a, b in zip(recall, recall[1:])), recall
    accepted = [r["accepted"] for r in rows]
    assert all(a <= b for a, b in zip(accepted, accepted[1:])) and accepted[0] < accepted[-1], accepted  # it trades
    assert len({r["revisits"] for r in rows}) == 1 and rows[0]["revisits"] > 0
    for r in rows:
        assert r["true_positive"] + r["false_positive"] == r["accepted"]
        if r["accepted"]:
            assert r["precision"] == pytest.approx(r["true_positive"] / r["accepted"])
        assert r["recall"] == pytest.approx(r["revisits_found"] / r["revisits"])


def test_default_row_matches_run_slam(cli_run, sim_log):
    """The grid point at the default setting accepts (and prunes) exactly as many closures as run_slam."""
    rows = json.loads((cli_run / "loops.json").read_text())["rows"]
    row = next(r for r in rows if r["consistency_probability"] == pytest.approx(LoopConfig().consistency_probability))
    result = run_slam(open_log(sim_log).frames(), SlamConfig.model_validate({"mapping": {"enabled": False}}))
    assert row["accepted"] == len(result.loops) > 0
    assert row["pruned"] == result.loop_stats["pruned"]


def test_csv_and_json_agree_one_row_per_grid_point(cli_run):
    """loops.csv and loops.json have the same columns and values, one row per grid point; pr.png is a PNG."""
    doc = json.loads((cli_run / "loops.json").read_text())
    rows = _csv_rows(cli_run)
    assert list(rows[0].keys()) == doc["columns"]
    assert len(rows) == len(doc["rows"]) == len(parse_sweep(SWEEP).values)
    assert doc["ground_truth"] is True and doc["sweeps"] == {"consistency_probability": [0.2, 0.575, 0.95]}
    for c_row, j_row in zip(rows, doc["rows"]):
        for k in doc["columns"]:
            v = j_row[k]
            assert (c_row[k] == "") if v is None else float(c_row[k]) == pytest.approx(v, rel=1e-12), k
    assert (cli_run / "pr.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_relation_error_beside_the_log(cli_run):
    """<stem>.relations beside the log is found; the SLAM trajectory satisfies the true relations within 5 cm / 1°."""
    doc = json.loads((cli_run / "loops.json").read_text())
    assert doc["relations"].endswith("corridor.relations")
    for r in doc["rows"]:
        assert 0 <= r["relation_trans_mean_m"] < 0.05 and 0 <= r["relation_rot_mean_deg"] < 1.0


def test_without_ground_truth_precision_is_self_consistency(sim_log):
    """Frames without ground truth are scored by Cartographer's criterion: precision = consistent / accepted."""
    cfg = SlamConfig.model_validate({"mapping": {"enabled": False}})  # the revisits that pass every test come after scan 150
    rec = record_front_end((replace(f, ground_truth=None) for f in open_log(sim_log).frames()), cfg)
    assert rec.ground_truth is None and len(rec.stamps) == 250
    res = sweep_recorded(rec, cfg)
    assert res.columns == list(COLUMNS_SELF) and len(res.rows) == 1
    r = res.rows[0]
    assert r["accepted"] > 0 and r["precision"] == pytest.approx(r["consistent"] / r["accepted"])


def test_sweep_parsing_and_grid():
    """start and stop are both included, count values evenly spaced; integer fields get ints; the grid is the
    cartesian product, first sweep slowest, every point a valid LoopConfig with the swept values."""
    s = parse_sweep("max_relative_rmse=0.05:0.1:6")
    assert len(s.values) == 6 and s.values[0] == 0.05 and s.values[-1] == pytest.approx(0.1)
    assert np.allclose(np.diff(s.values), 0.01)
    k = parse_sweep("exclude_recent_keyframes=10:20:3")
    assert k.values == (10, 15, 20) and all(isinstance(v, int) for v in k.values)
    assert parse_sweep("local_map_keyframes=1:3:5").values == (1, 2, 3)  # rounded, repeats dropped
    grid = sweep_grid(LoopConfig(), [s, k])
    assert len(grid) == 18
    assert [g[0] for g in grid[:3]] == [{"max_relative_rmse": 0.05, "exclude_recent_keyframes": v} for v in (10, 15, 20)]
    assert all(cfg.max_relative_rmse == st["max_relative_rmse"] and cfg.exclude_recent_keyframes == st["exclude_recent_keyframes"]
               for st, cfg in grid)
    assert sweep_grid(LoopConfig(), []) == [({}, LoopConfig())]
    # A check that can be switched off (None) is swept over its numeric values.
    r = parse_sweep("overlap_radius_m=0.1:0.3:3")
    assert r.values == (0.1, 0.2, 0.3)
    assert [cfg.overlap_radius_m for _, cfg in sweep_grid(LoopConfig(overlap_radius_m=None), [r])] == [0.1, 0.2, 0.3]


@pytest.mark.parametrize("bad", ["min_relative_fitness", "min_relative_fitness=0.5:0.8", "nope=1:2:3", "descriptor=0:1:2",
                                 "icp_gates_m=0.1:0.2:2", "min_relative_fitness=0.5:1.5:3", "min_relative_fitness=a:0.8:3",
                                 "min_relative_fitness=0.5:0.8:0", "min_relative_fitness=0.5:0.8:2.5", "max_relative_rmse=-1:0.1:3",
                                 "min_relative_fitness=nan:0.8:3"])
def test_bad_sweep_fails_in_one_line_without_output(bad, sim_log, tmp_path, capsys):
    """A malformed or out-of-range --sweep exits 2 with one `error:` line and creates no output folder."""
    out = tmp_path / "never"
    with pytest.raises(SystemExit) as exc:
        main(["loops", str(sim_log), "--sweep", bad, "--out", str(out), "--quiet"])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and "--sweep" in err[0]
    assert not out.exists()
    with pytest.raises(ConfigError):
        sweep_grid(LoopConfig(), [parse_sweep(bad)])


def test_same_field_swept_twice_is_an_error(sim_log, tmp_path, capsys):
    """Two --sweep options for one field exit 2 with one line; nothing is written."""
    out = tmp_path / "never"
    with pytest.raises(SystemExit) as exc:
        main(["loops", str(sim_log), "--sweep", "max_relative_rmse=0.05:0.1:2", "--sweep", "max_relative_rmse=0.1:0.2:2",
              "--out", str(out)])
    assert exc.value.code == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1 and not out.exists()


def test_missing_log_creates_no_output(tmp_path, capsys):
    """A log that does not exist: exit 2, one line, no output folder."""
    out = tmp_path / "never"
    with pytest.raises(SystemExit) as exc:
        main(["loops", str(tmp_path / "missing.mcap"), "--out", str(out), "--quiet"])
    assert exc.value.code == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1 and not out.exists()
