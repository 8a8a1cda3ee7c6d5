"""Readers skipping corrupt records (``frames(on_skip=...)``): what is left out is exactly the damaged
record, everything else is read as without damage, and each skip is reported with its position."""

from __future__ import annotations

import bz2
import itertools
from pathlib import Path

import numpy as np
import pytest

from core.errors import LogFormatError
from slam.logs import SkipLog, open_log
from slam.logs.carmen import CarmenReader
from slam.logs.ros_msgs import stamp_to_ns
from tests.conftest import DATA
from tests.test_logs_carmen import synthetic_log, write_log
from tests.test_logs_kitti import _write_seq
from tests.test_logs_mcap import write_basic_log
from tests.test_logs_rosbag1 import write_bag


def _stamps(frames) -> np.ndarray:
    return np.array([f.stamp for f in frames])


def rewrite_mcap(src: Path, dst: Path, topic: str, index: int) -> Path:
    """Copy an MCAP with the mcap library, cutting the serialised payload of message *index* of *topic*
    to a third (a well-formed container around a message that cannot be decoded)."""
    from mcap.reader import make_reader
    from mcap.writer import Writer

    with open(src, "rb") as fi, open(dst, "wb") as fo:
        reader = make_reader(fi)
        summary = reader.get_summary()
        w = Writer(fo)
        w.start("", "test")
        sids = {s.id: w.register_schema(s.name, s.encoding, s.data) for s in summary.schemas.values()}
        cids = {c.id: w.register_channel(c.topic, c.message_encoding, sids.get(c.schema_id, 0), c.metadata)
                for c in summary.channels.values()}
        k = 0
        for _, channel, m in reader.iter_messages(log_time_order=True):
            data = m.data
            if channel.topic == topic:
                if k == index:
                    data = data[: len(data) // 3]
                k += 1
            w.add_message(cids[channel.id], m.log_time, data, m.publish_time, m.sequence)
        w.finish()
    return dst


# ----------------------------------------------------------------------------- CARMEN


def test_carmen_bad_lines_are_skipped_one_by_one(tmp_path, rng):
    """A garbage line, a FLASER line cut short and a bad ODOM line in one block: stop mode raises at the
    first (naming its line); skip mode reports the three lines and yields every other scan unchanged."""
    lines = synthetic_log(rng, n_scans=60)
    good = write_log(tmp_path / "good.clf", lines)
    fl = [i for i, ln in enumerate(lines) if ln.startswith("FLASER")]
    od = [i for i, ln in enumerate(lines) if ln.startswith("ODOM")]
    bad = list(lines)
    bad[fl[20]] = bad[fl[20]][: len(bad[fl[20]]) // 2]  # scan 20 cut in the middle
    bad[od[40]] = "ODOM 1.0 2.0 nan-ish 0 0 0 1000.0 host 1000.0"  # not a number
    bad.insert(fl[10], "@@@ garbage \x00 line")  # before scan 10 (shifts the later lines by one)
    p = write_log(tmp_path / "bad.clf", bad)
    with pytest.raises(LogFormatError) as ei:
        list(CarmenReader(p).frames())
    assert ei.value.where == f"line {fl[10] + 1}"
    log = SkipLog()
    got = list(CarmenReader(p).frames(on_skip=log))
    want = list(CarmenReader(good).frames())
    assert [e.where for e in log.errors] == [f"line {fl[10] + 1}", f"line {fl[20] + 2}", f"line {od[40] + 2}"]
    keep = [f for k, f in enumerate(want) if k != 20]
    assert len(got) == len(keep) == 59
    np.testing.assert_array_equal(_stamps(got), _stamps(keep))
    for a, b in zip(got, keep):
        np.testing.assert_array_equal(a.ranges, b.ranges)
        np.testing.assert_array_equal(a.odom, b.odom)
    assert [f.index for f in got] == list(range(59))
    assert all(line.startswith(f"{p}:line ") for line in log.lines())


def test_carmen_skip_on_a_good_log_changes_nothing(rng, tmp_path):
    """On an undamaged log, skip mode yields the very frames of stop mode and reports nothing."""
    p = write_log(tmp_path / "g.clf.gz", synthetic_log(rng, n_scans=40), "gz")
    log = SkipLog()
    a, b = list(CarmenReader(p).frames(on_skip=log)), list(CarmenReader(p).frames())
    assert len(log) == 0 and len(a) == len(b) == 40
    np.testing.assert_array_equal(_stamps(a), _stamps(b))


def test_carmen_truncated_bz2_keeps_every_complete_scan(tmp_path):
    """The Intel log cut at 40 %: skip mode yields exactly the FLASER lines the bz2 decompressor can
    produce before the cut (counted independently), equal to the first scans of the whole log, and
    reports one 'truncated bz2' error."""
    raw = (DATA / "intel.clf.bz2").read_bytes()
    cut = raw[: int(len(raw) * 0.4)]
    p = tmp_path / "intel_cut.clf.bz2"
    p.write_bytes(cut)
    dec = bz2.BZ2Decompressor()
    text = dec.decompress(cut)  # everything a decompressor recovers (no exception: it just wants more input)
    complete = text[: text.rfind(b"\n") + 1].splitlines()
    n_expected = sum(1 for ln in complete if ln.startswith(b"FLASER "))
    log = SkipLog()
    got = list(CarmenReader(p).frames(on_skip=log))
    assert len(got) == n_expected > 4000
    assert len(log) == 1 and "truncated bz2" in log.errors[0].what
    want = list(itertools.islice(CarmenReader(DATA / "intel.clf.bz2").frames(), n_expected))
    np.testing.assert_array_equal(_stamps(got), _stamps(want))


# ----------------------------------------------------------------------------- MCAP


def test_mcap_undecodable_message_is_skipped(tmp_path):
    """One /scan message whose payload is cut: stop mode names '/scan message 7'; skip mode yields the
    other 39 scans with their stamps and odometry and reports that message."""
    src = write_basic_log(tmp_path / "a.mcap", n=40)
    p = rewrite_mcap(src, tmp_path / "bad.mcap", "/scan", 7)
    with pytest.raises(LogFormatError, match="/scan message 7"):
        list(open_log(p).frames())
    log = SkipLog()
    got = list(open_log(p).frames(on_skip=log))
    want = [f for k, f in enumerate(open_log(src).frames()) if k != 7]
    assert len(log) == 1 and log.errors[0].where == "/scan message 7"
    np.testing.assert_array_equal(_stamps(got), _stamps(want))
    for a, b in zip(got, want):
        np.testing.assert_allclose(a.odom, b.odom, atol=1e-12)


def test_mcap_corrupt_chunk_is_skipped_through_the_index(tmp_path):
    """Zeroed bytes in one chunk of a chunk-indexed MCAP: skip mode leaves out exactly the scans of that
    chunk (listed with the mcap library from the undamaged file) and reads all later chunks."""
    from mcap.data_stream import ReadDataStream
    from mcap.reader import make_reader
    from mcap.records import Chunk, Message
    from mcap.stream_reader import breakup_chunk

    src = write_basic_log(tmp_path / "a.mcap", n=400, chunk_size=8192)
    data = bytearray(src.read_bytes())
    mid = len(data) // 3
    data[mid: mid + 64] = bytes(64)
    p = tmp_path / "c.mcap"
    p.write_bytes(bytes(data))
    with open(src, "rb") as fh:
        summary = make_reader(fh).get_summary()
        hit = [c for c in summary.chunk_indexes if c.chunk_start_offset <= mid < c.chunk_start_offset + c.chunk_length]
        assert len(hit) == 1
        fh.seek(hit[0].chunk_start_offset + 9)
        records = breakup_chunk(Chunk.read(ReadDataStream(fh)))
    scan_ids = {c.id for c in summary.channels.values() if c.topic == "/scan"}
    lost = [r.log_time for r in records if isinstance(r, Message) and r.channel_id in scan_ids]
    want = [f for f in open_log(src).frames() if stamp_to_ns(f.stamp) not in lost]
    log = SkipLog()
    got = list(open_log(p).frames(on_skip=log))
    assert len(log) == 1 and log.errors[0].where == f"byte offset {hit[0].chunk_start_offset}"
    assert len(got) == 400 - len(lost) and 0 < len(lost) < 20
    assert log.scans() == (len(lost), True)  # counted from the chunk's message indexes
    np.testing.assert_array_equal(_stamps(got), _stamps(want))


def test_mcap_truncated_file_ends_with_what_was_read(tmp_path):
    """Cut in half (summary lost): skip mode yields the first scans in order, then reports the cut once."""
    src = write_basic_log(tmp_path / "a.mcap", n=300, chunk_size=8192)
    p = tmp_path / "t.mcap"
    p.write_bytes(src.read_bytes()[: src.stat().st_size // 2])
    log = SkipLog()
    got = list(open_log(p).frames(on_skip=log))
    want = list(open_log(src).frames())
    assert len(log) == 1 and "byte offset" in log.errors[0].where
    assert 100 < len(got) < 300
    np.testing.assert_array_equal(_stamps(got), _stamps(want[: len(got)]))


# ----------------------------------------------------------------------------- ROS 1, KITTI


def test_bag_corrupt_chunk_is_skipped(tmp_path):
    """Flipped bytes in one bz2 chunk of a bag: stop mode raises; skip mode reports the chunk once with every
    message it held (the bag's own index says which) and yields all other scans."""
    from rosbags.rosbag1 import Reader

    src = tmp_path / "a.bag"
    write_bag(src, n=200, compression="bz2", chunk_threshold=8000)
    data = bytearray(src.read_bytes())
    mid = len(data) // 2
    data[mid: mid + 16] = bytes(b ^ 0x5A for b in data[mid: mid + 16])
    p = tmp_path / "c.bag"
    p.write_bytes(bytes(data))
    with pytest.raises(LogFormatError, match="corrupt or truncated bag chunk"):
        list(open_log(p).frames())
    with Reader(src) as r:
        pos = max(c.pos for c in r.chunk_infos if c.pos <= mid)
        entries = [e for idx in r.indexes.values() for e in idx]
    lost = {e.time for e in entries if e.chunk_pos == pos}
    # resuming after the chunk restarts past its last stamp: messages sharing a lost stamp (an /odom
    # beside its /scan in the next chunk) are lost and reported too
    n_reported = sum(e.time in lost for e in entries)
    log = SkipLog()
    got = list(open_log(p).frames(on_skip=log))
    want = [f for f in open_log(src).frames() if stamp_to_ns(f.stamp) not in lost]
    chunk = [e for e in log.errors if e.where.startswith("chunk ")]  # the chunk once, with all it held
    assert len(chunk) == 1 and chunk[0].where.endswith(f"at byte offset {pos}")
    assert chunk[0].records == sum(e.chunk_pos == pos for e in entries)
    assert log.records() == n_reported > 0
    assert 0 < 200 - len(got) < 200
    np.testing.assert_array_equal(_stamps(got), _stamps(want))


def test_kitti_truncated_scan_file_is_skipped(tmp_path, rng):
    """A .bin whose size is not a multiple of 16 is skipped (reported with its name); the others keep
    their file positions as frame indexes."""
    seq, _ = _write_seq(tmp_path, rng, n=4)
    bad = seq / "velodyne" / "000002.bin"
    bad.write_bytes(bad.read_bytes()[:-6])
    log = SkipLog()
    got = list(open_log(seq).frames(on_skip=log))
    assert [f.index for f in got] == [0, 2, 3]
    assert len(log) == 1 and log.errors[0].path == str(bad)
