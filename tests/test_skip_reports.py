"""What damaged logs are reported as: a corrupt bag chunk names the chunk and the reason (also in skip mode,
once for the chunk), skipped scans are counted apart from skipped records, a log whose every scan was
skipped names the file and why, `slam info` reads what it summarises, and `eval report` on a folder with
none of a run's files is an error."""

from __future__ import annotations

import json

import pytest

from core.errors import LogFormatError
from slam.logs import SkipLog, open_log
from tests.cli_helpers import slam as _slam
from tests.test_logs_carmen import flaser, odom_line, write_log
from tests.test_logs_mcap import write_basic_log
from tests.test_logs_rosbag1 import write_bag
from tests.test_logs_skip import rewrite_mcap

pytestmark = pytest.mark.xdist_group("pipeline")


def _flipped_bag(tmp_path, compression):
    """The issue's case: a bag of 200 scans in ~8 kB chunks with 100 bytes flipped at 10 % of the file;
    returns the bag, the position of the damaged chunk, and its index entries (time, topic)."""
    from rosbags.rosbag1 import Reader

    src = tmp_path / "a.bag"
    write_bag(src, n=200, compression=compression, chunk_threshold=8000)
    data = bytearray(src.read_bytes())
    k = len(data) // 10
    data[k:k + 100] = bytes(b ^ 0xFF for b in data[k:k + 100])
    bad = tmp_path / f"flip_{compression}.bag"
    bad.write_bytes(bytes(data))
    with Reader(src) as r:
        infos = list(r.chunk_infos)
        pos = max(c.pos for c in infos if c.pos <= k)
        number = [c.pos for c in infos].index(pos) + 1
        entries = [(e.time, c.topic) for c in r.connections for e in r.indexes[c.id] if e.chunk_pos == pos]
    return bad, pos, number, entries


@pytest.mark.parametrize("compression", ["bz2", "lz4"])
def test_a_corrupt_bag_chunk_is_named_with_its_reason(tmp_path, compression):
    """Stop mode: the error names the damaged chunk (its number and byte offset) and a non-empty reason; an
    lz4 chunk's RuntimeError is such an error too, not a traceback."""
    bad, pos, number, _ = _flipped_bag(tmp_path, compression)
    with pytest.raises(LogFormatError) as ei:
        list(open_log(bad).frames())
    assert ei.value.where == f"chunk {number} at byte offset {pos}", ei.value
    reason = ei.value.what.split("corrupt or truncated bag chunk", 1)[1]
    assert len(reason.strip(" :()")) > 3, ei.value.what


def test_skip_mode_reports_the_chunk_once_with_what_it_held(tmp_path):
    """Skip mode: one error for the damaged chunk (not one per message, and not '/odom message 0'), counting
    its records and, apart, its scans (the bag's own index says what it held)."""
    bad, pos, number, entries = _flipped_bag(tmp_path, "bz2")
    log = SkipLog()
    frames = list(open_log(bad).frames(on_skip=log))
    chunk_errors = [e for e in log.errors if e.where == f"chunk {number} at byte offset {pos}"]
    assert len(chunk_errors) == 1
    e = chunk_errors[0]
    scans = sum(t == "/scan" for _, t in entries)
    assert (e.records, e.scans) == (len(entries), scans) and scans > 0
    assert log.scans() == (200 - len(frames), True)
    assert log.records() == sum(err.records for err in log.errors) >= len(entries)


def test_run_summary_counts_skipped_scans_apart_from_records(tmp_path, capsys):
    """A CARMEN log with a bad ODOM line and a bad FLASER line, run with --on-error skip: skipped_records 2,
    skipped_scans 1, and the warning says both."""
    lines = [flaser([1.0 + 0.01 * (k % 7)] * 90, robot=(0.02 * k, 0.0, 0.0), stamp=1.0 + 0.1 * k) for k in range(40)]
    lines.insert(10, odom_line(stamp=1.95).replace(" 0.0 0.0 0.0 ", " x 0.0 0.0 ", 1))
    lines[20] = lines[20][: len(lines[20]) // 2]
    p = write_log(tmp_path / "two_bad.clf", lines)
    out = tmp_path / "run"
    code, _, err = _slam(["run", p, "--out", out, "--quiet", "--map", "none", "--on-error", "skip"], capsys)
    assert code == 0, err
    s = json.loads((out / "summary.json").read_text())
    assert (s["skipped_records"], s["skipped_scans"], s["skipped_scans_exact"]) == (2, 1, True)
    assert s["scans"] == 39 and "2 corrupt record(s) (1 scan)" in err


def test_a_log_whose_every_scan_was_skipped_names_the_file_and_the_cause(tmp_path, capsys):
    """A one-chunk MCAP whose chunk is damaged, run with --on-error skip: exit 2 with one line naming the file
    and the first skipped record, instead of 'the log yielded no scans'."""
    src = write_basic_log(tmp_path / "one.mcap", n=20, chunk_size=1 << 20)
    data = bytearray(src.read_bytes())
    mid = len(data) // 2
    data[mid:mid + 64] = bytes(64)
    bad = tmp_path / "one_bad.mcap"
    bad.write_bytes(bytes(data))
    code, _, err = _slam(["run", bad, "--out", tmp_path / "run", "--quiet", "--map", "none", "--on-error", "skip"],
                         capsys)
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and lines[0].startswith(f"error: {bad}") and "byte offset" in lines[0]
    assert not (tmp_path / "run").exists()


def test_info_reads_what_it_summarises(tmp_path, capsys):
    """An MCAP whose /odom message 5 cannot be decoded: `slam info` (which reports 'odometry: yes') reads the
    odometry too and fails naming that message, as a run would, instead of calling the log fine."""
    src = write_basic_log(tmp_path / "a.mcap", n=30)
    bad = rewrite_mcap(src, tmp_path / "odom_bad.mcap", "/odom", 5)
    code, out, err = _slam(["info", src], capsys)
    assert code == 0 and "odometry: yes" in out
    code, out, err = _slam(["info", bad], capsys)
    assert code == 2 and err.strip().startswith(f"error: {bad}:/odom message 5: "), err


def test_report_on_a_folder_without_any_run_file_is_an_error(tmp_path, capsys):
    """eval report on an empty folder: exit 2 naming it, and no report.html / metrics.json written there."""
    d = tmp_path / "empty"
    d.mkdir()
    code, out, err = _slam(["eval", "report", d], capsys)
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and str(d) in lines[0] and list(d.iterdir()) == []
