"""Collision-free robot tours through a ground-truth world, sampled at the laser rate.

1. Clearance: Euclidean distance transform of the free cells (Maurer et al. 2003 via
   ``scipy.ndimage.distance_transform_edt``), made conservative by one cell diagonal.
2. Roadmap: a coarse (≈0.1 m) 8-connected grid graph of cells whose clearance is at least
   ``robot_radius + margin``; edge cost = length · (1 + r_safe / clearance) keeps paths central.
3. Coverage waypoints: farthest-point sampling (Gonzalez 1985, "Clustering to minimize the maximum
   intercluster distance") of the reachable safe cells (spacing ≈ 0.6 of the laser range),
   visited in a greedy nearest-neighbour order of geodesic distance; shortest paths by Dijkstra
   (1959) via ``scipy.sparse.csgraph``, shortened by line-of-sight string pulling against the
   clearance grid (every shortcut is sampled every quarter cell and must keep the clearance).
4. Revisits: the tour returns to its start (a closed loop); if the scan budget allows, it is
   driven again (a second lap revisits everything); if it is too long, the longest prefix of the
   tour that still returns to the start within the budget is used.
5. Motion: a differential-drive robot turns in place to the next segment heading, then drives
   straight, each with a rest-to-rest trapezoidal velocity profile (speed ≤ ``max_speed``, turn
   rate ≤ ``max_turn_rate``, bounded accelerations); poses are sampled every 1/rate_hz seconds.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components, dijkstra

from core.errors import ConfigError

from .sensors import LaserSpec
from .world import World

__all__ = ["plan_path", "clearance_map", "sample_motion", "Roadmap", "main_component", "pick_start", "string_pull"]


def clearance_map(world: World) -> NDArray[np.float64]:
    """Conservative distance (m) from any point of each cell to the nearest non-free cell
    (occupied or unknown, or outside the grid); 0 on non-free cells."""
    free = np.pad(world.free, 1, constant_values=False)
    edt = ndimage.distance_transform_edt(free)[1:-1, 1:-1] * world.resolution
    return np.maximum(edt - math.sqrt(2.0) * world.resolution, 0.0) * world.free


def _clearance_at(world: World, clear: NDArray[np.float64], xy: NDArray[np.float64]) -> NDArray[np.float64]:
    iy, ix = world.cell_of(xy)
    h, w = clear.shape
    ok = (ix >= 0) & (ix < w) & (iy >= 0) & (iy < h)
    out = np.zeros(len(xy))
    out[ok] = clear[iy[ok], ix[ok]]
    return out


def _segment_safe(world: World, clear: NDArray[np.float64], a: NDArray[np.float64], b: NDArray[np.float64],
                  r_safe: float) -> bool:
    n = max(2, int(math.ceil(np.linalg.norm(b - a) / (0.25 * world.resolution))) + 1)
    s = np.linspace(0.0, 1.0, n)[:, None]
    return bool(np.all(_clearance_at(world, clear, a + s * (b - a)) >= r_safe))


def string_pull(world: World, clear: NDArray[np.float64], pts: NDArray[np.float64], r_safe: float) -> NDArray[np.float64]:
    """Greedy line-of-sight shortcut of a polyline: keep a vertex only when the straight segment
    past it would leave the safe set."""
    if len(pts) <= 2:
        return pts
    out = [pts[0]]
    i = 0
    while i < len(pts) - 1:
        j = i + 1
        # grow the shortcut while it stays safe (exponential then linear search)
        step = 1
        while j + step < len(pts) and _segment_safe(world, clear, pts[i], pts[j + step], r_safe):
            j += step
            step *= 2
        while step > 1:
            step //= 2
            if j + step < len(pts) and _segment_safe(world, clear, pts[i], pts[j + step], r_safe):
                j += step
        out.append(pts[j])
        i = j
    return np.asarray(out)


def _trapezoid(amount: NDArray[np.float64], vmax: float, amax: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Peak speed and duration of rest-to-rest moves over *amount* (m or rad) with speed ≤ vmax and
    acceleration ≤ amax (trapezoidal profile, triangular when too short to reach vmax)."""
    vp = np.minimum(vmax, np.sqrt(amount * amax))
    with np.errstate(divide="ignore", invalid="ignore"):
        dur = np.where(amount > 0, amount / np.where(vp > 0, vp, 1.0) + vp / amax, 0.0)
    return vp, dur


def sample_motion(polyline: NDArray[np.float64], heading0: float, max_speed: float, max_turn_rate: float,
                  dt: float, n: int | None = None, max_accel: float = 0.5,
                  max_ang_accel: float = 2.0, pre_turns: NDArray[np.float64] | None = None,
                  ) -> tuple[NDArray[np.float64], float]:
    """Turn-in-place-then-drive motion along *polyline* ``(M, 2)`` starting with heading *heading0*.

    Every turn and every straight segment is a rest-to-rest trapezoidal velocity profile
    (accelerations ≤ ``max_accel`` m/s², ``max_ang_accel`` rad/s²; speeds ≤ ``max_speed`` m/s,
    ``max_turn_rate`` rad/s), so velocities are continuous. *pre_turns* ``(M,)`` (rad, signed) adds a
    look-around at vertex k: first turn by ``pre_turns[k]``, then (without wrapping, so the look is
    undone the way it came) to segment k's heading. Returns ``(poses (K, 3), duration)`` with poses
    sampled at ``k·dt`` (all of them, or the first *n*; the robot rests at the end).
    """
    seg = np.diff(polyline, axis=0)
    lens = np.linalg.norm(seg, axis=1)
    keep = lens > 1e-9
    seg, lens = seg[keep], lens[keep]
    starts = polyline[:-1][keep]
    pre = np.zeros(len(seg)) if pre_turns is None else np.asarray(pre_turns, dtype=np.float64)[:-1][keep]
    if len(seg) == 0:  # standing still
        poses = np.tile([polyline[0, 0], polyline[0, 1], heading0], (1 if n is None else n, 1))
        return poses, 0.0
    headings = np.arctan2(seg[:, 1], seg[:, 0])
    prev = np.concatenate([[heading0], headings[:-1]])
    turns = (headings - prev + np.pi) % (2 * np.pi) - np.pi - pre  # after the look, back the way it came
    # primitives, interleaved: look k, turn k, then drive k (a look of 0 rad takes no time)
    vp_pre, t_pre = _trapezoid(np.abs(pre), max_turn_rate, max_ang_accel)
    vp_turn, t_turn = _trapezoid(np.abs(turns), max_turn_rate, max_ang_accel)
    vp_drive, t_drive = _trapezoid(lens, max_speed, max_accel)
    amount = np.column_stack([np.abs(pre), np.abs(turns), lens]).ravel()
    vpeak = np.column_stack([vp_pre, vp_turn, vp_drive]).ravel()
    acc = np.tile([max_ang_accel, max_ang_accel, max_accel], len(lens))
    dur = np.column_stack([t_pre, t_turn, t_drive]).ravel()
    t_end = np.cumsum(dur)
    total = float(t_end[-1])
    k = int(math.floor(total / dt + 1e-9)) + 1 if n is None else n
    t = np.arange(k) * dt
    prim = np.minimum(np.searchsorted(t_end, t, side="right"), len(dur) - 1)
    T, L, vp, a = dur[prim], amount[prim], vpeak[prim], acc[prim]
    tau = np.clip(t - (t_end[prim] - T), 0.0, T)
    ta = vp / a
    done = 0.5 * a * ta**2 + vp * (tau - ta)                       # cruising
    done = np.where(tau < ta, 0.5 * a * tau**2, done)               # accelerating
    done = np.where(tau > T - ta, L - 0.5 * a * (T - tau) ** 2, done)  # braking
    frac = np.clip(np.where(L > 0, done / np.where(L > 0, L, 1.0), 1.0), 0.0, 1.0)
    frac = np.where(t >= total, 1.0, frac)
    seg_i = prim // 3
    kind = prim % 3  # 0 look, 1 turn, 2 drive
    th = np.where(kind == 0, prev[seg_i] + frac * pre[seg_i],
                  np.where(kind == 1, prev[seg_i] + pre[seg_i] + frac * turns[seg_i], headings[seg_i]))
    pos = starts[seg_i] + np.where(kind == 2, frac, 0.0)[:, None] * seg[seg_i]
    th = (th + np.pi) % (2 * np.pi) - np.pi
    return np.column_stack([pos, th]), total


class Roadmap:
    """Coarse safe-cell graph of a world with Dijkstra queries."""

    def __init__(self, world: World, clear: NDArray[np.float64], r_safe: float) -> None:
        k = max(1, int(round(0.1 / world.resolution)))  # ≈ 0.1 m roadmap cells
        self.block = k  # world cells per roadmap cell along each axis
        h, w = clear.shape
        hh, ww = -(-h // k), -(-w // k)
        pad = np.zeros((hh * k, ww * k))
        pad[:h, :w] = clear
        blocks = pad.reshape(hh, k, ww, k)
        cmin = blocks.min(axis=(1, 3))
        self.clear = cmin
        safe = cmin >= r_safe
        self.safe = safe
        ids = -np.ones(safe.shape, dtype=np.int64)
        ids[safe] = np.arange(int(safe.sum()))
        self.ids = ids
        cy, cx = np.nonzero(safe)
        cell = world.resolution * k
        self.xy = np.column_stack([world.origin_xy[0] + (cx + 0.5) * cell, world.origin_xy[1] + (cy + 0.5) * cell])
        rows, cols, wts = [], [], []
        padded = np.pad(safe, 1, constant_values=False)

        def shifted(dy: int, dx: int) -> NDArray[np.bool_]:
            return padded[1 + dy: 1 + dy + hh, 1 + dx: 1 + dx + ww]

        for dyy, dxx in ((0, 1), (1, 0), (1, 1), (1, -1)):
            ok = safe & shifted(dyy, dxx)
            if dyy and dxx:  # diagonal step: both orthogonal neighbours must be safe too
                ok &= shifted(dyy, 0) & shifted(0, dxx)
            y0, x0 = np.nonzero(ok)
            y1, x1 = y0 + dyy, x0 + dxx
            length = cell * math.hypot(dyy, dxx)
            cm = np.minimum(cmin[y0, x0], cmin[y1, x1])
            rows.append(ids[y0, x0])
            cols.append(ids[y1, x1])
            wts.append(length * (1.0 + r_safe / np.maximum(cm, 1e-6)))
        r, c, wv = np.concatenate(rows), np.concatenate(cols), np.concatenate(wts)
        nn = len(self.xy)
        self.graph = coo_matrix((np.concatenate([wv, wv]), (np.concatenate([r, c]), np.concatenate([c, r]))),
                                shape=(nn, nn)).tocsr()


def main_component(rm: "Roadmap") -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """The nodes of the roadmap's largest connected part and their clearance (m)."""
    _, labels = connected_components(rm.graph, directed=False)
    main = np.bincount(labels).argmax()
    nodes = np.flatnonzero(labels == main)
    node_clear = rm.clear.ravel()[np.flatnonzero(rm.ids.ravel() >= 0)][nodes]
    return nodes, node_clear


def pick_start(nodes: NDArray[np.int64], node_clear: NDArray[np.float64], rng: np.random.Generator) -> int:
    """A random start node among the most open tenth of *nodes*."""
    open_nodes = nodes[node_clear >= np.quantile(node_clear, 0.9)]
    return int(rng.choice(open_nodes))


def _out_and_back(out: NDArray[np.float64], heading0: float, v: float, w: float, dt: float,
                  budget: float) -> NDArray[np.float64]:
    """Drive along the polyline *out* as far as the time *budget* allows to come back the same way
    (bisection on the turning distance), and return the out-and-back polyline."""
    seglen = np.linalg.norm(np.diff(out, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seglen)])

    def tip(reach: float) -> NDArray[np.float64]:
        m = int(np.searchsorted(cum, reach, side="right"))
        if m >= len(out):
            pts = out
        else:
            f = (reach - cum[m - 1]) / max(seglen[m - 1], 1e-12)
            pts = np.vstack([out[:m], out[m - 1] + f * (out[m] - out[m - 1])])
        return np.vstack([pts, pts[-2::-1]])

    lo, hi = 0.0, float(cum[-1])
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        _, t = sample_motion(tip(mid), heading0, v, w, dt, n=1)
        lo, hi = (mid, hi) if t <= budget else (lo, mid)
    return tip(lo)


def plan_path(
    world: World,
    n_poses: int,
    spec: LaserSpec,
    rng: np.random.Generator,
    *,
    step: float | None = None,
    max_speed: float = 0.5,
    max_turn_rate: float = 1.0,
    robot_radius: float = 0.2,
    margin: float = 0.1,
    waypoint_spacing: float | None = None,
) -> NDArray[np.float64]:
    """A collision-free closed tour sampled at the laser rate: ``(n_poses, 3)`` world (x, y, θ) of
    the robot base.

    Args:
        world: the ground truth; the robot stays ``robot_radius + margin`` (m) from every occupied
            or unknown cell.
        n_poses: number of poses (one per scan, ``1/spec.rate_hz`` s apart).
        spec: the laser (its rate sets the time step, its range the waypoint spacing).
        rng: picks the start among the most open places.
        step: maximum distance (m) per scan; overrides ``max_speed`` (= step · rate).
        max_speed: m/s, max_turn_rate: rad/s.
    """
    if n_poses < 1:
        raise ConfigError(f"need at least one pose, got {n_poses}")
    dt = spec.period
    if step is not None:
        max_speed = step / dt
    r_safe = robot_radius + margin
    clear = clearance_map(world)
    rm = Roadmap(world, clear, r_safe)
    if len(rm.xy) == 0:
        raise ConfigError(f"world {world.name!r} has no free space with {r_safe:.2f} m clearance for the robot")
    nodes, node_clear = main_component(rm)
    start = pick_start(nodes, node_clear, rng)
    # farthest-point sampling of coverage waypoints (Euclidean), preferring open places
    spacing = waypoint_spacing if waypoint_spacing is not None else min(0.6 * spec.range_max, 3.0)
    cand = nodes[node_clear >= min(r_safe + 0.2, np.quantile(node_clear, 0.5))]
    wps = [start]
    dmin = np.linalg.norm(rm.xy[cand] - rm.xy[start], axis=1)
    while len(wps) < 80:
        j = int(np.argmax(dmin))
        if dmin[j] < spacing:
            break
        wps.append(int(cand[j]))
        dmin = np.minimum(dmin, np.linalg.norm(rm.xy[cand] - rm.xy[cand[j]], axis=1))
    wps_arr = np.asarray(wps)
    dist, pred = dijkstra(rm.graph, directed=False, indices=wps_arr, return_predecessors=True)
    # greedy nearest-neighbour tour over geodesic distances, starting (and ending) at the start
    order = [0]
    left = set(range(1, len(wps)))
    while left:
        cur = order[-1]
        nxt = min(left, key=lambda q: dist[cur, wps_arr[q]])
        order.append(nxt)
        left.remove(nxt)

    def leg(a: int, b: int) -> NDArray[np.float64]:
        """Shortest path from waypoint a to waypoint b (indices into wps), string-pulled."""
        path = [int(wps_arr[b])]
        src = int(wps_arr[a])
        while path[-1] != src:
            path.append(int(pred[a, path[-1]]))
        return string_pull(world, clear, rm.xy[np.asarray(path[::-1])], r_safe)

    def route(seq: list[int]) -> NDArray[np.float64]:
        parts = [leg(seq[i], seq[i + 1]) for i in range(len(seq) - 1)]
        if not parts:
            return rm.xy[[wps_arr[seq[0]]]]
        return np.vstack([parts[0]] + [p[1:] for p in parts[1:]])

    heading0 = float(rng.uniform(-np.pi, np.pi))
    budget = (n_poses - 1) * dt
    full = route(order + [0])
    _, t_full = sample_motion(full, heading0, max_speed, max_turn_rate, dt, n=1)
    if t_full <= budget or len(order) == 1:
        loop = full
    else:
        loop = None
        # bisection for the longest prefix whose closed tour fits (durations grow roughly with k;
        # whatever prefix is chosen was checked to fit)
        lo, hi = 1, len(order) - 1
        while lo <= hi:
            mid = (lo + hi) // 2
            cand_route = route(order[: mid + 1] + [0])
            _, t = sample_motion(cand_route, heading0, max_speed, max_turn_rate, dt, n=1)
            if t <= budget:
                loop, lo = cand_route, mid + 1
            else:
                hi = mid - 1
        if loop is None:  # even the nearest waypoint is too far: go out and come back the same way
            loop = _out_and_back(leg(0, order[1]), heading0, max_speed, max_turn_rate, dt, budget)
    # drive the closed loop as many times as needed, then cut at n_poses
    laps = [loop]
    _, t_loop = sample_motion(loop, heading0, max_speed, max_turn_rate, dt, n=1)
    if t_loop > 0:
        laps += [loop[1:]] * int(math.ceil(budget / t_loop))
    poly = np.vstack(laps)
    poses, _ = sample_motion(poly, heading0, max_speed, max_turn_rate, dt, n=n_poses)
    return poses
