"""PointCloud2 decoding: the vectorised decoder equals a slow per-point reference for any layout."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from core.errors import LogFormatError
from slam.logs.mcap_reader import McapReader
from slam.logs.mcap_writer import McapLogWriter
from slam.logs.pointcloud2 import POINTFIELD_TYPES, decode_pointcloud2
from slam.logs.ros_msgs import POINTCLOUD2, humble_typestore

TS = humble_typestore()
T = TS.types
_STRUCT = {1: "b", 2: "B", 3: "h", 4: "H", 5: "i", 6: "I", 7: "f", 8: "d"}
_SIZE = {k: np.dtype(v).itemsize for k, v in POINTFIELD_TYPES.items()}


def reference_decode(msg) -> np.ndarray:
    """Slow, obviously-correct decoder: one struct.unpack per coordinate of every point."""
    buf = bytes(np.asarray(msg.data, dtype=np.uint8))
    order = ">" if msg.is_bigendian else "<"
    f = {fl.name: fl for fl in msg.fields}
    out = []
    for r in range(msg.height):
        for c in range(msg.width):
            base = r * msg.row_step + c * msg.point_step
            p = [struct.unpack_from(order + _STRUCT[f[n].datatype], buf, base + f[n].offset)[0] for n in "xyz"]
            if all(np.isfinite(v) for v in p):
                out.append(p)
    return np.array(out, dtype=np.float64).reshape(-1, 3)


def make_cloud(rng, layout: dict, height: int, width: int, row_pad: int, big: bool, nonfinite: float):
    """Build a PointCloud2 with fields {name: (offset, datatype)} and random values (some NaN/inf)."""
    step = layout.pop("_step")
    row_step = width * step + row_pad
    data = bytearray(rng.integers(0, 256, size=height * row_step, dtype=np.uint8).tobytes())  # garbage padding
    order = ">" if big else "<"
    for r in range(height):
        for c in range(width):
            base = r * row_step + c * step
            for name, (off, dt) in layout.items():
                if dt in (7, 8):
                    v = float(rng.normal(scale=30.0))
                    if name in "xyz" and rng.random() < nonfinite:
                        v = [np.nan, np.inf, -np.inf][int(rng.integers(3))]
                else:
                    info = np.iinfo(np.dtype(POINTFIELD_TYPES[dt]))
                    v = int(rng.integers(info.min, info.max, endpoint=True))
                struct.pack_into(order + _STRUCT[dt], data, base + off, v)
    fields = [T["sensor_msgs/msg/PointField"](name=n, offset=o, datatype=d, count=1) for n, (o, d) in layout.items()]
    hdr = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=1, nanosec=0), frame_id="lidar")
    msg = T[POINTCLOUD2](
        header=hdr, height=height, width=width, fields=fields, is_bigendian=big, point_step=step, row_step=row_step,
        data=np.frombuffer(bytes(data), dtype=np.uint8), is_dense=nonfinite == 0,
    )
    # Through CDR and back, as a reader sees it.
    return TS.deserialize_cdr(TS.serialize_cdr(msg, POINTCLOUD2), POINTCLOUD2)


LAYOUTS = {
    "packed_xyz_f32": {"x": (0, 7), "y": (4, 7), "z": (8, 7), "_step": 12},
    "padded_with_intensity": {"x": (0, 7), "y": (4, 7), "z": (8, 7), "intensity": (16, 7), "_step": 32},
    "float64": {"x": (0, 8), "y": (8, 8), "z": (16, 8), "_step": 24},
    "extra_fields_out_of_order": {"t": (0, 6), "ring": (4, 4), "z": (6, 7), "intensity": (10, 2), "y": (11, 7), "x": (15, 7), "_step": 22},
    "int16_coords": {"x": (0, 3), "y": (2, 3), "z": (4, 3), "_step": 6},
}


@pytest.mark.parametrize("name", sorted(LAYOUTS))
@pytest.mark.parametrize("big", [False, True])
def test_layouts_match_reference(name, big):
    """For each field layout (padding, float64, extra fields, odd offsets, ints) in both byte orders,
    with NaN/inf points and an organised cloud with padded rows, the vectorised decode equals the
    per-point reference bit for bit."""
    rng = np.random.default_rng(hash((name, big)) % 2**32)
    msg = make_cloud(rng, dict(LAYOUTS[name]), height=3, width=41, row_pad=5, big=big, nonfinite=0.1)
    got = decode_pointcloud2(msg)
    ref = reference_decode(msg)
    assert got.dtype == np.float64 and got.shape[1] == 3
    np.testing.assert_array_equal(got, ref)
    assert np.isfinite(got).all()


def test_random_layouts_match_reference():
    """Property: for 40 random layouts (random datatypes, offsets, field order, padding, endianness,
    height, row padding, density) the decode equals the reference."""
    rng = np.random.default_rng(7)
    for _ in range(40):
        names = ["x", "y", "z"] + [f"f{k}" for k in range(int(rng.integers(0, 4)))]
        rng.shuffle(names)
        layout, off = {}, 0
        for n in names:
            dt = int(rng.integers(1, 9)) if n not in "xyz" or rng.random() < 0.3 else int(rng.choice([7, 8]))
            off += int(rng.integers(0, 4))
            layout[n] = (off, dt)
            off += _SIZE[dt]
        layout["_step"] = off + int(rng.integers(0, 5))
        msg = make_cloud(
            rng, layout, height=int(rng.integers(1, 4)), width=int(rng.integers(1, 30)), row_pad=int(rng.integers(0, 9)),
            big=bool(rng.random() < 0.5), nonfinite=float(rng.choice([0.0, 0.2])),
        )
        np.testing.assert_array_equal(decode_pointcloud2(msg), reference_decode(msg))


def test_bad_layouts_raise():
    """A missing coordinate field, a field past point_step, or a short buffer is an error, not garbage."""
    rng = np.random.default_rng(1)
    msg = make_cloud(rng, {"x": (0, 7), "y": (4, 7), "_step": 8}, 1, 4, 0, False, 0.0)
    with pytest.raises(ValueError, match="z"):
        decode_pointcloud2(msg)
    msg = make_cloud(rng, {"x": (0, 7), "y": (4, 7), "z": (8, 7), "_step": 12}, 1, 4, 0, False, 0.0)
    msg.point_step = 10
    with pytest.raises(ValueError, match="exceeds point_step"):
        decode_pointcloud2(msg)
    msg = make_cloud(rng, {"x": (0, 7), "y": (4, 7), "z": (8, 7), "_step": 12}, 1, 4, 0, False, 0.0)
    msg.width = 5
    with pytest.raises(ValueError, match="bytes"):
        decode_pointcloud2(msg)


def test_writer_reader_round_trip_bit_exact(tmp_path, rng):
    """Points written with extra fields come back as exactly float32(points) (non-finite ones
    dropped), and the extra fields survive with their numpy types."""
    pts = rng.normal(scale=50.0, size=(5000, 3))
    pts[17] = [np.nan, 0, 0]
    fields = {"intensity": rng.random(5000).astype(np.float32), "ring": rng.integers(0, 64, 5000).astype(np.uint16),
              "t": rng.random(5000)}
    p = tmp_path / "c.mcap"
    with McapLogWriter(p) as w:
        w.write_pointcloud("/points", 12.5, "velodyne", pts, fields=fields)
    frames = list(McapReader(p).frames())
    assert len(frames) == 1 and frames[0].stamp == 12.5 and frames[0].dim == 3
    keep = np.isfinite(pts).all(1)
    np.testing.assert_array_equal(frames[0].points, pts[keep].astype(np.float32).astype(np.float64))
    from slam.logs.pointcloud2 import pointcloud2_structured

    r = McapReader(p)
    raw = next(r._raw_messages({"/points"}))
    view = pointcloud2_structured(r._decode(raw)).reshape(-1)
    for k, v in fields.items():
        assert view[k].dtype.str[1:] == v.dtype.str[1:]
        np.testing.assert_array_equal(view[k], v)


def test_corrupt_cloud_in_log_names_message(tmp_path):
    """A PointCloud2 whose declared layout needs more bytes than it carries is a LogFormatError
    naming the file and the message."""
    p = tmp_path / "bad.mcap"
    hdr = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=3, nanosec=0), frame_id="l")
    pf = [T["sensor_msgs/msg/PointField"](name=n, offset=4 * i, datatype=7, count=1) for i, n in enumerate("xyz")]
    good = T[POINTCLOUD2](header=hdr, height=1, width=2, fields=pf, is_bigendian=False, point_step=12, row_step=24,
                          data=np.zeros(24, np.uint8), is_dense=True)
    bad = T[POINTCLOUD2](header=hdr, height=1, width=3, fields=pf, is_bigendian=False, point_step=12, row_step=36,
                         data=np.zeros(24, np.uint8), is_dense=True)
    with McapLogWriter(p) as w:
        w.write_message("/points", POINTCLOUD2, good, 3.0)
        w.write_message("/points", POINTCLOUD2, bad, 3.1)
    with pytest.raises(LogFormatError) as ei:
        list(McapReader(p).frames())
    assert str(p) in str(ei.value) and "/points message 1" in str(ei.value)
