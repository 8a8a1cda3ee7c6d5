"""Ground-truth worlds for the 2D laser simulator: map_server maps or built-in procedural worlds.

A :class:`World` is a grid (``[iy, ix]``, row 0 at the origin = lowest y, see
``docs/ARCHITECTURE.md``) of *occupied* cells (which reflect the laser) and *known* cells. Unknown
cells are neither traversable nor reflective: like the STDR simulator (an obstacle only where the
OccupancyGrid value is > 70) the laser passes through them.

The procedural worlds ``rooms``, ``corridor``, ``obstacles`` and ``ring`` are our own (MIT), generated from
axis-aligned walls, boxes and discs, deterministic for a seed and rasterised at any resolution
(a cell is occupied when its centre lies inside a shape).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from mapping.mapserver import read_map_server, write_map_server

__all__ = ["World", "load_world", "PROCEDURAL_WORLDS", "world_from_map_server"]

PROCEDURAL_WORLDS = ("rooms", "corridor", "obstacles", "ring")


@dataclass
class World:
    """A ground-truth 2D world.

    Attributes:
        occupied: bool ``(H, W)``, True where a cell reflects the laser.
        known: bool ``(H, W)``, False for unknown cells (not traversable, transparent to the laser).
        resolution: cell size (m).
        origin_xy: ``(2,)`` world position (m) of the lower-left corner of cell ``[0, 0]``.
        name: world name (procedural name or map file stem).
    """

    occupied: NDArray[np.bool_]
    known: NDArray[np.bool_]
    resolution: float
    origin_xy: NDArray[np.float64]
    name: str

    @property
    def shape(self) -> tuple[int, int]:
        return (int(self.occupied.shape[0]), int(self.occupied.shape[1]))

    @property
    def free(self) -> NDArray[np.bool_]:
        """Known and not occupied."""
        return self.known & ~self.occupied

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """``(xmin, xmax, ymin, ymax)`` in metres."""
        h, w = self.shape
        x0, y0 = self.origin_xy
        return (float(x0), float(x0 + w * self.resolution), float(y0), float(y0 + h * self.resolution))

    def classes(self) -> NDArray[np.int8]:
        """OccupancyGrid classes: −1 unknown, 0 free, 100 occupied."""
        out = np.where(self.occupied, 100, 0).astype(np.int8)
        out[~self.known & ~self.occupied] = -1
        return out

    def cell_of(self, xy: NDArray[np.float64]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """``(iy, ix)`` indices of the cells containing world points ``(N, 2)`` (may be out of range)."""
        g = np.floor((np.asarray(xy, dtype=np.float64) - self.origin_xy) / self.resolution).astype(np.int64)
        return g[..., 1], g[..., 0]

    def cell_centres(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """1-D x centres ``(W,)`` and y centres ``(H,)`` of the cells (m)."""
        h, w = self.shape
        xs = self.origin_xy[0] + (np.arange(w) + 0.5) * self.resolution
        ys = self.origin_xy[1] + (np.arange(h) + 0.5) * self.resolution
        return xs, ys

    def save(self, yaml_path: str | Path, image_name: str | None = None) -> None:
        """Write the world as a map_server map (occupied 0, free 254, unknown 205)."""
        write_map_server(yaml_path, self.classes(), self.resolution, (*self.origin_xy, 0.0), image_name=image_name)


# ----------------------------------------------------------------------------- map_server worlds

def world_from_map_server(yaml_path: str | Path, resolution: float | None = None) -> World:
    """A world from a map_server map: occupied where the class is > 70 (as STDR), unknown where −1.

    A map with a non-zero origin yaw is rejected (cells would not be axis-aligned). With
    *resolution* the grid is resampled by nearest cell centre (exact for integer up-sampling).
    """
    from core.errors import MapFormatError

    m = read_map_server(yaml_path)
    if abs(m.origin[2]) > 1e-12:
        raise MapFormatError(yaml_path, None, f"origin yaw {m.origin[2]} not supported by the simulator (need 0)")
    occupied = m.classes > 70
    known = m.classes != -1
    origin = m.origin[:2].astype(np.float64)
    res = m.resolution
    if resolution is not None and not math.isclose(resolution, res, rel_tol=1e-9):
        h, w = occupied.shape
        nw, nh = int(round(w * res / resolution)), int(round(h * res / resolution))
        ix = np.minimum(((np.arange(nw) + 0.5) * resolution / res).astype(np.int64), w - 1)
        iy = np.minimum(((np.arange(nh) + 0.5) * resolution / res).astype(np.int64), h - 1)
        occupied = occupied[np.ix_(iy, ix)]
        known = known[np.ix_(iy, ix)]
        res = float(resolution)
    return World(occupied=occupied, known=known | occupied, resolution=float(res), origin_xy=origin,
                 name=Path(yaml_path).stem)


# ----------------------------------------------------------------------------- procedural worlds

class _Canvas:
    """Rasteriser for a procedural world: interior ``[0, W] × [0, H]`` m plus an unknown margin."""

    def __init__(self, width: float, height: float, resolution: float) -> None:
        self.res = float(resolution)
        margin = 0.6 + 2.0 * self.res
        self.origin = np.array([-margin, -margin])
        nx = int(math.ceil((width + 2 * margin) / self.res))
        ny = int(math.ceil((height + 2 * margin) / self.res))
        self.xs = self.origin[0] + (np.arange(nx) + 0.5) * self.res
        self.ys = self.origin[1] + (np.arange(ny) + 0.5) * self.res
        self.occupied = np.zeros((ny, nx), dtype=bool)
        self.known = np.zeros((ny, nx), dtype=bool)
        self.wall = max(0.15, 2.0 * self.res)
        self.width, self.height = width, height

    def _span(self, c: NDArray[np.float64], a: float, b: float) -> slice:
        return slice(int(np.searchsorted(c, min(a, b), "left")), int(np.searchsorted(c, max(a, b), "right")))

    def rect(self, x0: float, y0: float, x1: float, y1: float, occupied: bool = True) -> None:
        """Set the cells whose centres lie in the axis-aligned box (occupied or free, always known)."""
        sy, sx = self._span(self.ys, y0, y1), self._span(self.xs, x0, x1)
        self.occupied[sy, sx] = occupied
        self.known[sy, sx] = True

    def disc(self, cx: float, cy: float, r: float) -> None:
        sy, sx = self._span(self.ys, cy - r, cy + r), self._span(self.xs, cx - r, cx + r)
        yy, xx = np.meshgrid(self.ys[sy], self.xs[sx], indexing="ij")
        inside = (xx - cx) ** 2 + (yy - cy) ** 2 <= r * r
        self.occupied[sy, sx] |= inside
        self.known[sy, sx] |= inside

    def rotated_box(self, cx: float, cy: float, half: float, yaw: float) -> None:
        r = half * math.sqrt(2.0)
        sy, sx = self._span(self.ys, cy - r, cy + r), self._span(self.xs, cx - r, cx + r)
        yy, xx = np.meshgrid(self.ys[sy] - cy, self.xs[sx] - cx, indexing="ij")
        c, s = math.cos(yaw), math.sin(yaw)
        u, v = c * xx + s * yy, -s * xx + c * yy
        inside = (np.abs(u) <= half) & (np.abs(v) <= half)
        self.occupied[sy, sx] |= inside
        self.known[sy, sx] |= inside

    def hwall(self, y: float, x0: float, x1: float) -> None:
        t = self.wall / 2
        self.rect(x0 - t, y - t, x1 + t, y + t)

    def vwall(self, x: float, y0: float, y1: float) -> None:
        t = self.wall / 2
        self.rect(x - t, y0 - t, x + t, y1 + t)

    def door(self, x0: float, y0: float, x1: float, y1: float) -> None:
        """Carve free space (an opening) through walls."""
        self.rect(x0, y0, x1, y1, occupied=False)

    def notch(self, x: float, bottom: bool, half_width: float, depth: float) -> None:
        """An alcove through the bottom (y = 0) or top (y = H) outer wall, walled behind."""
        y = 0.0 if bottom else self.height
        out = -depth if bottom else depth
        self.door(x - half_width, min(y, y + out), x + half_width, max(y, y + out))
        t = self.wall / 2
        self.door(x - half_width, y - t, x + half_width, y + t)
        self.hwall(y + out, x - half_width, x + half_width)
        self.vwall(x - half_width, min(y, y + out), max(y, y + out))
        self.vwall(x + half_width, min(y, y + out), max(y, y + out))

    def outer_walls(self) -> None:
        self.rect(0, 0, self.width, self.height, occupied=False)
        self.hwall(0, 0, self.width)
        self.hwall(self.height, 0, self.width)
        self.vwall(0, 0, self.height)
        self.vwall(self.width, 0, self.height)

    def world(self, name: str) -> World:
        return World(self.occupied.copy(), self.known | self.occupied, self.res, self.origin.astype(np.float64), name)


def _partition(rng: np.random.Generator, length: float, lo: float, hi: float) -> list[float]:
    """Cut ``[0, length]`` into pieces of random length in ``[lo, hi]`` (last piece absorbs the rest)."""
    cuts, x = [0.0], 0.0
    while length - x > hi:
        x += rng.uniform(lo, hi)
        if length - x < lo:
            break
        cuts.append(x)
    cuts.append(length)
    return cuts


def _furniture(cv: _Canvas, rng: np.random.Generator, x0: float, y0: float, x1: float, y1: float,
               keep_out: list[tuple[float, float]], count: int) -> None:
    """Drop up to *count* boxes/discs inside a room, away from its doors (*keep_out* centres)."""
    for _ in range(count):
        for _attempt in range(20):
            size = rng.uniform(0.3, 0.8)
            cx, cy = rng.uniform(x0 + size + 0.1, x1 - size - 0.1), rng.uniform(y0 + size + 0.1, y1 - size - 0.1)
            if all(math.hypot(cx - kx, cy - ky) > 1.6 + size for kx, ky in keep_out):
                if rng.uniform() < 0.5:
                    cv.disc(cx, cy, size / 2)
                else:
                    cv.rotated_box(cx, cy, size / 2, rng.uniform(0, np.pi / 2))
                break


def _rooms(resolution: float, rng: np.random.Generator) -> World:
    """Rooms with doors on both sides of a straight hallway; neighbouring rooms share a second door
    on some walls, so a tour through them closes loops."""
    width, hall_w, room_d = 22.0, 2.0, rng.uniform(4.5, 5.5)
    height = 2 * room_d + hall_w
    cv = _Canvas(width, height, resolution)
    cv.outer_walls()
    hy0, hy1 = room_d, room_d + hall_w
    cv.hwall(hy0, 0, width)
    cv.hwall(hy1, 0, width)
    door_w = 1.0
    for ry0, ry1, wall_y in ((0.0, hy0, hy0), (hy1, height, hy1)):
        cuts = _partition(rng, width, 3.5, 5.5)
        for k in range(1, len(cuts) - 1):
            cv.vwall(cuts[k], ry0, ry1)
        doors: list[list[tuple[float, float]]] = [[] for _ in range(len(cuts) - 1)]
        for k in range(len(cuts) - 1):
            a, b = cuts[k], cuts[k + 1]
            dx = rng.uniform(a + 0.4 + door_w / 2, b - 0.4 - door_w / 2)
            cv.door(dx - door_w / 2, wall_y - cv.wall, dx + door_w / 2, wall_y + cv.wall)
            doors[k].append((dx, wall_y))
            if k > 0 and rng.uniform() < 0.5:  # a door to the previous room
                dy = rng.uniform(ry0 + 0.5 + door_w / 2, ry1 - 0.5 - door_w / 2)
                cv.door(a - cv.wall, dy - door_w / 2, a + cv.wall, dy + door_w / 2)
                doors[k].append((a, dy))
                doors[k - 1].append((a, dy))
        for k in range(len(cuts) - 1):
            _furniture(cv, rng, cuts[k], ry0, cuts[k + 1], ry1, doors[k], int(rng.integers(0, 3)))
    # a few pillars on the hallway wall (never in a doorway) keep scan matching along it well-posed
    row = int(np.searchsorted(cv.ys, hy0))
    placed = 0
    for x in rng.uniform(2.0, width - 2.0, size=30):
        if placed == 3:
            break
        if cv.occupied[row, cv._span(cv.xs, x - 0.7, x + 0.7)].all():
            cv.rect(x - 0.1, hy0, x + 0.1, hy0 + 0.25)
            placed += 1
    return cv.world("rooms")


def _corridor(resolution: float, rng: np.random.Generator) -> World:
    """A rectangular ring corridor with a cross corridor (two loops), alcoves and pillars."""
    width, height, cw = rng.uniform(22.0, 26.0), rng.uniform(14.0, 17.0), 2.0
    cv = _Canvas(width, height, resolution)
    cv.outer_walls()
    xc = rng.uniform(0.4, 0.6) * width  # cross corridor centre
    blocks = [(cw, cw, xc - cw / 2, height - cw), (xc + cw / 2, cw, width - cw, height - cw)]
    for bx0, by0, bx1, by1 in blocks:
        cv.rect(bx0, by0, bx1, by1)
        # alcoves (door niches) cut into the inner blocks
        for _ in range(int(rng.integers(2, 5))):
            if rng.uniform() < 0.5:
                x = rng.uniform(bx0 + 0.8, bx1 - 0.8)
                y = by0 if rng.uniform() < 0.5 else by1
                cv.door(x - 0.5, y - 0.6 if y == by1 else y, x + 0.5, y if y == by1 else y + 0.6)
            else:
                y = rng.uniform(by0 + 0.8, by1 - 0.8)
                x = bx0 if rng.uniform() < 0.5 else bx1
                cv.door(x - 0.6 if x == bx1 else x, y - 0.5, x if x == bx1 else x + 0.6, y + 0.5)
    # alcoves (0.4 m deep notches) in the outer walls, and small pillars along them
    for _ in range(int(rng.integers(4, 8))):
        x = rng.uniform(1.0, width - 1.0)
        cv.notch(x, bottom=rng.uniform() < 0.5, half_width=0.5, depth=0.4)
    for _ in range(int(rng.integers(5, 9))):
        x = rng.uniform(1.0, width - 1.0)
        y = 0.25 if rng.uniform() < 0.5 else height - 0.25
        cv.rect(x - 0.15, y - 0.15, x + 0.15, y + 0.15)
    return cv.world("corridor")


def _ring(resolution: float, rng: np.random.Generator) -> World:
    """A square ring of corridors 44–56 m across, crossed by two central corridors (four loops, a building's
    floor of offices around a core), 2.4 m wide; door niches at irregular spacing along every face: long
    corridors with little along them, where a scan matcher slides and a drifted heading meets its start
    again only after a long loop."""
    size, cw = rng.uniform(44.0, 56.0), 2.4
    cv = _Canvas(size, size, resolution)
    cv.outer_walls()
    mid = rng.uniform(0.45, 0.55, size=2) * size  # centres of the north-south and east-west cross corridors
    xs = [(cw, mid[0] - cw / 2), (mid[0] + cw / 2, size - cw)]
    ys = [(cw, mid[1] - cw / 2), (mid[1] + cw / 2, size - cw)]
    for bx0, bx1 in xs:
        for by0, by1 in ys:
            cv.rect(bx0, by0, bx1, by1)
            for a, b, fixed, along_x in ((bx0, bx1, by0, True), (bx0, bx1, by1, True), (by0, by1, bx0, False),
                                         (by0, by1, bx1, False)):
                for c in np.cumsum(rng.uniform(3.0, 9.0, size=12)) + a:
                    if c > b - 1.0:
                        break
                    inward = 0.6 if fixed in (by0, bx0) else -0.6
                    if along_x:
                        cv.door(c - 0.5, min(fixed, fixed + inward), c + 0.5, max(fixed, fixed + inward))
                    else:
                        cv.door(min(fixed, fixed + inward), c - 0.5, max(fixed, fixed + inward), c + 0.5)
    for _ in range(int(rng.integers(6, 12))):
        cv.notch(rng.uniform(1.0, size - 1.0), bottom=rng.uniform() < 0.5, half_width=0.5, depth=0.4)
    return cv.world("ring")


def _obstacles(resolution: float, rng: np.random.Generator) -> World:
    """An open walled area with random discs and rotated squares at least 1.2 m apart."""
    width = height = 16.0
    cv = _Canvas(width, height, resolution)
    cv.outer_walls()
    placed: list[tuple[float, float, float]] = []
    target = int(rng.integers(18, 26))
    for _ in range(400):
        if len(placed) >= target:
            break
        r = rng.uniform(0.2, 0.6)
        cx, cy = rng.uniform(1.2 + r, width - 1.2 - r), rng.uniform(1.2 + r, height - 1.2 - r)
        if all(math.hypot(cx - px, cy - py) > r + pr + 1.2 for px, py, pr in placed):
            placed.append((cx, cy, r))
            if rng.uniform() < 0.5:
                cv.disc(cx, cy, r)
            else:
                cv.rotated_box(cx, cy, r / math.sqrt(2.0) * 1.2, rng.uniform(0, np.pi / 2))
    return cv.world("obstacles")


_BUILDERS = {"rooms": _rooms, "corridor": _corridor, "obstacles": _obstacles, "ring": _ring}


def load_world(name_or_yaml: str | Path, resolution: float | None = None, seed: int = 0) -> World:
    """A procedural world (``rooms``, ``corridor``, ``obstacles``, ``ring``; default 0.05 m cells) or a
    map_server YAML path (its own resolution unless *resolution* is given). Deterministic in *seed*."""
    name = str(name_or_yaml)
    if name in _BUILDERS:
        res = 0.05 if resolution is None else float(resolution)
        if not (0.005 <= res <= 0.25):
            from core.errors import ConfigError

            raise ConfigError(f"world resolution must be within [0.005, 0.25] m, got {res}")
        return _BUILDERS[name](res, np.random.default_rng(seed))
    path = Path(name)
    if not path.exists():
        from core.errors import ConfigError

        raise ConfigError(f"unknown world {name!r}: not one of {PROCEDURAL_WORLDS} and no such map yaml file")
    return world_from_map_server(path, resolution)
