"""Every subcommand × {missing file, directory instead of file, unreadable file, unwritable output, bad option
value}: exit 2, one ``error:`` line on stderr (no traceback), and no output written (nor a hidden temporary)."""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import pytest

from slam.cli import main
from slam.logs.simulated import map_paths
from tests.cli_helpers import corridor_log

pytestmark = pytest.mark.xdist_group("pipeline")

KINDS = ("missing", "directory", "unreadable", "unwritable", "bad option")


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """Good inputs of every kind: a simulated log (with its map) and the folder of a short run of it."""
    from slam.cli import main as slam

    d = tmp_path_factory.mktemp("inputs")
    log = d / "c.mcap"
    sim = corridor_log(log, 60, seed=2)
    with pytest.raises(SystemExit) as ei:
        slam(["run", str(log), "--out", str(d / "run"), "--quiet", "--map", "logodds"])
    assert (ei.value.code or 0) == 0
    run = d / "run"
    rel = d / "c.relations"
    rel.write_text("".join(f"{sim.stamps[k]!r} {sim.stamps[k + 5]!r} 0.1 0 0 0 0 0\n" for k in range(0, 50, 5)))
    cfg = d / "config.yaml"
    cfg.write_text("max_scans: 20\n")
    spec = d / "batch.yaml"
    spec.write_text(f"logs: [{log}]\n")
    return {"spec": spec, "log": log, "gt_map": map_paths(log)[0], "run": run, "tum": run / "trajectory.tum",
            "g2o": run / "graph.g2o", "npz": run / "map.npz", "stamps": run / "node_stamps.txt", "rel": rel,
            "cfg": cfg}


@pytest.fixture(scope="module")
def unreadable_target(tmp_path_factory):
    """A path that exists but cannot be read: a mode-000 file, or, for root (who ignores modes), /proc/1/mem."""
    f = tmp_path_factory.mktemp("locked") / "locked"
    f.write_text("secret")
    f.chmod(0)
    for cand in (f, Path("/proc/1/mem")):
        try:
            with open(cand, "rb") as fh:
                fh.read(16)
        except OSError:
            return cand
    pytest.fail("no unreadable file available on this machine")


@pytest.fixture(scope="module")
def unwritable_dir(tmp_path_factory):
    """A folder nothing can be created in: mode 0555, or, for root, /sys/kernel."""
    d = tmp_path_factory.mktemp("ro")
    d.chmod(0o555)
    for cand in (d, Path("/sys/kernel")):
        try:
            os.rmdir(tempfile.mkdtemp(dir=cand))
        except OSError:
            return cand
    pytest.fail("no unwritable folder available on this machine")


# Each subcommand: its arguments with the input that the case replaces ({IN} with its suffix), where its
# output goes ({OUT}), and an option with a bad value.
COMMANDS = {
    "info": (["{IN:log}"], None, ["--topic", ""]),
    "demo": (["--log", "{IN:log}", "--relations", "{rel}", "--out", "{OUT:dir}", "--quiet"], "dir", ["--max-scans", "0"]),
    "eval ape": (["{IN:tum}", "{tum}", "--json", "{OUT:file}"], "file", ["--max-diff", "nan"]),
    "eval rpe": (["{tum}", "{IN:tum}", "--json", "{OUT:file}"], "file", ["--delta", "-1"]),
    "eval relations": (["{tum}", "{IN:rel}", "--json", "{OUT:file}"], "file", ["--stamp-tol", "inf"]),
    "eval loops": (["{IN:g2o}", "--gt", "{tum}", "--node-stamps", "{stamps}", "--json", "{OUT:file}"], "file",
                   ["--min-separation", "0"]),
    "eval crosscheck": (["{g2o}", "{IN:g2o}", "{g2o}", "--json", "{OUT:file}"], "file", ["--names"]),
    "eval report": (["{run}", "--gt", "{IN:tum}", "--out", "{OUT:dir}"], "dir", ["--gt-map"]),
    "eval map": (["{IN:npz}", "{gt_map}", "--plot", "{OUT:file}"], "file", ["--plot"]),
    "simulate": (["{IN:yaml}", "--scans", "5", "--out", "{OUT:file}"], "file", ["--range-noise", "-0.1"]),
    "solve": (["{IN:g2o}", "--out", "{OUT:file}"], "file", ["--backend", "ceres"]),
    "map": (["{log}", "--poses", "{IN:tum}", "--out", "{OUT:dir}"], "dir", ["--resolution", "0"]),
    "run": (["{log}", "--relations", "{IN:rel}", "--out", "{OUT:dir}", "--quiet"], "dir", ["--map", "foo"]),
    "loops": (["{IN:log}", "--out", "{OUT:dir}", "--quiet"], "dir", ["--sweep", "nonsense"]),
    "batch": (["{IN:spec}", "--out", "{OUT:dir}", "--quiet"], "dir", ["--cpus-per-run", "0"]),
}
SUFFIX = {"log": ".mcap", "tum": ".tum", "rel": ".relations", "g2o": ".g2o", "npz": ".npz", "yaml": ".yaml",
          "spec": ".yaml"}


def _args(cmd, kind, files, tmp_path, unreadable_target, unwritable_dir):
    """The command line of one cell of the matrix, and the output path it must not create."""
    argv, out_kind, bad = COMMANDS[cmd]
    good_out = tmp_path / ("out" if out_kind == "dir" else "out.json")
    out = unwritable_dir / good_out.name if kind == "unwritable" else good_out
    args = []
    for a in argv:
        if a.startswith("{IN:"):
            key = a[4:-1]
            src = files["gt_map"] if key == "yaml" else files[key]
            name = tmp_path / f"input{SUFFIX[key]}"
            if kind == "missing":
                pass
            elif kind == "directory":
                name.mkdir()
            elif kind == "unreadable":
                name.symlink_to(unreadable_target)
            else:
                shutil.copy(src, name) if src.is_file() else None
                name = src if not src.is_file() else name
            args.append(str(name))
        elif a.startswith("{OUT:"):
            args.append(str(out))
        else:
            args.append(a.format(**files))
    if kind == "bad option":
        args += bad
    return cmd.split() + args, out


CELLS = [(c, k) for c in COMMANDS for k in KINDS if not (k == "unwritable" and COMMANDS[c][1] is None)]


@pytest.mark.parametrize("cmd,kind", CELLS, ids=[f"{c}-{k}" for c, k in CELLS])
def test_bad_input_is_one_line_exit_2_and_writes_nothing(cmd, kind, files, tmp_path, unreadable_target,
                                                        unwritable_dir, capsys):
    argv, out = _args(cmd, kind, files, tmp_path, unreadable_target, unwritable_dir)
    before = sorted(p.name for p in tmp_path.iterdir())
    with pytest.raises(SystemExit) as ei:
        main(argv)
    cap = capsys.readouterr()
    lines = cap.err.strip().splitlines()
    assert ei.value.code == 2, (argv, cap.err)
    assert len(lines) == 1 and lines[0].startswith("error: ") and "Traceback" not in cap.err, (argv, cap.err)
    assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == before


@pytest.mark.parametrize("option,value", [("--max-scans", "0"), ("--max-scans", "-3"), ("--backend", "foo"),
                                          ("--map", "foo"), ("--odometry", "foo"), ("--on-error", "ignore")])
def test_bad_run_option_names_the_option_before_any_work(option, value, files, tmp_path, capsys):
    """The issue's cases (a pydantic ValidationError traceback before): one line naming the option, exit 2,
    and the run never starts."""
    with pytest.raises(SystemExit) as ei:
        main(["run", str(files["log"]), "--out", str(tmp_path / "run"), option, value])
    cap = capsys.readouterr()
    lines = cap.err.strip().splitlines()
    assert ei.value.code == 2 and len(lines) == 1 and f"'{option}'" in lines[0] and "log:" not in cap.out
    assert not (tmp_path / "run").exists()
