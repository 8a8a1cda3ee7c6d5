"""ROS 2 bag folders in SQLite storage (``.db3``, ``ros2 bag record``'s default before Iron): read through rosbags,
decoded as the MCAP reader decodes the same messages."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from core.errors import LogFormatError
from slam.logs import detect_format, open_log
from tests.cli_helpers import corridor_log, one_error_line, slam


def write_rosbag2(mcap_path: Path, bag: Path) -> None:
    """Every message of the MCAP log *mcap_path*, byte for byte (CDR), into a new ROS 2 bag folder *bag* in SQLite
    storage, the types declared from rosbags' ROS 2 Humble store as ``ros2 bag record`` declares its own."""
    from mcap.reader import make_reader
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    conns: dict[str, object] = {}
    with open(mcap_path, "rb") as fh, Writer(bag, version=8) as w:
        for schema, channel, message in make_reader(fh).iter_messages(log_time_order=True):
            if channel.topic not in conns:
                conns[channel.topic] = w.add_connection(channel.topic, schema.name, typestore=store)
            w.write(conns[channel.topic], message.log_time, message.data)


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
