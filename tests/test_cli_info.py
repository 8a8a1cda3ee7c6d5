"""``slam info``: the acceptance scan counts, and one-line errors with exit status 2 for bad input."""

from __future__ import annotations

import bz2
import gzip
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from slam.cli import main
from tests.conftest import DATA, REPO, shared_path
from tests.test_logs_carmen import flaser, odom_line, robotlaser


def run_info(args: list[str], capsys) -> tuple[int, str, str]:
    """Run ``slam info ARGS`` in-process; return (exit status, stdout, stderr)."""
    try:
        main(["info", *args])
        code = 0
    except SystemExit as exc:
        code = int(exc.code or 0)
    out = capsys.readouterr()
    return code, out.out, out.err


def scans_of(stdout: str) -> int:
    lines = [ln for ln in stdout.splitlines() if re.fullmatch(r"scans: \d+", ln)]
    assert len(lines) == 1, stdout
    return int(lines[0].split()[1])


# ----------------------------------------------------------------------------- acceptance counts

def test_intel_scans(capsys):
    """`slam info data/intel.clf.bz2` prints the line `scans: 13631` (SOURCE.md count)."""
    code, out, err = run_info([str(DATA / "intel.clf.bz2")], capsys)
    assert code == 0 and err == ""
    assert scans_of(out) == 13631
    assert "format: carmen" in out and "beams_per_scan: 180" in out and "odometry: yes" in out


def test_csail_scans(capsys):
    """CSAIL: `scans: 1988`, 361 beams, odometry from the laser lines."""
    code, out, _ = run_info([str(DATA / "mit-csail.clf.bz2")], capsys)
    assert code == 0 and scans_of(out) == 1988
    assert "beams_per_scan: 361" in out and "odometry: yes" in out


def test_fr_clinic_scans(capsys):
    """Freiburg hospital ROBOTLASER1 log: `scans: 6917`."""
    code, out, _ = run_info([str(shared_path("slam2d_kummerle_benchmark", "fr-clinic_robotlaser.clf.bz2"))], capsys)
    assert code == 0 and scans_of(out) == 6917
    assert "sensor_topic: ROBOTLASER1" in out


def test_kitti_scans(capsys):
    """The KITTI sample sequence: `scans: 10`, 3D, ground truth present."""
    code, out, _ = run_info([str(shared_path("kitti_odometry_00_sample", "sequences", "00"))], capsys)
    assert code == 0 and scans_of(out) == 10
    assert "format: kitti" in out and "dimension: 3D" in out and "ground_truth: yes" in out


def test_console_script_end_to_end():
    """The installed `slam` entry point (a real subprocess) prints `scans: 1988` for CSAIL and exits 0."""
    exe = Path(sys.executable).with_name("slam")
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "slam"]
    res = subprocess.run([*cmd, "info", str(DATA / "mit-csail.clf.bz2")], capture_output=True, text=True,
                         cwd=REPO, timeout=120, env={**os.environ, "PYTHONPATH": str(REPO)})
    assert res.returncode == 0, res.stderr
    assert "scans: 1988" in res.stdout.splitlines()


# ----------------------------------------------------------------------------- bad input

def _bad_files(d: Path) -> dict[str, tuple[Path, list[str], str]]:
    """name → (path, extra CLI args, text the one error line must contain)."""
    good = [flaser([1.0, 2.0, 3.0], stamp=float(k)) for k in range(300)]
    body = ("\n".join(good) + "\n").encode()
    files: dict[str, tuple[Path, list[str], str]] = {}

    def add(name: str, data: bytes, args: list[str], what: str) -> None:
        p = d / name
        p.write_bytes(data)
        files[name] = (p, args, what)

    bz = bz2.compress(body)
    gz = gzip.compress(body)
    add("truncated.clf.bz2", bz[: len(bz) // 2], [], "truncated bz2 stream")
    corrupt = bytearray(bz)
    corrupt[len(corrupt) // 2] ^= 0xFF
    add("corrupt.clf.bz2", bytes(corrupt), [], "line ")
    add("truncated.clf.gz", gz[: len(gz) // 2], [], "truncated gzip stream")
    add("garbage.clf", body + b"\x7fELF\x02\x01\x01 garbage\n", [], "line 301: garbage line")
    add("fields.clf", (flaser([1.0, 2.0]) + " extra\n").encode(), [], "line 1: FLASER with num_readings=2 needs 13 fields")
    add("text.clf", flaser([1.0, 2.0]).replace(" 2.0 ", " two ").encode(), [], "line 1: non-numeric")
    add("nan.clf", flaser([1.0, float("nan")]).encode(), [], "range 2 is nan")
    add("negative.clf", flaser([1.0, -0.5]).encode(), [], "range 2 is -0.5")
    add("empty_scan.log", b"FLASER 0 0 0 0 0 0 0 5.0 host 0.1\n", [], "empty FLASER scan")
    add("empty.clf", b"", [], "no scans")
    add("odom_only.clf", (odom_line() + "\n").encode(), [], "no scans")
    add("topic.clf", body, ["--topic", "/scan"], "unknown CARMEN topic")
    add("absent_topic.clf", (robotlaser([1.0, 2.0]) + "\n").encode(), ["--topic", "RLASER"], "no RLASER scans")
    add("kitti_bad.bin", b"\x00" * 40, [], "not a multiple of 16")
    return files


BAD_NAMES = ["truncated.clf.bz2", "corrupt.clf.bz2", "truncated.clf.gz", "garbage.clf", "fields.clf", "text.clf",
             "nan.clf", "negative.clf", "empty_scan.log", "empty.clf", "odom_only.clf", "topic.clf",
             "absent_topic.clf", "kitti_bad.bin"]


@pytest.mark.parametrize("name", BAD_NAMES)
def test_bad_input_one_line_exit_2(tmp_path, capsys, name):
    """Each bad input: exit status 2, nothing on stdout, exactly one stderr line `error: <file>…`
    naming the file (and the line where there is one)."""
    path, args, what = _bad_files(tmp_path)[name]
    code, out, err = run_info([str(path), *args], capsys)
    assert code == 2
    assert out == ""
    lines = err.splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith(f"error: {path}")
    assert what in lines[0]


def test_missing_file(tmp_path, capsys):
    """A path that does not exist: exit 2, one line naming it."""
    code, _, err = run_info([str(tmp_path / "nope.clf")], capsys)
    assert code == 2 and err.count("\n") == 1 and "nope.clf" in err


def test_bad_input_subprocess(tmp_path):
    """Through a real process: a truncated bz2 log exits 2 with one stderr line and no traceback."""
    path, _, what = _bad_files(tmp_path)["truncated.clf.bz2"]
    res = subprocess.run([sys.executable, "-m", "slam", "info", str(path)], capture_output=True, text=True,
                         cwd=REPO, timeout=120, env={**os.environ, "PYTHONPATH": str(REPO)})
    assert res.returncode == 2
    assert len(res.stderr.splitlines()) == 1 and what in res.stderr and "Traceback" not in res.stderr
