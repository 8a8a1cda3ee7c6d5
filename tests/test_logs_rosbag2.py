"""ROS 2 bag folders in SQLite storage (``.db3``, ``ros2 bag record``'s default before Iron): read through rosbags,
decoded as the MCAP reader decodes the same messages."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from core.errors import LogFormatError
from slam.logs import detect_format, open_log
from tests.cli_helpers import corridor_log, one_error_line, slam


def write_rosbag2(mcap_path: Path, bag: Path, first: int = 0, stop: int | None = None) -> None:
    """The messages *first* … *stop* − 1 (in log time) of the MCAP log *mcap_path*, byte for byte (CDR), into a new
    ROS 2 bag folder *bag* in SQLite storage, the types declared from rosbags' ROS 2 Humble store as
    ``ros2 bag record`` declares its own (the topics of every message, so that parts of one log match)."""
    from mcap.reader import make_reader
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    with open(mcap_path, "rb") as fh:
        messages = list(make_reader(fh).iter_messages(log_time_order=True))
    with Writer(bag, version=8) as w:
        types = {ch.topic: schema.name for schema, ch, _ in messages}
        conns = {topic: w.add_connection(topic, msgtype, typestore=store) for topic, msgtype in types.items()}
        for _, channel, message in messages[first:stop]:
            w.write(conns[channel.topic], message.log_time, message.data)


def split_rosbag2(mcap_path: Path, bag: Path, at: int) -> None:
    """*mcap_path*'s messages as one ROS 2 bag folder *bag* split into two SQLite files at message *at*, its
    metadata.yaml listing both (as ``ros2 bag record --max-bag-size`` leaves a long recording)."""
    import shutil

    import yaml

    parts = [bag.parent / f"{bag.name}_part{k}" for k in range(2)]
    write_rosbag2(mcap_path, parts[0], 0, at)
    write_rosbag2(mcap_path, parts[1], at, None)
    metas = [yaml.safe_load((p / "metadata.yaml").read_text())["rosbag2_bagfile_information"] for p in parts]
    bag.mkdir()
    names = []
    for k, p in enumerate(parts):
        db3 = next(p.glob("*.db3"))
        names.append(f"{bag.name}_{k}.db3")
        shutil.copy(db3, bag / names[-1])
        metas[k]["files"][0]["path"] = names[-1]
    meta = metas[0]
    meta["relative_file_paths"] = names
    meta["files"] = metas[0]["files"] + metas[1]["files"]
    meta["message_count"] = metas[0]["message_count"] + metas[1]["message_count"]
    end = metas[1]["starting_time"]["nanoseconds_since_epoch"] + metas[1]["duration"]["nanoseconds"]
    meta["duration"]["nanoseconds"] = end - meta["starting_time"]["nanoseconds_since_epoch"]
    for t0, t1 in zip(meta["topics_with_message_count"], metas[1]["topics_with_message_count"]):
        t0["message_count"] += t1["message_count"]
    (bag / "metadata.yaml").write_text(yaml.safe_dump({"rosbag2_bagfile_information": meta}))


@pytest.fixture(scope="module")
def bag_and_mcap(tmp_path_factory):
    d = tmp_path_factory.mktemp("rosbag2")
    corridor_log(d / "tour.mcap", 40, seed=4)
    write_rosbag2(d / "tour.mcap", d / "tour_bag")
    return d / "tour_bag", d / "tour.mcap"


def test_an_sqlite_bag_reads_as_the_mcap_its_messages_came_from(bag_and_mcap, capsys):
    """The same CDR messages in SQLite storage give the same frames (stamps, beams, points, wheel odometry, ground
    truth, the laser's mount from /tf_static) as in the MCAP file, and `slam info` the same count."""
    bag, mcap = bag_and_mcap
    assert sorted(p.suffix for p in bag.iterdir()) == [".db3", ".yaml"]
    assert detect_format(bag) == "ros2"
    reader = open_log(bag)
    assert reader.format == "ros2 bag" and reader.info().sensor_topic == "/scan"
    a, b = list(reader), list(open_log(mcap))
    assert len(a) == len(b) == 40
    for x, y in zip(a, b):
        assert x.stamp == y.stamp
        for field in ("points", "angles", "ranges", "no_return", "odom", "ground_truth", "base_T_sensor"):
            np.testing.assert_array_equal(getattr(x, field), getattr(y, field))
    code, out, _ = slam(["info", bag], capsys)
    assert code == 0 and "scans: 40" in out.splitlines() and "format: ros2 bag" in out.splitlines()


def test_a_bag_split_into_two_files_reads_as_one(bag_and_mcap, tmp_path):
    """A recording split into two SQLite files (metadata.yaml listing both) gives the frames of the whole log."""
    _, mcap = bag_and_mcap
    split_rosbag2(mcap, tmp_path / "split", at=70)
    assert len(list((tmp_path / "split").glob("*.db3"))) == 2
    a, b = list(open_log(tmp_path / "split")), list(open_log(mcap))
    assert [f.stamp for f in a] == [f.stamp for f in b] and len(a) == 40
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x.points, y.points)
        np.testing.assert_array_equal(x.odom, y.odom)


def test_a_damaged_bag_is_refused_in_one_line_naming_it(bag_and_mcap, tmp_path, capsys):
    """A cut SQLite file, a garbled metadata.yaml and the .db3 file given without its folder: exit 2, one line
    naming the path, nothing else."""
    bag, _ = bag_and_mcap
    db3 = next(bag.glob("*.db3"))
    cut = tmp_path / "cut"
    cut.mkdir()
    (cut / "metadata.yaml").write_bytes((bag / "metadata.yaml").read_bytes())
    (cut / db3.name).write_bytes(db3.read_bytes()[: db3.stat().st_size // 3])
    garbled = tmp_path / "garbled"
    garbled.mkdir()
    (garbled / "metadata.yaml").write_text("rosbag2_bagfile_information: [unclosed\n")
    (garbled / db3.name).write_bytes(db3.read_bytes())
    for folder in (cut, garbled):
        with pytest.raises(LogFormatError):
            list(open_log(folder))
        code, _, err = slam(["info", folder], capsys)
        one_error_line(code, err, folder)
    code, _, err = slam(["info", db3], capsys)
    one_error_line(code, err, db3, "give the bag's folder")
