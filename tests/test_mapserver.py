"""ROS map_server YAML + image reading and writing (mapping/mapserver.py)."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from core.errors import MapFormatError
from mapping.mapserver import classes_from_probability, read_map_server, write_map_server
from tests.conftest import shared_path


def _yaml(path, image, **kw):
    lines = [f"image: {image}", f"resolution: {kw.get('resolution', 0.05)}", f"origin: {kw.get('origin', [0.0, 0.0, 0.0])}",
             f"occupied_thresh: {kw.get('occ', 0.65)}", f"free_thresh: {kw.get('free', 0.196)}", f"negate: {kw.get('negate', 0)}"]
    if "mode" in kw:
        lines.append(f"mode: {kw['mode']}")
    path.write_text("\n".join(lines) + "\n")
    return path


def _random_classes(rng, shape=(37, 53)):
    return rng.choice(np.array([-1, 0, 100], dtype=np.int8), size=shape)


def test_class_round_trip_pgm(tmp_path, rng):
    """Writing int8 classes and reading them back gives identical classes, resolution and origin."""
    cls = _random_classes(rng)
    write_map_server(tmp_path / "m.yaml", cls, 0.05, (1.5, -2.25, 0.0))
    m = read_map_server(tmp_path / "m.yaml")
    assert (tmp_path / "m.pgm").read_bytes().startswith(b"P5")
    np.testing.assert_array_equal(m.classes, cls)
    assert m.resolution == 0.05 and np.allclose(m.origin, [1.5, -2.25, 0.0])
    assert m.shape == cls.shape


def test_class_round_trip_png_and_thresholds(tmp_path, rng):
    """PNG output round-trips too, also with non-default thresholds recorded in the YAML."""
    cls = _random_classes(rng)
    write_map_server(tmp_path / "m.yaml", cls, 0.1, (0, 0), image_name="img.png", occupied_thresh=0.6, free_thresh=0.3)
    m = read_map_server(tmp_path / "m.yaml")
    np.testing.assert_array_equal(m.classes, cls)
    assert (m.occupied_thresh, m.free_thresh) == (0.6, 0.3)


def test_probability_thresholds_honoured(tmp_path, rng):
    """A float grid (NaN = unknown) reads back as exactly p > occ → 100, p < free → 0, else −1,
    including probabilities within one grey level of the thresholds, and p_occ within 1/255."""
    p = rng.uniform(0, 1, size=(40, 40))
    occ, free = 0.65, 0.196
    p[0, :10] = occ + np.linspace(-2, 2, 10) / 255.0
    p[1, :10] = free + np.linspace(-2, 2, 10) / 255.0
    p[2, :5] = [occ, free, 0.0, 1.0, np.nan]
    p[rng.uniform(size=p.shape) < 0.1] = np.nan
    write_map_server(tmp_path / "p.yaml", p, 0.05, (0, 0, 0))
    m = read_map_server(tmp_path / "p.yaml")
    np.testing.assert_array_equal(m.classes, classes_from_probability(p, occ, free))
    interior = np.isfinite(p) & (np.abs(p - occ) > 2 / 255) & (np.abs(p - free) > 2 / 255)
    assert np.max(np.abs(m.occupancy[interior] - p[interior])) <= 0.5 / 255 + 1e-12


def test_row_zero_is_lowest_y(tmp_path):
    """Image row 0 (top) is the largest y: a black pixel in the image's bottom-left is cell [0, 0]."""
    img = np.full((4, 6), 254, np.uint8)
    img[3, 0] = 0
    Image.fromarray(img, "L").save(tmp_path / "a.pgm")
    m = read_map_server(_yaml(tmp_path / "a.yaml", "a.pgm"))
    assert m.classes[0, 0] == 100 and (m.classes == 100).sum() == 1


def test_negate(tmp_path):
    """negate: 1 makes white occupied and black free (p_occ = grey/255)."""
    img = np.array([[0, 255, 127]], np.uint8)
    Image.fromarray(img, "L").save(tmp_path / "n.png")
    m = read_map_server(_yaml(tmp_path / "n.yaml", "n.png", negate=1))
    np.testing.assert_array_equal(m.classes[0], [0, 100, -1])
    np.testing.assert_allclose(m.occupancy[0], img[0] / 255.0)


def test_rgb_and_rgba_average_like_map_server(tmp_path):
    """RGB: grey is the channel mean. RGBA in trinary mode averages alpha in (map_server's
    image_loader quirk): black with alpha 255 → mean 63.75 → p 0.75 (occupied); black with
    alpha 0 → mean 0 → occupied; white with alpha 0 → mean 191.25 → p 0.25 (unknown)."""
    rgb = np.array([[[0, 0, 0], [255, 255, 255], [255, 0, 0], [200, 200, 200]]], np.uint8)
    Image.fromarray(rgb, "RGB").save(tmp_path / "c.png")
    m = read_map_server(_yaml(tmp_path / "c.yaml", "c.png"))
    np.testing.assert_allclose(m.occupancy[0], (255 - rgb[0].mean(axis=1)) / 255)
    np.testing.assert_array_equal(m.classes[0], [100, 0, 100, -1])  # red: p = 0.667; 200: p = 0.216
    rgba = np.array([[[0, 0, 0, 255], [0, 0, 0, 0], [255, 255, 255, 0], [255, 255, 255, 255]]], np.uint8)
    Image.fromarray(rgba, "RGBA").save(tmp_path / "d.png")
    m = read_map_server(_yaml(tmp_path / "d.yaml", "d.png"))
    np.testing.assert_allclose(m.occupancy[0], [0.75, 1.0, 0.25, 0.0])
    np.testing.assert_array_equal(m.classes[0], [100, 100, -1, 0])
    # scale mode ignores alpha for the mean and marks alpha == 0 in-between cells unknown
    m = read_map_server(_yaml(tmp_path / "e.yaml", "d.png", mode="scale"))
    np.testing.assert_allclose(m.occupancy[0], [1.0, 1.0, 0.0, 0.0])


@pytest.mark.parametrize("name,size,res,origin", [
    ("sparse_obstacles.kuanghaofei_fork.yaml", (746, 775), 0.02, (-7.75, -7.46)),
    ("sparse_obstacles.yaml", (746, 775), 0.02, (0.0, 0.0)),
    ("simple_rooms.yaml", (300, 400), 0.05, (0.0, 0.0)),
    ("robocup.yaml", (729, 769), 0.03, (0.0, 0.0)),
    ("mines.yaml", (615, 1200), 0.05, (0.0, 0.0)),
])
def test_stdr_maps_size_and_extent(name, size, res, origin):
    """The STDR maps load with the pixel size, resolution, origin and extent listed in SOURCE.md,
    and contain both free and occupied cells."""
    m = read_map_server(shared_path("stdr_maps", name))
    assert m.shape == size and m.resolution == res
    assert np.allclose(m.origin[:2], origin)
    assert np.allclose(m.extent, (size[1] * res, size[0] * res))
    assert (m.classes == 0).any() and (m.classes == 100).any()


def test_stdr_unknown_border_is_grey_127():
    """SOURCE.md: grey 127 is unknown in sparse_obstacles (the outer border) with thresholds 0.6/0.3."""
    m = read_map_server(shared_path("stdr_maps", "robocup.yaml"))
    assert m.classes[0, 0] == -1 and m.classes[-1, -1] == -1


def test_errors_name_the_file(tmp_path):
    """Missing keys, a missing image, a garbage image and bad YAML raise MapFormatError naming the file."""
    with pytest.raises(MapFormatError, match="nope.yaml"):
        read_map_server(tmp_path / "nope.yaml")
    (tmp_path / "k.yaml").write_text("image: x.pgm\norigin: [0, 0, 0]\n")
    with pytest.raises(MapFormatError, match="resolution"):
        read_map_server(tmp_path / "k.yaml")
    with pytest.raises(MapFormatError, match="does not exist"):
        read_map_server(_yaml(tmp_path / "m.yaml", "missing.pgm"))
    (tmp_path / "g.pgm").write_bytes(b"P5\n10 10\n255\n\x00\x01")
    with pytest.raises(MapFormatError, match="g.pgm"):
        read_map_server(_yaml(tmp_path / "g.yaml", "g.pgm"))
    (tmp_path / "b.yaml").write_text("image: [unclosed\n")
    with pytest.raises(MapFormatError, match="line"):
        read_map_server(tmp_path / "b.yaml")
    with pytest.raises(MapFormatError, match="origin"):
        read_map_server(_yaml(tmp_path / "o.yaml", "x.pgm", origin=[0, 0]))


def test_failed_write_leaves_nothing(tmp_path):
    """A write that fails (probabilities outside [0, 1]) leaves neither image nor YAML behind."""
    with pytest.raises(ValueError):
        write_map_server(tmp_path / "z.yaml", np.array([[0.5, 2.0]]), 0.05, (0, 0))
    assert list(tmp_path.iterdir()) == []
