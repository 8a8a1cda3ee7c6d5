"""mapping.shape: how square a map is drawn, on rasterised rooms with known angles."""

from __future__ import annotations

import numpy as np
import pytest

from core.errors import DegenerateInputError
from mapping.shape import square_share, wall_directions_deg

RES = 0.05


def _room(grid: np.ndarray, centre: tuple[float, float], size: tuple[float, float], angle_deg: float) -> None:
    """Rasterise the outline of a *size* rectangle turned by *angle_deg* about *centre* (m) into *grid*."""
    a = np.radians(angle_deg)
    R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    w, h = size
    corners = np.array([[-w, -h], [w, -h], [w, h], [-w, h], [-w, -h]]) / 2
    for p, q in zip(corners[:-1], corners[1:]):
        s = np.linspace(0, 1, int(np.linalg.norm(q - p) / (RES / 4)))[:, None]
        xy = (p + s * (q - p)) @ R.T + centre
        ij = np.round(xy / RES).astype(int)
        grid[ij[:, 0], ij[:, 1]] = 1.0


def _map(rooms) -> tuple[np.ndarray, np.ndarray]:
    p = np.zeros((400, 400))
    for r in rooms:
        _room(p, *r)
    return p, np.ones_like(p, bool)


def test_an_axis_aligned_building_is_square():
    p, o = _map([((5.0, 5.0), (6.0, 4.0), 0.0), ((5.0, 12.0), (6.0, 6.0), 0.0)])
    assert square_share(p, o, RES) > 0.9  # corner cells lean


@pytest.mark.parametrize("angle", [17.0, 30.0, 45.0, 71.0])
def test_a_whole_building_turned_is_still_square(angle):
    """The dominant directions come from the map itself: turning everything changes nothing but rasterisation."""
    p, o = _map([((10.0, 7.0), (6.0, 4.0), angle), ((10.0, 13.0), (8.0, 5.0), angle)])
    assert square_share(p, o, RES) > 0.8


def test_one_room_at_an_angle_to_the_other_lowers_the_share_to_its_part():
    """Two equal rooms, the second turned by 20°: about half of the wall cells lie off the dominant directions."""
    p, o = _map([((5.0, 5.0), (6.0, 6.0), 0.0), ((5.0, 14.0), (6.0, 6.0), 20.0)])
    share = square_share(p, o, RES)
    assert 0.35 < share < 0.65
    ang = wall_directions_deg(p, o, RES)
    assert np.mean(np.abs(ang - 20.0) < 3.0) > 0.3  # the turned room's walls are found at its angle


def test_unobserved_or_free_cells_are_not_walls():
    p, o = _map([((5.0, 5.0), (6.0, 4.0), 0.0)])
    with pytest.raises(DegenerateInputError):
        square_share(p, np.zeros_like(o), RES)
    with pytest.raises(DegenerateInputError):
        square_share(np.full_like(p, 0.5), o, RES)
