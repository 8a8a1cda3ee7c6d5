"""Output paths: checked before any work (an existing file or folder of the wrong kind, a path under a file,
a folder nothing can be written in), a full disk mid-write is one error line with nothing left behind, and a
rerun replaces its whole output folder (never merges into it, never wipes a folder it did not write)."""

from __future__ import annotations

import errno
import json
import os
import tempfile
from pathlib import Path

import pytest

from core.atomic import atomic_directory, atomic_open, check_output_dir, check_output_file
from core.errors import OutputError
from tests.cli_helpers import corridor_log
from tests.cli_helpers import one_error_line as _one_error
from tests.cli_helpers import slam as _slam

pytestmark = pytest.mark.xdist_group("pipeline")
FAST = ["--quiet", "--map", "none"]


def _hidden(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.startswith("."))


@pytest.fixture
def unwritable(tmp_path):
    """A folder in which nothing can be created: mode 0555, or, for root (who ignores modes), /sys."""
    d = tmp_path / "ro"
    d.mkdir()
    d.chmod(0o555)
    if os.geteuid() == 0:
        d = Path("/sys/kernel")
    with pytest.raises(OSError):  # the fixture must really be unwritable, or the tests prove nothing
        tempfile.mkdtemp(dir=d)
    yield d
    (tmp_path / "ro").chmod(0o755)


@pytest.fixture(scope="module")
def sim_log(tmp_path_factory):
    d = tmp_path_factory.mktemp("sim")
    corridor_log(d / "c.mcap", 80, seed=5)
    return d / "c.mcap"


# ----------------------------------------------------------------------------- before the work


@pytest.mark.parametrize("case", ["existing file", "under a file", "unwritable"])
def test_run_checks_its_output_folder_before_reading_the_log(tmp_path, sim_log, unwritable, capsys, case):
    """slam run --out EXISTING_FILE, FILE/sub, or a folder nothing can be created in: exit 2, one line naming
    the path, before the run starts (no 'log:' line), nothing created."""
    f = tmp_path / "file.txt"
    f.write_text("keep")
    out = {"existing file": f, "under a file": f / "sub", "unwritable": unwritable / "run"}[case]
    before = sorted(p.name for p in tmp_path.iterdir())
    code, stdout, err = _slam(["run", sim_log, "--out", out, *FAST], capsys)
    _one_error(code, err, out)
    assert "log:" not in stdout and sorted(p.name for p in tmp_path.iterdir()) == before
    assert f.read_text() == "keep"


def test_file_outputs_are_checked_before_the_work(tmp_path, sim_log, unwritable, capsys):
    """solve --out <existing folder>, eval ape --json <unwritable>, simulate --out <unwritable>, simulate --out
    <a device>: exit 2 with one line naming the path and nothing printed on stdout (no work done)."""
    g = tmp_path / "g.g2o"
    g.write_text("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n")
    t = tmp_path / "t.tum"
    t.write_text("0 0 0 0 0 0 0 1\n1 1 0 0 0 0 0 1\n")
    (tmp_path / "adir").mkdir()
    for args, bad in (
        (["solve", g, "--out", tmp_path / "adir"], tmp_path / "adir"),
        (["eval", "ape", t, t, "--json", unwritable / "a.json"], unwritable / "a.json"),
        (["simulate", "corridor", "--scans", "5", "--out", unwritable / "s.mcap"], unwritable / "s.mcap"),
        (["simulate", "corridor", "--scans", "5", "--out", "/dev/full"], "/dev/full"),
    ):
        code, stdout, err = _slam(args, capsys)
        _one_error(code, err, bad)
        assert stdout == ""
    assert sorted(p.name for p in tmp_path.iterdir()) == ["adir", "g.g2o", "ro", "t.tum"]
    assert list((tmp_path / "adir").iterdir()) == []


def test_check_helpers_accept_what_can_be_written(tmp_path):
    """A new name in a writable folder (also below folders still to create) passes both checks."""
    check_output_file(tmp_path / "a" / "b" / "x.json")
    check_output_dir(tmp_path / "a" / "run", ("summary.json",))
    assert list(tmp_path.iterdir()) == []  # the check leaves nothing behind
    with pytest.raises(OutputError, match="is a folder"):
        check_output_file(tmp_path)


# ----------------------------------------------------------------------------- during the work


def test_a_full_disk_while_writing_is_one_line_and_leaves_nothing(tmp_path, sim_log, capsys, monkeypatch):
    """ENOSPC in the middle of writing a run's outputs: exit 2, 'error: OUT: cannot write: No space left on
    device', no output folder and no temporary beside it."""
    import slam.pipeline.outputs as outputs

    def full(path, *a, **k):
        with open(path, "wb") as fh:
            fh.write(b"half")
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(outputs, "_write_mcap", full)
    out = tmp_path / "run"
    code, _, err = _slam(["run", sim_log, "--out", out, *FAST], capsys)
    _one_error(code, err, out, "No space left on device")
    assert not out.exists() and _hidden(tmp_path) == []


def test_atomic_open_turns_a_write_failure_into_an_output_error(tmp_path):
    """A failing write inside atomic_open is an OutputError naming the target; the target is untouched."""
    target = tmp_path / "x.json"
    target.write_text("old")
    with pytest.raises(OutputError) as ei:
        with atomic_open(target) as fh:
            fh.write("new")
            raise OSError(errno.EDQUOT, os.strerror(errno.EDQUOT))
    assert ei.value.path == str(target) and target.read_text() == "old" and _hidden(tmp_path) == []


# ----------------------------------------------------------------------------- a rerun replaces its folder


@pytest.mark.parametrize("exchange", [True, False])
def test_a_rerun_replaces_the_whole_folder(tmp_path, monkeypatch, exchange):
    """The second output into the same folder replaces the first entirely: no file of the first survives
    (by the atomic exchange of renameat2, and by two renames where the system lacks it)."""
    import core.atomic as atomic

    if not exchange:
        monkeypatch.setattr(atomic, "_exchange", lambda a, b: False)
    out = tmp_path / "run"
    with atomic_directory(out, ("summary.json",)) as d:
        for name in ("summary.json", "map.png", "report.html"):
            (d / name).write_text("first")
    with atomic_directory(out, ("summary.json",)) as d:
        (d / "summary.json").write_text("second")
    assert {p.name: p.read_text() for p in out.iterdir()} == {"summary.json": "second"}
    assert [p.name for p in tmp_path.iterdir()] == ["run"]


def test_a_folder_this_command_did_not_write_is_never_replaced(tmp_path):
    """An existing non-empty folder without the marker files (e.g. --out ~) is refused, before and at the
    move, and left as it was."""
    home = tmp_path / "home"
    home.mkdir()
    (home / "thesis.tex").write_text("precious")
    with pytest.raises(OutputError, match="summary.json"):
        check_output_dir(home, ("summary.json",))
    with pytest.raises(OutputError):
        with atomic_directory(home, ("summary.json",)) as d:
            (d / "summary.json").write_text("{}")
    assert [p.name for p in home.iterdir()] == ["thesis.tex"] and _hidden(tmp_path) == []


def test_slam_run_rerun_leaves_only_the_new_runs_files(tmp_path, sim_log, capsys):
    """The issue's case: a run with --eval and a map, then one with --map none --max-scans 50 into the same
    folder: report.html, metrics.json and map.* of the first run are gone and summary.json says 50 scans."""
    out = tmp_path / "X"
    code, _, err = _slam(["run", sim_log, "--out", out, "--eval", "--quiet"], capsys)
    assert code == 0, err
    first = {p.name for p in out.iterdir()}
    assert {"report.html", "metrics.json", "map.npz"} <= first
    code, _, err = _slam(["run", sim_log, "--out", out, "--max-scans", "50", *FAST], capsys)
    assert code == 0, err
    second = {p.name for p in out.iterdir()}
    assert not second & {"report.html", "metrics.json", "map.npz", "map.png", "map.pgm", "map.yaml"}
    assert json.loads((out / "summary.json").read_text())["scans"] == 50
    assert _hidden(tmp_path) == []


def test_batch_checks_its_folder_before_starting_ray(tmp_path, sim_log, unwritable, capsys):
    """slam batch --out <a folder nothing can be created in>: one error line before any run (no 'batch:' or
    'ray:' progress line: it used to start Ray, run every log and fail only writing results.csv)."""
    code, _, err = _slam(["batch", sim_log, "--out", unwritable / "batch"], capsys)
    _one_error(code, err, unwritable / "batch")
