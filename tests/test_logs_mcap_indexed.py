"""The chunk-by-chunk MCAP read (slam/logs/mcap_indexed.py) against the mcap library's SeekingReader:
same messages, same bytes, same order, same frames; a bad chunk is an error naming its offset, or with
on_skip is left out and the rest read."""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from core import geometry as geo
from core.errors import LogFormatError
from slam.logs import mcap_indexed
from slam.logs.mcap_reader import McapReader
from slam.logs.mcap_writer import McapLogWriter

COMPRESSIONS = ["zstd", "lz4", "none"]


def write_mixed_log(path, compression, *, n=40, chunk_size=1 << 14, jitter=0.0, seed=0):
    """LaserScan /scan, PointCloud2 /points, /odom, /ground_truth (PoseStamped), /tf and /tf_static,
    interleaved; with *jitter* > 0 the log times are shuffled locally so that chunks overlap in time."""
    rng = np.random.default_rng(seed)
    t0 = 1.7e9
    with McapLogWriter(path, compression=compression, chunk_size=chunk_size) as w:
        w.write_tf(t0, [("base_link", "laser", geo.xytheta_to_matrix(0.2, 0.0, 0.1))], static=True)
        w.write_tf(t0, [("base_link", "velodyne", geo.se3_exp(np.array([0.0, 0.0, 1.2, 0.0, 0.0, 0.3])))], static=True)
        for i in range(n):
            t = t0 + 0.1 * i
            dt = lambda: float(rng.uniform(-jitter, jitter))  # noqa: E731
            r = rng.uniform(0.5, 9.0, 181).astype(np.float32)
            r[::9] = np.inf
            w.write_scan("/scan", t + dt(), "laser", -np.pi / 2, np.pi / 180, 0.1, 8.0, r)
            w.write_odometry("/odom", t + dt(), "odom", "base_link", geo.xytheta_to_matrix(0.1 * i, 0.01 * i, 0.02 * i))
            w.write_pose("/ground_truth", t + dt(), "map", geo.xytheta_to_matrix(0.1 * i, 0.0, 0.02 * i))
            w.write_tf(t + dt(), [("odom", "base_link", geo.xytheta_to_matrix(0.1 * i, 0.01 * i, 0.02 * i))])
            if i % 3 == 0:
                pts = rng.normal(0.0, 10.0, (int(rng.integers(50, 400)), 3))
                pts[::17] = np.nan
                w.write_pointcloud("/points", t + dt(), "velodyne", pts, fields={"intensity": rng.random(len(pts)).astype(np.float32)})
    return path


def raw_list(reader, topics=None):
    """Every raw message as a comparable tuple (payload copied to bytes)."""
    return [(r.index, r.topic, r.msgtype, r.log_time_ns, bytes(r.data), r.where) for r in reader._raw_messages(topics)]


def assert_same_frames(a, b):
    assert len(a) == len(b) and len(a) > 0
    for fa, fb in zip(a, b):
        assert (fa.stamp, fa.index, fa.source, fa.max_range, fa.min_range) == (fb.stamp, fb.index, fb.source, fb.max_range, fb.min_range)
        np.testing.assert_array_equal(fa.points, fb.points)
        for name in ("angles", "ranges", "no_return", "odom", "ground_truth", "base_T_sensor"):
            va, vb = getattr(fa, name), getattr(fb, name)
            assert (va is None) == (vb is None), name
            if va is not None:
                np.testing.assert_array_equal(va, vb)


@pytest.mark.parametrize("compression", COMPRESSIONS)
def test_indexed_frames_equal_library_frames(tmp_path, compression):
    """For zstd, lz4 and uncompressed chunks, the chunk-by-chunk path
    and the mcap library give bit-identical frames (points, ranges, odometry, ground truth, mounts,
    stamps, indices) in the same order, for the LaserScan and for the PointCloud2 topic."""
    p = write_mixed_log(tmp_path / "m.mcap", compression)
    fast = McapReader(p)
    assert fast._use_index()
    for topic in ("/scan", "/points"):
        assert_same_frames(list(McapReader(p, topic).frames()), list(McapReader(p, topic, indexed=False).frames()))
    assert fast.info() == McapReader(p, indexed=False).info()


@pytest.mark.parametrize("compression", COMPRESSIONS)
def test_overlapping_chunks_same_order(tmp_path, compression):
    """With log times shuffled across chunk boundaries (chunks overlap in time) every message comes
    out in the library's order — (log_time, chunk offset, position) — with the same bytes, for all
    topics and for each single-topic filter."""
    p = write_mixed_log(tmp_path / "o.mcap", compression, chunk_size=2048, jitter=0.25)
    fast, lib = McapReader(p), McapReader(p, indexed=False)
    got, ref = raw_list(fast), raw_list(lib)
    assert got == ref
    times = [r[3] for r in got]
    assert times == sorted(times)
    for topic in ("/scan", "/points", "/tf", "/tf_static"):
        assert raw_list(fast, {topic}) == raw_list(lib, {topic})


@st.composite
def message_plans(draw):
    n = draw(st.integers(1, 60))
    stamps = draw(st.lists(st.integers(0, 30), min_size=n, max_size=n))  # few distinct values: many ties
    topics = draw(st.lists(st.sampled_from(["/a", "/b", "/c"]), min_size=n, max_size=n))
    return list(zip(stamps, topics)), draw(st.sampled_from(COMPRESSIONS)), draw(st.sampled_from([256, 1024, 1 << 20]))


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(plan=message_plans(), filt=st.sets(st.sampled_from(["/a", "/b", "/c", "/nope"])))
def test_random_logs_same_messages(plan, filt):
    """Property: for random logs (out-of-order log times with many ties, random chunk size and
    compression) and any topic filter, the chunk-by-chunk path yields exactly the library's messages —
    payload bytes, log times, per-topic indices — in the library's order."""
    msgs, compression, chunk = plan
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "r.mcap"
        with McapLogWriter(p, compression=compression, chunk_size=chunk) as w:
            for k, (s, topic) in enumerate(msgs):
                w.write_odometry(topic, 100.0 + 0.5 * s, "odom", "base_link", geo.xytheta_to_matrix(k, 0.0, 0.0))
        fast, lib = McapReader(p), McapReader(p, indexed=False)
        assert fast._use_index()
        for topics in (None, filt):
            assert raw_list(fast, topics) == raw_list(lib, topics)


@pytest.mark.parametrize("compression", COMPRESSIONS)
def test_corrupt_chunk_names_file_and_offset(tmp_path, compression):
    """Zeroed bytes inside a chunk (CRC, decompression) and a chunk index pointing at the wrong
    place are LogFormatErrors naming the file, 'byte offset' and the last good message; every
    message before the bad chunk is delivered first, as the library does."""
    p = write_mixed_log(tmp_path / "c.mcap", compression, n=60, chunk_size=4096)
    summary = McapReader(p)._summary()
    chunks = sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
    bad_chunk = chunks[len(chunks) // 2]
    data = bytearray(p.read_bytes())
    mid = bad_chunk.chunk_start_offset + bad_chunk.chunk_length // 2
    data[mid : mid + 32] = bytes(32)
    q = tmp_path / "bad.mcap"
    q.write_bytes(bytes(data))
    fast = McapReader(q)
    assert fast._use_index()
    with pytest.raises(LogFormatError) as ei:
        raw_list(fast)
    msg = str(ei.value)
    assert str(q) in msg and f"byte offset {bad_chunk.chunk_start_offset}" in msg and "after /" in msg, msg
    # the messages before the bad chunk are those of the intact file
    good: list = []
    with pytest.raises(LogFormatError):
        for r in McapReader(q)._raw_messages(None):
            good.append((r.topic, r.log_time_ns, bytes(r.data)))
    ref = [(r[1], r[3], r[4]) for r in raw_list(McapReader(p, indexed=False))]
    assert good == ref[: len(good)] and len(good) > 0
    with pytest.raises(LogFormatError):  # the frames path too
        list(McapReader(q).frames())


def test_wrong_chunk_offset_in_index(tmp_path):
    """A chunk index whose offset does not point at a chunk record raises ChunkError with that offset."""
    p = write_mixed_log(tmp_path / "w.mcap", "zstd", n=10)
    summary = McapReader(p)._summary()
    ci = summary.chunk_indexes[0]
    ci.chunk_start_offset += 1
    with open(p, "rb") as fh, pytest.raises(mcap_indexed.ChunkError) as ei:
        list(mcap_indexed.indexed_messages(fh, summary))
    assert ei.value.offset == ci.chunk_start_offset


def test_files_without_index_use_the_library(tmp_path):
    """A file without chunk indexes (truncated: no summary) is not read chunk by chunk and
    gives the library's error, naming the last good message."""
    p = write_mixed_log(tmp_path / "t.mcap", "zstd", n=60, chunk_size=4096)
    data = p.read_bytes()
    q = tmp_path / "trunc.mcap"
    q.write_bytes(data[: len(data) // 2])
    r = McapReader(q)
    assert not r._use_index()
    with pytest.raises(LogFormatError, match="after /"):
        raw_list(r)


def test_typestore_shared_between_readers(tmp_path):
    """Reopening a log reuses the message types built for it (no per-reader parse/compile)."""
    p = write_mixed_log(tmp_path / "s.mcap", "zstd", n=3)
    a, b = McapReader(p), McapReader(p)
    a.topics()
    b.topics()
    assert a._store is b._store


_CLEAN: dict[str, tuple[bytes, list, list]] = {}


def _clean_log(compression: str) -> tuple[bytes, list, list[tuple[int, int]]]:
    """A small mixed log per compression (written once per session): its bytes, its messages and
    the byte ranges [start, end) of every chunk record in it."""
    if compression not in _CLEAN:
        with tempfile.TemporaryDirectory() as d:
            p = write_mixed_log(Path(d) / "x.mcap", compression, n=12, chunk_size=2048)
            r = McapReader(p, indexed=False)
            spans = [(c.chunk_start_offset, c.chunk_start_offset + c.chunk_length) for c in r._summary().chunk_indexes]
            _CLEAN[compression] = (p.read_bytes(), raw_list(r), spans)
    return _CLEAN[compression]


def _outcome(reader):
    try:
        return raw_list(reader)
    except LogFormatError:
        return "error"


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(compression=st.sampled_from(COMPRESSIONS), where=st.floats(0.0, 1.0), size=st.integers(1, 24), fill=st.sampled_from([0x00, 0xFF, 0x5A]))
def test_damaged_files_error_or_agree(compression, where, size, fill):
    """Property: with a run of overwritten bytes anywhere in the file (chunks, indexes, summary,
    footer) the reader raises LogFormatError — never another exception — or yields what the mcap
    library yields; damage inside a chunk never yields different messages (CRC, decompression and
    header checks catch it)."""
    clean, clean_msgs, spans = _clean_log(compression)
    data = bytearray(clean)
    start = min(int(where * len(data)), len(data) - 1)
    data[start : start + size] = bytes([fill]) * len(data[start : start + size])
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "d.mcap"
        p.write_bytes(bytes(data))
        fast = _outcome(McapReader(p))
        lib = _outcome(McapReader(p, indexed=False))
    if fast != "error" and lib != "error":
        assert fast == lib
    if any(a <= start and start + size <= b for a, b in spans):
        assert fast == "error" or fast == clean_msgs, (start, size)


# ----------------------------------------------------------------------------- skipping damaged chunks


def chunk_contents(data: bytes) -> list[tuple[int, int, list[tuple[str, int, bytes]]]]:
    """Every chunk of an intact MCAP as ``(start, end, [(topic, log_time, payload), ...])``, read with the
    mcap library (its own chunk reader), independently of the chunk-by-chunk path."""
    import io

    from mcap.data_stream import ReadDataStream
    from mcap.reader import make_reader
    from mcap.records import Chunk, Message
    from mcap.stream_reader import breakup_chunk

    fh = io.BytesIO(data)
    summary = make_reader(fh).get_summary()
    out = []
    for ci in sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset):
        fh.seek(ci.chunk_start_offset + 9)
        msgs = [(summary.channels[r.channel_id].topic, r.log_time, bytes(r.data))
                for r in breakup_chunk(Chunk.read(ReadDataStream(fh))) if isinstance(r, Message)]
        out.append((ci.chunk_start_offset, ci.chunk_start_offset + ci.chunk_length, msgs))
    return out


def messages(reader, on_skip=None) -> list[tuple[str, int, bytes]]:
    """(topic, log_time, payload bytes) of every message, in the reader's order."""
    return [(r.topic, r.log_time_ns, bytes(r.data)) for r in reader._raw_messages(None, on_skip)]


def without(msgs: list, lost: list) -> list:
    """*msgs* with one occurrence of each item of *lost* removed, order kept."""
    from collections import Counter

    left = Counter(lost)
    out = []
    for m in msgs:
        if left[m] > 0:
            left[m] -= 1
        else:
            out.append(m)
    return out


@pytest.mark.parametrize("compression", COMPRESSIONS)
@pytest.mark.parametrize("topic", ["/scan", "/points"])
def test_damaged_chunk_is_skipped_rest_bit_exact(tmp_path, compression, topic):
    """A damaged chunk in the middle of a LaserScan + PointCloud2 MCAP, read with on_skip through the
    chunk-by-chunk path: exactly one skip, naming the file and the chunk's byte
    offset; every message of every other chunk comes out with the intact file's bytes in the library's
    order; the frames of *topic* are the intact file's frames minus those whose message was in the
    damaged chunk, with bit-identical points, ranges and stamps. Without on_skip it is an error."""
    from slam.logs import SkipLog
    from slam.logs.ros_msgs import stamp_to_ns

    p = write_mixed_log(tmp_path / "m.mcap", compression, n=60, chunk_size=4096)
    clean = p.read_bytes()
    chunks = chunk_contents(clean)
    with_topic = [c for c in chunks if any(m[0] == topic for m in c[2])]
    assert len(with_topic) >= 5
    start, end, lost = with_topic[len(with_topic) // 2]  # a chunk in the middle holding *topic*
    data = bytearray(clean)
    mid = (start + end) // 2
    data[mid : mid + 32] = bytes(32)
    q = tmp_path / "bad.mcap"
    q.write_bytes(bytes(data))

    reader = McapReader(q, topic)
    assert reader._use_index()
    with pytest.raises(LogFormatError, match=f"byte offset {start}"):
        list(McapReader(q, topic).frames())

    log = SkipLog()
    got = messages(McapReader(q), log)
    assert got == without(messages(McapReader(p, indexed=False)), lost)
    assert len(log) == 1 and log.errors[0].where == f"byte offset {start}" and log.errors[0].path == str(q)

    log = SkipLog()
    frames = list(reader.frames(on_skip=log))
    lost_ns = {t for tp, t, _ in lost if tp == topic}
    want = [f for f in McapReader(p, topic, indexed=False).frames() if stamp_to_ns(f.stamp) not in lost_ns]
    assert len(log) == 1 and log.errors[0].where == f"byte offset {start}"
    assert len(frames) == len(want) > 0 and lost_ns
    for a, b in zip(frames, want):
        assert a.stamp == b.stamp
        np.testing.assert_array_equal(a.points, b.points)
        if topic == "/scan":
            np.testing.assert_array_equal(a.ranges, b.ranges)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(compression=st.sampled_from(COMPRESSIONS), which=st.floats(0.0, 1.0), where=st.floats(0.0, 1.0),
       size=st.integers(1, 24), fill=st.sampled_from([0x00, 0xFF, 0x5A]))
def test_damage_inside_a_chunk_with_on_skip(compression, which, where, size, fill):
    """Property: overwritten bytes anywhere inside one chunk record, read with on_skip, never raise; the
    messages are either all of the intact file (the damage changed nothing that is read) with no skip,
    or exactly those of all other chunks, in order and bit-exact, with one skip naming that chunk."""
    from slam.logs import SkipLog

    clean, _msgs, _spans = _clean_log(compression)
    chunks = chunk_contents(clean)
    start, end, lost = chunks[min(int(which * len(chunks)), len(chunks) - 1)]
    at = start + min(int(where * (end - start)), end - start - 1)
    data = bytearray(clean)
    data[at : min(at + size, end)] = bytes([fill]) * len(data[at : min(at + size, end)])
    all_msgs = [m for _, _, ms in chunks for m in ms]
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "d.mcap"
        p.write_bytes(bytes(data))
        log = SkipLog()
        got = messages(McapReader(p), log)
        q = Path(d) / "c.mcap"
        q.write_bytes(clean)
        ref = messages(McapReader(q, indexed=False))
    assert sorted(ref) == sorted(all_msgs)  # the independent chunk listing covers the file
    if len(log) == 0:
        assert got == ref, (at, size)
    else:
        assert len(log) == 1 and log.errors[0].where == f"byte offset {start}", log.lines()
        assert got == without(ref, lost)


def test_chunk_header_disagreeing_with_its_index(tmp_path):
    """An uncompressed chunk whose header sizes and CRC are zeroed reads as a valid empty chunk ("no
    CRC", no records) to the mcap library; the chunk-by-chunk path compares the header with the chunk index
    (compression, compressed and uncompressed size): an error naming the chunk's byte offset, or with
    on_skip one skip of that chunk and every other message intact."""
    from slam.logs import SkipLog

    p = write_mixed_log(tmp_path / "m.mcap", "none", n=30, chunk_size=2048)
    clean = p.read_bytes()
    start, _end, lost = chunk_contents(clean)[5]
    assert lost
    data = bytearray(clean)
    data[start + 25 : start + 49] = bytes(24)  # uncompressed_size, CRC, compression length, records length
    q = tmp_path / "z.mcap"
    q.write_bytes(bytes(data))
    ref = messages(McapReader(p, indexed=False))
    assert messages(McapReader(q, indexed=False)) == without(ref, lost)  # the library sees an empty chunk
    with pytest.raises(LogFormatError, match=f"byte offset {start} .*differs from its index"):
        messages(McapReader(q))
    log = SkipLog()
    assert messages(McapReader(q), log) == without(ref, lost)
    assert len(log) == 1 and log.errors[0].where == f"byte offset {start}"
