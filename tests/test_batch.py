"""`slam batch`: logs × settings as Ray tasks on a local Ray of 2 CPUs that this module starts and stops.

Properties checked: every batch run equals the sequential `slam run` of the same log and config byte for
byte (trajectory) and in its figures; a broken log is its rows' `failed:` line naming the file and the
position, the others finish, exit status 1; --resume runs nothing again (tasks counted, folders untouched)
and a changed config reruns exactly the runs it changes; Ctrl-C leaves only complete run folders and no
Ray process; `slam loops --parallel` gives the rows of `slam loops`; the short form is the spec without a
file; a bad spec is one line, exit 2, nothing written; nothing imports Ray unless a batch runs.
"""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest

from core import geometry as G
from evaluation.sim import LASER_PRESETS, load_world, simulate
from slam.cli import main
from slam.logs.simulated import write_simulated_log
from tests.conftest import DATA, REPO
from tests.test_logs_skip import rewrite_mcap

pytestmark = pytest.mark.xdist_group("batch")

SWEEP = "odometry.icp_2d.icp.tol_translation_m=0.0005:0.001:2"  # a dotted name: any numeric config value
SETTINGS = ("odometry.icp_2d.icp.tol_translation_m=0.0005", "odometry.icp_2d.icp.tol_translation_m=0.001")


def _slam(args, capsys):
    """Run the CLI in this process: (exit code, stdout, stderr)."""
    with pytest.raises(SystemExit) as ei:
        main([str(a) for a in args])
    cap = capsys.readouterr()
    return ei.value.code or 0, cap.out, cap.err


def _ray_processes(temp_dir: str) -> list[int]:
    """Processes whose command line names *temp_dir* (a Ray instance's session lives there)."""
    import psutil

    pids = []
    for p in psutil.process_iter(["pid", "cmdline"]):
        try:
            if any(temp_dir in part for part in (p.info["cmdline"] or [])):
                pids.append(p.info["pid"])
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            pass
    return pids


def _no_ray_left(temp_dir: str, timeout_s: float = 20.0) -> list[int]:
    deadline = time.monotonic() + timeout_s
    while (left := _ray_processes(temp_dir)) and time.monotonic() < deadline:
        time.sleep(0.5)
    return left


@pytest.fixture(scope="module")
def ray_cluster():
    """A local Ray of 2 CPUs for this module (the CLI in this process uses it); stopped after, no process left."""
    import ray

    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    temp_dir = tempfile.mkdtemp(prefix="rt", dir="/tmp")  # short: Ray's socket paths live under it
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, _temp_dir=temp_dir)
    try:
        yield ray
    finally:
        ray.shutdown()
        assert _no_ray_left(temp_dir) == [], "Ray processes left after ray.shutdown()"


def _relations(sim, path: Path) -> None:
    """Kümmerle-style relations from the simulator's ground truth: scan i to scan i + 20."""
    i = np.arange(0, len(sim) - 20, 5)
    xyt = G.matrix_to_xytheta(G.relative(sim.ground_truth[i], sim.ground_truth[i + 20]))
    rows = np.column_stack([sim.stamps[i], sim.stamps[i + 20], xyt[:, 0], xyt[:, 1], np.zeros((len(i), 3)), xyt[:, 2]])
    np.savetxt(path, rows, fmt="%.9f")


@pytest.fixture(scope="module")
def logs(tmp_path_factory):
    """Three 110-scan simulated corridor tours (SICK LMS, ground truth in the frames, relations beside the
    first) and a copy of the second whose /scan message 40 cannot be decoded."""
    d = tmp_path_factory.mktemp("logs")
    good = []
    for k, seed in enumerate((1, 3, 6)):
        sim = simulate(load_world("corridor"), n_scans=110, spec=LASER_PRESETS["sick_lms"], seed=seed)
        path = d / f"tour{k}.mcap"
        write_simulated_log(sim, path)
        good.append(path)
        if k == 0:
            _relations(sim, d / "tour0.relations")
    bad = rewrite_mcap(good[1], d / "broken.mcap", "/scan", 40)
    return good, bad


def _spec(path: Path, logs: list[Path], extra: str = "") -> Path:
    lines = ["config: {mapping.enabled: false}", "logs:", *[f"  - {p}" for p in logs], "sweep:", f"  - {SWEEP}"]
    path.write_text("\n".join(lines) + "\n" + extra)
    return path


@pytest.fixture(scope="module")
def batch(ray_cluster, logs, tmp_path_factory):
    """The batch of 4 logs (one broken) × 2 settings, run once through the CLI: (out folder, exit code, stdout)."""
    good, bad = logs
    d = tmp_path_factory.mktemp("batch")
    spec = _spec(d / "spec.yaml", [*good, bad])
    out = d / "out"
    with pytest.raises(SystemExit) as ei:
        main(["batch", str(spec), "--out", str(out), "--quiet"])
    return out, ei.value.code, json.loads((out / "results.json").read_text())


@pytest.fixture(scope="module")
def sequential(logs, tmp_path_factory):
    """`slam run LOG --eval --config C` for every good log and setting, one after another in this process."""
    good, _ = logs
    d = tmp_path_factory.mktemp("sequential")
    out = {}
    for value in (0.0005, 0.001):
        cfg = d / f"cfg{value}.yaml"
        cfg.write_text(f"mapping:\n  enabled: false\nodometry:\n  icp_2d:\n    icp:\n      tol_translation_m: {value}\n")
        for log in good:
            run = d / f"{log.stem}_{value}"
            with pytest.raises(SystemExit) as ei:
                main(["run", str(log), "--config", str(cfg), "--out", str(run), "--eval", "--quiet"])
            assert ei.value.code in (0, None)
            out[(log.stem, f"odometry.icp_2d.icp.tol_translation_m={value}")] = run
    return out


def test_batch_runs_equal_sequential_slam_runs(batch, sequential):
    """Each of the 6 good rows: the run folder's trajectory.tum equals sequential `slam run`'s byte for byte, and
    its figures (APE, relation error, closures, keyframes) are that run's metrics.json and summary.json."""
    out, _, doc = batch
    ok = [r for r in doc["rows"] if r["status"] == "ok"]
    assert sorted((r["log"], r["setting"]) for r in ok) == sorted(sequential)
    for r in ok:
        single = sequential[(r["log"], r["setting"])]
        run = out / "runs" / r["log"] / r["setting"]
        assert r["run_dir"] == str(run)
        assert (run / "trajectory.tum").read_bytes() == (single / "trajectory.tum").read_bytes()
        m = json.loads((single / "metrics.json").read_text())
        s = json.loads((single / "summary.json").read_text())
        assert r["ape_rmse_m"] == m["ape_trans_m"]["estimate"]["rmse"]
        assert r["keyframes"] == s["keyframes"] and r["scans"] == s["scans"] == 110
        assert r["loops_accepted"] == s["loop_closures"] + s["loop_stats"]["pruned"]
        if r["log"] == "tour0":  # relations beside the log, found as `slam run --eval` finds them
            assert r["relation_trans_mean_m"] == m["relations"]["estimate"]["trans_mean"] < 0.05
            assert r["relations_used"] == m["relations"]["estimate"]["n_used"] > 0
        else:
            assert r["relation_trans_mean_m"] is None
    # The setting reaches the run: the two ICP tolerances give different trajectories.
    traj = {(r["log"], r["setting"]): (out / "runs" / r["log"] / r["setting"] / "trajectory.tum").read_bytes() for r in ok}
    assert all(traj[(g, SETTINGS[0])] != traj[(g, SETTINGS[1])] for g in ("tour0", "tour1", "tour2"))


def test_loop_precision_is_the_reports(batch):
    """The row's loop precision (from graph.g2o, the pruned closures counted as violated) is the evaluation
    report's precision_counting_pruned of the same run folder."""
    out, _, doc = batch
    for r in (r for r in doc["rows"] if r["status"] == "ok"):
        lp = json.loads((out / "runs" / r["log"] / r["setting"] / "metrics.json").read_text()).get("loops", {})
        if r["loops_accepted"]:
            assert r["loop_precision"] == pytest.approx(lp["precision_counting_pruned"], abs=1e-12)
        else:
            assert r["loop_precision"] is None


def test_the_row_carries_the_runs_self_check(batch):
    """Each ok row's self-check verdict and contradicting / checked keyframes are those of its run's
    summary.json; a failed row has none."""
    out, _, doc = batch
    for r in doc["rows"]:
        if r["status"] != "ok":
            assert r["self_check"] is None and r["self_check_contradicting"] is None
            continue
        sc = json.loads((out / "runs" / r["log"] / r["setting"] / "summary.json").read_text())["self_check"]
        assert r["self_check"] == sc["verdict"] in ("consistent", "suspect")
        assert r["self_check_contradicting"] == f"{sc['keyframes_contradicting']} / {sc['keyframes_checked']}"
    assert "| self-check |" in (out / "results.md").read_text()


def test_broken_log_is_a_failed_row_and_the_rest_finish(batch, logs):
    """The broken log's two rows say `failed: <file>:/scan message 40: ...`; no folder was made for them;
    the 6 others are ok; the exit status is 1."""
    out, code, doc = batch
    _, bad = logs
    assert code == 1
    rows = {(r["log"], r["setting"]): r for r in doc["rows"]}
    assert len(rows) == 8 and [r["log"] for r in doc["rows"]] == ["tour0"] * 2 + ["tour1"] * 2 + ["tour2"] * 2 + ["broken"] * 2
    for s in SETTINGS:
        status = rows[("broken", s)]["status"]
        assert status.startswith(f"failed: {bad}:/scan message 40: ") and "\n" not in status
    assert sum(r["status"] == "ok" for r in doc["rows"]) == 6
    assert not (out / "runs" / "broken").exists()
    assert doc["ok"] == 6 and doc["failed"] == 2 and doc["tasks_run"] == 8 and doc["resumed"] == 0
    hidden = [p for p in out.rglob(".*")]
    assert hidden == []


def test_results_csv_json_md_and_report_agree(batch):
    """results.csv and results.json hold the same rows and columns; results.md has a line per row; report.html
    carries its figures inline (the relation-error bars and the per-setting plots of the sweep)."""
    out, _, doc = batch
    with open(out / "results.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert list(rows[0]) == doc["columns"] and len(rows) == len(doc["rows"]) == 8
    assert doc["columns"][:3] == ["log", "setting", "odometry.icp_2d.icp.tol_translation_m"]
    for c_row, j_row in zip(rows, doc["rows"]):
        for k in doc["columns"]:
            v = j_row[k]
            if v is None:
                assert c_row[k] == ""
            elif isinstance(v, float):
                assert float(c_row[k]) == v
            else:
                assert c_row[k] == str(v)
    md = (out / "results.md").read_text().splitlines()
    assert len(md) == 2 + 8 and all(line.startswith("|") and line.endswith("|") for line in md)
    html = (out / "report.html").read_text()
    # relation bars and relation error against the swept value, and, when any run closed a loop (these short
    # tours may not return to an earlier pass), precision bars and precision against the swept value
    closed = any(r["loop_precision"] is not None for r in doc["rows"])
    assert html.count("data:image/png;base64,") == (4 if closed else 2)
    assert ("Loop-closure precision per log" in html) == closed
    assert "Relation error per log" in html and "against odometry.icp_2d.icp.tol_translation_m" in html


def test_resume_reruns_nothing_and_a_changed_config_reruns_its_runs(batch, logs, tmp_path, capsys):
    """A spec of the good logs into the same folder: 0 tasks (every run has the same log and config hash), the
    folders untouched. A config value changed for one log: exactly its 2 runs again, the others resumed."""
    out, _, _ = batch
    good, _ = logs
    before = {p: p.stat().st_mtime_ns for p in out.glob("runs/*/*/batch.json")}
    spec = _spec(tmp_path / "again.yaml", good)
    code, stdout, err = _slam(["batch", spec, "--out", out, "--quiet"], capsys)
    assert code == 0, err
    doc = json.loads((out / "results.json").read_text())
    assert doc["tasks_run"] == 0 and doc["resumed"] == 6 and all(r["resumed"] for r in doc["rows"])
    assert {p: p.stat().st_mtime_ns for p in out.glob("runs/*/*/batch.json")} == before
    # tour2 gets its own config value: its two runs have another config hash
    lines = spec.read_text().replace(f"  - {good[2]}", f"  - log: {good[2]}\n    config: {{odometry.icp_2d.icp.tol_translation_m: 4.0e-4}}")
    spec.write_text(lines)
    code, _, err = _slam(["batch", spec, "--out", out, "--quiet"], capsys)
    assert code == 0, err
    doc = json.loads((out / "results.json").read_text())
    assert doc["tasks_run"] == 2 and doc["resumed"] == 4
    rerun = {r["log"] for r in doc["rows"] if not r["resumed"]}
    assert rerun == {"tour2"}
    after = {p: p.stat().st_mtime_ns for p in out.glob("runs/*/*/batch.json")}
    assert {p for p in after if after[p] != before[p]} == {p for p in before if p.parts[-3] == "tour2"}


def test_two_cpus_per_run_keep_the_stage_processes(ray_cluster, logs, batch, tmp_path, capsys):
    """--cpus-per-run 2: the run keeps its front-end process (its peak memory is counted) and its trajectory
    equals the one-process run's."""
    out1, _, _ = batch
    good, _ = logs
    out = tmp_path / "two"
    code, _, err = _slam(["batch", good[0], "--sweep", "odometry.icp_2d.icp.tol_translation_m=0.0005:0.0005:1", "--config",
                          _mapping_off(tmp_path), "--out", out, "--cpus-per-run", "2", "--quiet"], capsys)
    assert code == 0, err
    run = out / "runs" / "tour0" / SETTINGS[0]
    s = json.loads((run / "summary.json").read_text())
    assert s["config"]["stage_processes"] is True and "front_end" in s["peak_memory_by_process_mb"]
    assert (run / "trajectory.tum").read_bytes() == (out1 / "runs" / "tour0" / SETTINGS[0] / "trajectory.tum").read_bytes()


def _mapping_off(d: Path) -> Path:
    p = d / "mapping_off.yaml"
    p.write_text("mapping:\n  enabled: false\n")
    return p


def test_short_form_is_the_spec_without_a_file(logs, tmp_path):
    """`slam batch LOG... --sweep ... --config ...` expands to the jobs of the equivalent spec: same folders,
    same config hashes."""
    from slam.batch.spec import load_spec, spec_from_command_line
    from slam.cli.run_eval import log_stem

    good, _ = logs
    spec = _spec(tmp_path / "s.yaml", good)
    a = load_spec(spec, log_stem).jobs(tmp_path / "o")
    b = spec_from_command_line([str(p) for p in good], [SWEEP], _mapping_off(tmp_path), log_stem).jobs(tmp_path / "o")
    assert [(j.out, j.config_sha256, j.log_sha256) for j in a] == [(j.out, j.config_sha256, j.log_sha256) for j in b]
    # tour1 and tour2 share a config per setting; tour0's hash has the content of the relations beside it
    assert len(a) == 6 and len({j.config_sha256 for j in a}) == 4


def test_settings_are_explicit_ones_times_the_sweep_and_log_values_come_last(logs, tmp_path):
    """Two explicit settings × a 2-point sweep = 4 settings with distinct ids; every job's config holds its
    setting's values, and a log's own config value wins over the setting's."""
    from slam.batch.spec import load_spec
    from slam.cli.run_eval import log_stem

    good, _ = logs
    spec = tmp_path / "s.yaml"
    spec.write_text(f"""logs:
  - log: {good[0]}
    config: {{odometry: {{use_wheel_odometry: false}}}}
  - {good[1]}
sweep: [exclude_recent_keyframes=10:20:2]
settings:
  - {{id: base}}
  - {{odometry.use_wheel_odometry: true, backend: {{kind: chordal}}}}
""")
    b = load_spec(spec, log_stem)
    ids = [s.id for s in b.settings]
    assert ids == ["base,loops.exclude_recent_keyframes=10", "base,loops.exclude_recent_keyframes=20",
                   "odometry.use_wheel_odometry=true,backend.kind=chordal,loops.exclude_recent_keyframes=10",
                   "odometry.use_wheel_odometry=true,backend.kind=chordal,loops.exclude_recent_keyframes=20"]
    assert b.value_names == ["loops.exclude_recent_keyframes", "odometry.use_wheel_odometry", "backend.kind"]
    jobs = b.jobs(tmp_path / "o")
    assert len(jobs) == 8
    for j in jobs:
        assert j.config["loops"]["exclude_recent_keyframes"] == j.values["loops.exclude_recent_keyframes"]
        assert j.config["backend"]["kind"] == j.values.get("backend.kind", "gtsam")
        assert j.config["odometry"]["use_wheel_odometry"] is (j.log_name != "tour0")


def test_hashes_follow_content_not_names(tmp_path):
    """The log hash is of the bytes (a copy under another name has the same, one changed byte not); the config
    hash ignores stage_processes and changes with any other value or the reference's content."""
    from slam.batch.fingerprint import config_sha256, content_sha256
    from slam.pipeline.config import SlamConfig

    a, b = tmp_path / "a.clf", tmp_path / "b.clf"
    a.write_bytes(b"FLASER 1 2 3\n" * 1000)
    b.write_bytes(a.read_bytes())
    assert content_sha256(a) == content_sha256(b)
    b.write_bytes(a.read_bytes()[:-2] + b"4\n")
    assert content_sha256(a) != content_sha256(b)
    c = SlamConfig().model_dump(mode="json")
    h = config_sha256(c, None, {"relations": None})
    assert config_sha256(c | {"stage_processes": not c["stage_processes"]}, None, {"relations": None}) == h
    assert config_sha256(c | {"max_scans": 10}, None, {"relations": None}) != h
    assert config_sha256(c, None, {"relations": "0" * 64}) != h
    assert config_sha256(c, None, {"relations": None}, code="0" * 64) != h  # rows another version made are rerun


def test_the_code_hash_follows_the_packages_sources(tmp_path):
    """code_sha256 reads every .py file of the installed packages: a changed byte in one changes it, a file
    outside them (tests, docs) does not; the project's own tree hashes as the running code."""
    from slam.batch.fingerprint import PACKAGES, code_sha256

    for pkg in PACKAGES:
        (tmp_path / pkg / "sub").mkdir(parents=True)
        (tmp_path / pkg / "sub" / "m.py").write_text(f"X = '{pkg}'\n")
    (tmp_path / "tests").mkdir()
    (tmp_path / "tests" / "t.py").write_text("pass\n")
    h = code_sha256(str(tmp_path))
    (tmp_path / "tests" / "t.py").write_text("assert True\n")
    (tmp_path / "README.md").write_text("# changed\n")
    code_sha256.cache_clear()
    assert code_sha256(str(tmp_path)) == h
    (tmp_path / "slam" / "sub" / "m.py").write_text("X = 'slam!'\n")
    code_sha256.cache_clear()
    assert code_sha256(str(tmp_path)) != h
    assert code_sha256(str(REPO)) == code_sha256()


@pytest.mark.parametrize("body, where, what", [
    ("logs: [missing.clf]\n", "logs[0]", "no such log"),
    ("logs: ['nothing*.clf']\n", "logs[0]", "no log matches"),
    ("logs: [{LOG}]\nsweep: [exclude_recent_keyframes=0:5:2]\n", "sweep", "exclude_recent_keyframes"),
    ("logs: [{LOG}]\nsweep: [nope=1:2:3]\n", "sweep[0]", "not a numeric setting"),
    ("logs: [{LOG}]\nsettings: [{{odometry.nope: 1}}]\n", "settings[0]", "'odometry.nope' is not a configuration setting"),
    ("logs: [{LOG}]\nsettings: [{{max_scans: 0}}]\n", "settings[0]", "max_scans"),
    ("logs: [{{log: {LOG}, relations: none.relations}}]\n", "logs[0].relations", "no such file"),
    ("logs: [{LOG}, {LOG}]\n", "logs", "two logs named 'tour0'"),
    ("logs: [{{log: {LOG}, colour: red}}]\n", "logs[0]", "unknown key"),
    ("logs: [{LOG}\n  - x\n", "line", "not YAML"),
    ("settings: [{{id: a}}, {{id: a}}]\nlogs: [{LOG}]\n", "settings", "two settings have the id 'a'"),
])
def test_bad_spec_is_one_line_exit_2_and_nothing_written(body, where, what, logs, tmp_path, capsys):
    """Every mistake in a spec: exit 2, one `error: <spec>:<entry>: ...` line, no --out folder, no Ray started."""
    good, _ = logs
    spec = tmp_path / "bad.yaml"
    spec.write_text(body.format(LOG=good[0]))
    out = tmp_path / "never"
    code, stdout, err = _slam(["batch", spec, "--out", out, "--quiet"], capsys)
    assert code == 2, err
    err = err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"error: {spec}:{where}") and what in err[0], err
    assert not out.exists()


def test_nothing_imports_ray_unless_a_batch_runs():
    """Importing the CLI (every command module, the batch's too) and the batch modules does not import Ray."""
    code = ("import sys; import slam.cli, slam.cli.batch_cmd, slam.cli.batch_task, slam.batch.spec, "
            "evaluation.batch_report; assert 'ray' not in sys.modules, 'ray imported'")
    r = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr


def test_loops_parallel_gives_the_rows_of_loops(ray_cluster, logs, tmp_path, capsys):
    """`slam loops LOG --sweep ... --parallel` (each setting a Ray task) writes the rows of `slam loops` (the
    replay times aside)."""
    good, _ = logs
    rows = {}
    for mode in ([], ["--parallel"]):
        out = tmp_path / ("par" if mode else "seq")
        code, _, err = _slam(["loops", good[0], "--sweep", "exclude_recent_keyframes=5:15:3", "--out", out, "--quiet",
                              *mode], capsys)
        assert code == 0, err
        rows[bool(mode)] = [{k: v for k, v in r.items() if k != "time_s"}
                            for r in json.loads((out / "loops.json").read_text())["rows"]]
    assert rows[True] == rows[False] and len(rows[False]) == 3


@pytest.mark.slow
def test_ctrl_c_leaves_complete_run_folders_only(tmp_path):
    """SIGINT to `slam batch` (its own local Ray) while the first runs are under way: exit 130 with 'error:
    interrupted', every run folder complete (batch.json beside its outputs), no staging folder, no Ray process
    left; the same command then resumes: only the unfinished runs are run."""
    spec = tmp_path / "intel.yaml"
    spec.write_text(f"config: {{mapping.enabled: false}}\nlogs: [{DATA / 'intel.clf.bz2'}]\n"
                    "settings: [{max_scans: 400}, {max_scans: 1200}, {max_scans: 1600}]\n")
    out = tmp_path / "out"
    ray_tmp = tempfile.mkdtemp(prefix="rc", dir="/tmp")
    env = dict(os.environ, PYTHONPATH=str(REPO), RAY_TMPDIR=ray_tmp, RAY_USAGE_STATS_ENABLED="0")
    proc = subprocess.Popen([sys.executable, "-m", "slam", "batch", str(spec), "--out", str(out)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env, cwd=tmp_path,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        seen = []
        while not (line := proc.stderr.readline()).startswith("ray:"):  # printed once Ray is up
            seen.append(line)
            assert line, "".join(seen)
        assert _ray_processes(ray_tmp), "the batch did not start its Ray under RAY_TMPDIR"
        # Interrupt as soon as the first (400-scan) run has finished, while the longer ones run: a fixed
        # sleep depends on the machine's speed (on a fast one all three had finished).
        deadline = time.monotonic() + 300.0
        while not list(out.glob("runs/intel/*/batch.json")):
            assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read() if proc.poll() is not None else "timeout"
            time.sleep(0.05)
        assert proc.poll() is None
        proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode in (130, -signal.SIGINT), stderr
    assert stderr.strip().splitlines()[-1] == "error: interrupted"
    assert "results:" not in stdout
    assert _no_ray_left(ray_tmp) == []
    assert list(out.rglob(".*")) == []  # no staging or temporary folder (nothing at all if out does not exist)
    finished = sorted(p.parent.name for p in out.glob("runs/intel/*/batch.json"))
    folders = sorted(p.name for p in out.glob("runs/intel/*"))
    assert folders == finished and len(finished) < 3
    for name in finished:
        assert (out / "runs" / "intel" / name / "trajectory.tum").stat().st_size > 0
    # Resume: the finished runs are not run again.
    r = subprocess.run([sys.executable, "-m", "slam", "batch", str(spec), "--out", str(out), "--quiet"],
                       capture_output=True, text=True, env=env, cwd=tmp_path, timeout=600)
    assert r.returncode == 0, r.stderr
    doc = json.loads((out / "results.json").read_text())
    assert doc["resumed"] == len(finished) and doc["tasks_run"] == 3 - len(finished)
    assert _no_ray_left(ray_tmp) == []


def test_example_specs_name_every_log_and_its_reference():
    """examples/kummerle.yaml: the bundled Intel log and the three benchmark logs with relations, each with its
    relations file (Cartographer's figure is known for each); examples/devset.yaml: those logs, the Killian bag
    and every log of ../shared/data/slam2d_devset, the GMapping-corrected ones scan-only, and the three logs with
    relations once more without their wheels. Needs ../shared/data
    (a missing log fails the spec)."""
    from evaluation.published import recognise_dataset
    from slam.batch.spec import load_spec
    from slam.cli.run_eval import log_stem

    k = load_spec(REPO / "examples" / "kummerle.yaml", log_stem)
    refs = {e.name: e.relations or e.found_relations for e in k.logs}
    assert list(refs) == ["intel-bundled", "intel", "mit-csail", "fr-clinic"] and [s.id for s in k.settings] == ["default"]
    assert [recognise_dataset(r) for r in refs.values()] == ["intel", "intel", "mit-csail", "fr-clinic"]
    d = load_spec(REPO / "examples" / "devset.yaml", log_stem)
    devset = REPO.parent / "shared" / "data" / "slam2d_devset"
    logs = {p.resolve() for p in devset.rglob("*") if p.name.endswith((".clf", ".clf.gz", ".log.gz"))}
    assert logs and logs <= {e.path for e in d.logs}
    assert {e.path for e in k.logs if e.name != "intel-bundled"} <= {e.path for e in d.logs}
    for e in d.logs:
        scan_only = e.path.parent.name == "gmapping-corrected" or e.name.endswith("-scan-only")
        assert e.values == ({"odometry.use_wheel_odometry": False, "odometry.wheel_edges": False} if scan_only else {})
    # the three logs with relations also run without their wheels, each with its relations
    blind = {e.name: e.relations or e.found_relations for e in d.logs if e.name.endswith("-scan-only")}
    assert [recognise_dataset(r) for r in blind.values()] == ["intel", "mit-csail", "fr-clinic"]
    assert {e.name: e.relations for e in d.logs}["killian"].name == "mit-killian.relations"


def _die_on(i: int, bad: int) -> int:
    """A task body: returns *i*, except that for *bad* its worker process dies (as under the OOM killer)."""
    if i == bad:
        os._exit(3)
    return i


def _raise_on(i: int, bad: int) -> int:
    from core.errors import ConfigError

    if i == bad:
        raise ConfigError(f"item {i} is bad")
    return i


def test_executor_reports_a_dead_worker_and_reraises_a_task_error(ray_cluster):
    """A task whose worker dies is a TaskFailure in its place and the others' results stand (in order); with
    failures="raise" the task's own exception comes back here, as the sequential call would raise it."""
    import cloudpickle

    from core.errors import ConfigError
    from slam.batch.executor import RayExecutor, TaskFailure

    cloudpickle.register_pickle_by_value(sys.modules[__name__])  # the workers cannot import tests/
    try:
        with RayExecutor() as ex:
            done = []
            res = ex.map(_die_on, (), [(i, 2) for i in range(4)], lambda i, r: done.append(i))
            assert res[:2] == [0, 1] and res[3] == 3 and isinstance(res[2], TaskFailure)
            assert "\n" not in res[2].message and res[2].message and sorted(done) == [0, 1, 2, 3]
            assert ex.map(_raise_on, (), [(0, 9), (1, 9)], failures="raise") == [0, 1]
            with pytest.raises(ConfigError, match="item 1 is bad"):
                ex.map(_raise_on, (), [(0, 1), (1, 1)], failures="raise")
            assert ex.submitted == 8
        assert ray_cluster.is_initialized()  # the executor leaves a Ray it did not start running
    finally:
        cloudpickle.unregister_pickle_by_value(sys.modules[__name__])


@pytest.mark.parametrize("address, what", [("127.0.0.1:1", "no Ray cluster answers there"),
                                           ("nonsense", "expected auto, HOST:PORT")])
def test_unreachable_address_is_one_line_exit_2(address, what, logs, tmp_path, capsys):
    """--address where no cluster listens: one error line within seconds (Ray would retry for minutes and then
    exit), exit 2, nothing written."""
    good, _ = logs
    out = tmp_path / "never"
    code, _, err = _slam(["batch", good[0], "--out", out, "--address", address, "--quiet"], capsys)
    assert code == 2
    err = err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"error: --address {address}: ") and what in err[0]
    assert not out.exists()
