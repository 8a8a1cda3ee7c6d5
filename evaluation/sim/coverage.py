"""Coverage tours: one closed drive that lets the laser see every free cell the robot can see.

The plan is the art-gallery / set-cover view of coverage (Gonzalez-Baños & Latombe, "A randomized
art-gallery algorithm for sensor placement", SoCG 2001): choose viewpoints whose 360° views cover the
free space, then visit them in a short closed order.

1. Reachable space: the roadmap of :mod:`.path` (cells with clearance ≥ CLEARANCE_PER_RADIUS radii),
   its part connected to the start. The robot's footprint over it, grown through free space, is
   the free space the robot can reach; what is left, in pieces of at least ``MIN_REGION_M2``, is
   reported as unreachable at that radius (a room behind a doorway narrower than the robot).
2. Viewpoints: candidates every ``CANDIDATE_SPACING_M`` over the reachable roadmap (the most open
   node of each block), each with the coverage targets (``TARGET_CELL_M`` cells of free space) its
   full sweep sees (:func:`.visibility.visible_targets`); greedy weighted set cover (Chvátal 1979,
   "A greedy heuristic for the set-covering problem"; lazy evaluation) until ``COVER_FRACTION`` of
   what any candidate sees is covered.
3. Order: geodesic distances on the roadmap (Dijkstra 1959), nearest-neighbour tour improved by 2-opt
   (Croes 1958), legs string-pulled as in :mod:`.path`.
4. Looking: the laser sees ± half its field of view around the heading; at a viewpoint whose own
   targets lie outside what the turn there sweeps, the robot first turns the other way (a
   look-around of the smallest angle that brings them into view).
5. Check and repair: the tour is sampled, the actual scans' coverage is computed
   (:func:`.visibility.seen_cells`); where coverable free space stayed unseen, viewpoints for it are
   added and the tour re-planned (at most ``REPAIR_ROUNDS`` times).
"""

from __future__ import annotations

import heapq
import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage
from scipy.sparse.csgraph import dijkstra

from core import geometry as geo
from core.errors import ConfigError
from mapping.roc import free_space

from .path import Roadmap, clearance_map, main_component, pick_start, sample_motion, string_pull
from .sensors import LaserSpec
from .visibility import seen_cells, visible_targets
from .world import World

__all__ = ["CoverageTour", "Region", "coverage_tour", "unreachable_regions", "plan_space", "scan_coverage",
           "unreachable_space", "CLEARANCE_PER_RADIUS"]

CLEARANCE_PER_RADIUS = 1.0  # the robot's centre keeps one radius, plus the clearance map's and the roadmap's
# conservative rounding (≈ 1.5 world cells), from obstacles: a 0.2 m robot passes ≈ 0.6 m doorways at 0.05 m cells
TARGET_CELL_M = 0.2  # side of a coverage target (a block of world cells)
CANDIDATE_SPACING_M = 0.4  # one candidate viewpoint per block of this side
MAX_PLANNING_RANGE_M = 10.0  # a long-range laser plans with this much (more viewpoints, fewer rays)
COVER_FRACTION = 0.995  # of the coverable free space (weighted by world cells)
MIN_REGION_M2 = 0.5  # smaller unreachable pieces (corners the robot's outline cannot enter) are not reported
REPAIR_ROUNDS = 3
DIJKSTRA_SOURCES = 16  # viewpoints whose geodesic distances are computed together (memory: 16 × roadmap nodes)
LOOK_MARGIN_RAD = 0.05  # a look-around brings its targets this far inside the field of view


@dataclass(frozen=True)
class Region:
    """A connected piece of free space the robot cannot reach: area (m²), centroid (m), world cells."""

    area_m2: float
    centroid_xy: tuple[float, float]
    cells: int


@dataclass
class CoverageTour:
    """A planned closed tour and what its scans see.

    Attributes:
        poses: ``(N, 3)`` base poses (x, y, θ) sampled at the laser rate, all laps.
        duration_s, length_m: of all laps. viewpoints: ``(K, 2)`` in visiting order (m).
        coverage: fraction of the world's free cells the scans of the tour see.
        unreachable: free space the robot cannot reach at its radius, largest first.
    """

    poses: NDArray[np.float64]
    duration_s: float
    length_m: float
    viewpoints: NDArray[np.float64]
    coverage: float
    laps: int
    unreachable: list[Region] = field(default_factory=list)


def plan_space(world: World) -> tuple[NDArray[np.bool_], int, float]:
    """The plan's free space (:func:`mapping.roc.free_space`: isolated specks of free cells left out), and
    the number and area (m²) of the specks."""
    return free_space(world.classes(), world.resolution)


def scan_coverage(world: World, sensor_poses_xyt: NDArray[np.float64], spec: LaserSpec,
                  space: NDArray[np.bool_] | None = None) -> float:
    """Fraction of the plan's space (:func:`plan_space`) that scans of *spec* at world sensor poses
    ``(N, 3)`` see."""
    space = plan_space(world)[0] if space is None else space
    seen = seen_cells(world, sensor_poses_xyt, spec.angles(), spec.range_max)
    return float((seen & space).sum() / max(int(space.sum()), 1))


def _reachable_footprint(world: World, rm: Roadmap, nodes: NDArray[np.int64], r_safe: float) -> NDArray[np.bool_]:
    """World cells the robot's outline can cover: its reachable centres, grown by the clearance plus
    the roadmap's discretisation, through free space only (a wall is never crossed)."""
    centre = np.zeros(rm.safe.shape, dtype=bool)
    cy, cx = np.nonzero(rm.ids >= 0)
    centre[cy[nodes], cx[nodes]] = True
    k = rm.block
    fine = np.repeat(np.repeat(centre, k, axis=0), k, axis=1)[: world.shape[0], : world.shape[1]]
    steps = int(math.ceil((r_safe + k * world.resolution + 2 * world.resolution) / world.resolution))
    return ndimage.binary_dilation(fine, structure=np.ones((3, 3), bool), iterations=steps, mask=world.free) | fine


def unreachable_regions(world: World, footprint: NDArray[np.bool_], min_area_m2: float = MIN_REGION_M2,
                        space: NDArray[np.bool_] | None = None) -> list[Region]:
    """Connected pieces (8-neighbours) of the plan's *space* (:func:`plan_space` unless given) outside
    *footprint* of at least *min_area_m2*."""
    rest = (plan_space(world)[0] if space is None else space) & ~footprint
    labels, n = ndimage.label(rest, structure=np.ones((3, 3), bool))
    if n == 0:
        return []
    cells = np.bincount(labels.ravel(), minlength=n + 1)[1:]
    a = world.resolution**2
    big = np.flatnonzero(cells * a >= min_area_m2) + 1
    if big.size == 0:
        return []
    xs, ys = world.cell_centres()
    cy = ndimage.mean(ys[:, None] * np.ones(world.shape), labels, big)
    cx = ndimage.mean(np.ones(world.shape) * xs[None, :], labels, big)
    out = [Region(float(cells[b - 1] * a), (float(x), float(y)), int(cells[b - 1])) for b, x, y in zip(big, cx, cy)]
    return sorted(out, key=lambda r: -r.area_m2)


def _targets(world: World, free: NDArray[np.bool_]) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64]]:
    """Target id per world cell (−1 off *free*), each target's weight (cells of *free*) and centre (m)."""
    tb = max(1, int(round(TARGET_CELL_M / world.resolution)))
    h, w = world.shape
    iy, ix = np.indices((h, w))
    key = (iy // tb) * (-(-w // tb)) + ix // tb
    uniq, inv = np.unique(key[free], return_inverse=True)
    tid = -np.ones((h, w), dtype=np.int64)
    tid[free] = inv
    weight = np.bincount(inv, minlength=len(uniq)).astype(np.float64)
    xs, ys = world.cell_centres()
    cx = np.bincount(inv, weights=np.broadcast_to(xs[None, :], (h, w))[free], minlength=len(uniq)) / weight
    cy = np.bincount(inv, weights=np.broadcast_to(ys[:, None], (h, w))[free], minlength=len(uniq)) / weight
    return tid, weight, np.column_stack([cx, cy])


def _candidates(rm: Roadmap, nodes: NDArray[np.int64], node_clear: NDArray[np.float64], start: int) -> NDArray[np.int64]:
    """The most open node of each CANDIDATE_SPACING_M block of the reachable roadmap; *start* first."""
    xy = rm.xy[nodes]
    blk = np.floor(xy / CANDIDATE_SPACING_M).astype(np.int64)
    key = (blk[:, 0] - blk[:, 0].min()) * (int(np.ptp(blk[:, 1])) + 1) + (blk[:, 1] - blk[:, 1].min())
    order = np.lexsort((-node_clear, key))
    first = np.concatenate([[True], key[order][1:] != key[order][:-1]])
    picked = nodes[order[first]]
    return np.concatenate([[start], picked[picked != start]])


def _greedy_cover(indptr: NDArray[np.int64], indices: NDArray[np.int64], weight: NDArray[np.float64],
                  covered: NDArray[np.bool_], goal: float, exclude: set[int]) -> list[tuple[int, NDArray[np.int64]]]:
    """Lazy greedy weighted set cover: candidates (with the targets each newly covers) until the
    covered weight reaches *goal*; *covered* is updated in place."""
    def gain(c: int) -> float:
        t = indices[indptr[c]: indptr[c + 1]]
        return float(weight[t[~covered[t]]].sum())

    heap = [(-gain(c), c) for c in range(len(indptr) - 1) if c not in exclude]
    heapq.heapify(heap)
    got = float(weight[covered].sum())
    out = []
    while heap and got < goal:
        g, c = heapq.heappop(heap)
        g_now = gain(c)
        if g_now <= 0:
            continue
        if heap and g_now < -heap[0][0]:
            heapq.heappush(heap, (-g_now, c))
            continue
        t = indices[indptr[c]: indptr[c + 1]]
        new = t[~covered[t]]
        covered[new] = True
        got += g_now
        out.append((c, new))
    return out


def _two_opt(order: list[int], dist: NDArray[np.float64], max_passes: int = 100) -> list[int]:
    """2-opt on the closed tour *order* (first element fixed) under the symmetric matrix *dist*."""
    tour = np.array(order + [order[0]])
    for _ in range(max_passes):
        improved = False
        for i in range(1, len(tour) - 2):
            a, b = tour[i - 1], tour[i]
            c, d = tour[i + 1: -1], tour[i + 2:]
            delta = dist[a, c] + dist[b, d] - dist[a, b] - dist[c, d]
            j = int(np.argmin(delta))
            if delta[j] < -1e-9:
                tour[i: i + j + 2] = tour[i: i + j + 2][::-1]
                improved = True
        if not improved:
            break
    return [int(v) for v in tour[:-1]]


def _order(dist: NDArray[np.float64]) -> list[int]:
    """A short closed order of all rows of *dist*, starting at 0: nearest neighbour, then 2-opt."""
    n = len(dist)
    order, left = [0], np.ones(n, dtype=bool)
    left[0] = False
    while left.any():
        row = np.where(left, dist[order[-1]], np.inf)
        nxt = int(np.argmin(row))
        order.append(nxt)
        left[nxt] = False
    return _two_opt(order, dist) if n > 3 else order


def _look(short: float, needed: NDArray[np.float64], fov: float) -> float:
    """Signed pre-turn (rad) before a turn of *short* rad so that the directions *needed* (relative to
    the arrival heading, rad) fall within ± fov/2 of a heading swept: 0 when the turn sees them."""
    if needed.size == 0 or fov >= 2 * np.pi:
        return 0.0
    lo, hi = min(0.0, short), max(0.0, short)
    cap = max(0.0, 2 * np.pi - fov - (hi - lo))  # a look of this much sees every direction
    d_low = np.mod(lo - fov / 2 - needed, 2 * np.pi)  # how far below the seen arc, going clockwise
    d_high = np.mod(needed - hi - fov / 2, 2 * np.pi)  # how far above it, counter-clockwise
    inside = np.mod(needed - (lo - fov / 2), 2 * np.pi) <= hi - lo + fov  # within the arc already
    if inside.all():
        return 0.0
    x_low = min(float(d_low[~inside].max()) + LOOK_MARGIN_RAD, cap)
    x_high = min(float(d_high[~inside].max()) + LOOK_MARGIN_RAD, cap)
    return lo - x_low if x_low <= x_high else hi + x_high


def _reachable(world: World, robot_radius: float) -> tuple[NDArray[np.float64], Roadmap, NDArray[np.int64],
                                                             NDArray[np.float64], float]:
    """Clearance map, roadmap, its largest connected part (nodes, clearances) and the clearance kept (m)."""
    if not (robot_radius > 0 and math.isfinite(robot_radius)):
        raise ConfigError(f"--robot-radius must be a finite number > 0, got {robot_radius}")
    r_safe = max(CLEARANCE_PER_RADIUS * robot_radius, world.resolution)
    clear = clearance_map(world)
    rm = Roadmap(world, clear, r_safe)
    if len(rm.xy) == 0:
        raise ConfigError(f"world {world.name!r} has no place with {r_safe:.2f} m clearance for a robot of radius "
                          f"{robot_radius:.2f} m")
    nodes, node_clear = main_component(rm)
    return clear, rm, nodes, node_clear, r_safe


def unreachable_space(world: World, robot_radius: float) -> list[Region]:
    """The plan's space a robot of *robot_radius* (m) cannot reach from the largest connected part of
    the places it fits (where tours start), largest piece first."""
    _, rm, nodes, _, r_safe = _reachable(world, robot_radius)
    return unreachable_regions(world, _reachable_footprint(world, rm, nodes, r_safe))


class _Planner:
    """The state of one coverage plan: reachable roadmap, candidates and what each sees (module docstring)."""

    def __init__(self, world: World, spec: LaserSpec, rng: np.random.Generator, robot_radius: float,
                 max_speed: float, max_turn_rate: float, base_T_sensor: NDArray[np.float64]) -> None:
        self.world, self.spec = world, spec
        self.v, self.w = max_speed, max_turn_rate
        self.b_T_s = base_T_sensor
        self.space = plan_space(world)[0]
        self.clear, self.rm, nodes, node_clear, self.r_safe = _reachable(world, robot_radius)
        self.start = pick_start(nodes, node_clear, rng)
        self.heading0 = float(rng.uniform(-np.pi, np.pi))
        self.footprint = _reachable_footprint(world, self.rm, nodes, self.r_safe)
        self.cands = _candidates(self.rm, nodes, node_clear, self.start)
        self.tid, self.weight, self.tcentre = _targets(world, self.space)
        offset = float(np.hypot(base_T_sensor[0, 3], base_T_sensor[1, 3]))
        plan_range = max(min(0.95 * spec.range_max, MAX_PLANNING_RANGE_M) - offset, 2 * world.resolution)
        n_rays = int(math.ceil(2 * np.pi * plan_range / (0.5 * TARGET_CELL_M)))
        self.indptr, self.indices = visible_targets(world, self.tid, self.rm.xy[self.cands], plan_range, n_rays)
        self.coverable = np.zeros(len(self.weight), dtype=bool)
        self.coverable[self.indices] = True

    def choose(self) -> tuple[list[int], dict[int, NDArray[np.int64]]]:
        covered = np.zeros(len(self.weight), dtype=bool)
        t0 = self.indices[self.indptr[0]: self.indptr[1]]
        covered[t0] = True
        goal = COVER_FRACTION * float(self.weight[self.coverable].sum())
        picked = _greedy_cover(self.indptr, self.indices, self.weight, covered, goal, exclude={0})
        return [0] + [c for c, _ in picked], {0: t0, **{c: t for c, t in picked}}

    def repair(self, chosen: list[int], seen: NDArray[np.bool_]) -> list[tuple[int, NDArray[np.int64]]]:
        """Viewpoints for coverable free space the tour's scans missed (weighted by missed cells)."""
        missed = self.space & ~seen
        w_missed = np.bincount(self.tid[missed], minlength=len(self.weight)).astype(np.float64) * self.coverable
        total = float(self.weight[self.coverable].sum())
        if w_missed.sum() <= (1.0 - COVER_FRACTION) * total:
            return []
        goal = 0.9 * float(w_missed.sum())  # most of what was missed; the next round checks again
        return _greedy_cover(self.indptr, self.indices, w_missed, w_missed == 0, goal, exclude=set(chosen))

    def tour(self, chosen: list[int], private: dict[int, NDArray[np.int64]],
             ) -> tuple[NDArray[np.float64], NDArray[np.float64], list[int]]:
        """Polyline, per-vertex look-arounds and the visiting order of the *chosen* candidates."""
        vp_nodes = self.cands[np.asarray(chosen)]
        # geodesic distances between viewpoints, a few sources at a time (a full (K, nodes) matrix of a
        # large plan would not fit in memory); each leg's path by a search stopped at its own length
        dist = np.empty((len(vp_nodes), len(vp_nodes)))
        for k in range(0, len(vp_nodes), DIJKSTRA_SOURCES):
            block = dijkstra(self.rm.graph, directed=False, indices=vp_nodes[k: k + DIJKSTRA_SOURCES])
            dist[k: k + DIJKSTRA_SOURCES] = block[:, vp_nodes]
        order = _order(dist)
        seq = order + [order[0]]
        legs = []
        for a, b in zip(seq[:-1], seq[1:]):
            _, pred = dijkstra(self.rm.graph, directed=False, indices=int(vp_nodes[a]), return_predecessors=True,
                               limit=dist[a, b] * (1 + 1e-9) + 1e-9)
            path = [int(vp_nodes[b])]
            while path[-1] != int(vp_nodes[a]):
                path.append(int(pred[path[-1]]))
            legs.append(string_pull(self.world, self.clear, self.rm.xy[np.asarray(path[::-1])], self.r_safe))
        poly = np.vstack([legs[0]] + [leg[1:] for leg in legs[1:]])
        starts = np.cumsum([0] + [len(leg) - 1 for leg in legs[:-1]])  # polyline vertex of each viewpoint
        pre = np.zeros(len(poly))
        fov = self.spec.angle_max - self.spec.angle_min + self.spec.angle_increment
        seg = np.diff(poly, axis=0)
        lens = np.linalg.norm(seg, axis=1)
        head = np.arctan2(seg[:, 1], seg[:, 0])
        for q, v in zip(order, starts):
            if v >= len(seg) or lens[v] <= 1e-9:
                continue
            h_in = self.heading0 if v == 0 else head[v - 1]
            short = float(geo.wrap_angle(head[v] - h_in))
            t = private.get(q, np.empty(0, np.int64))
            rel = self.tcentre[t] - poly[v]
            far = np.hypot(rel[:, 0], rel[:, 1]) > 0.5 * TARGET_CELL_M
            needed = np.mod(np.arctan2(rel[far, 1], rel[far, 0]) - h_in + np.pi, 2 * np.pi) - np.pi
            pre[v] = _look(short, needed, fov)
        return poly, pre, order

    def sample(self, poly: NDArray[np.float64], pre: NDArray[np.float64], laps: int,
               ) -> tuple[NDArray[np.float64], float]:
        full = np.vstack([poly] + [poly[1:]] * (laps - 1))
        pres = np.concatenate([pre] + [pre[1:]] * (laps - 1))
        return sample_motion(full, self.heading0, self.v, self.w, self.spec.period, pre_turns=pres)

    def seen(self, poses: NDArray[np.float64]) -> NDArray[np.bool_]:
        sensor = geo.matrix_to_xytheta(geo.xytheta_to_matrix(poses) @ self.b_T_s)
        return seen_cells(self.world, sensor, self.spec.angles(), self.spec.range_max)


def coverage_tour(world: World, spec: LaserSpec, rng: np.random.Generator, *, robot_radius: float = 0.2,
                  laps: int = 1, max_speed: float = 0.5,
                  max_turn_rate: float = 1.0, base_T_sensor: NDArray[np.float64] | None = None) -> CoverageTour:
    """Plan a closed coverage tour of *world* for a robot of *robot_radius* (m) carrying *spec* (module
    docstring), driven *laps* times, and measure the coverage of its scans."""
    if laps < 1:
        raise ConfigError(f"--laps must be >= 1, got {laps}")
    b_T_s = np.eye(4) if base_T_sensor is None else np.asarray(base_T_sensor, dtype=np.float64)
    p = _Planner(world, spec, rng, robot_radius, max_speed, max_turn_rate, b_T_s)
    chosen, private = p.choose()
    for _ in range(REPAIR_ROUNDS + 1):
        poly, pre, order = p.tour(chosen, private)
        poses, duration = p.sample(poly, pre, 1)
        seen = p.seen(poses)
        extra = p.repair(chosen, seen)
        if not extra:
            break
        chosen = chosen + [c for c, _ in extra]
        private.update({c: t for c, t in extra})
    if laps > 1:
        poses, duration = p.sample(poly, pre, laps)
    length = float(np.linalg.norm(np.diff(poly, axis=0), axis=1).sum()) * laps
    vps = p.rm.xy[p.cands[np.asarray([chosen[i] for i in order])]]
    return CoverageTour(poses=poses, duration_s=duration, length_m=length, viewpoints=vps,
                        coverage=float((seen & p.space).sum() / max(int(p.space.sum()), 1)), laps=laps,
                        unreachable=unreachable_regions(world, p.footprint, space=p.space))
