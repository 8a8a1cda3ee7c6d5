"""Coverage tours (``slam simulate --scans auto``): visibility, look-arounds, reachability, the tour."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from core import geometry as geo
from evaluation.sim import LASER_PRESETS, load_world
from evaluation.sim.coverage import (_look, _order, _two_opt, coverage_tour, plan_space, scan_coverage,
                                     unreachable_space)
from evaluation.sim.path import clearance_map, sample_motion
from evaluation.sim.visibility import seen_cells, visible_targets
from evaluation.sim.world import World
from tests.cli_helpers import slam

SPEC = LASER_PRESETS["fastgpom"]


def _box(w_m: float, h_m: float, res: float = 0.05) -> World:
    """An empty rectangle closed by one-cell walls."""
    h, w = int(round(h_m / res)), int(round(w_m / res))
    occ = np.zeros((h, w), bool)
    occ[0, :] = occ[-1, :] = occ[:, 0] = occ[:, -1] = True
    return World(occupied=occ, known=np.ones((h, w), bool), resolution=res, origin_xy=np.zeros(2), name="box")


def _two_rooms(door_m: float) -> World:
    """A 10 × 6 m hall and, behind a wall at x = 6 m, a 4 × 6 m room entered by one doorway of *door_m*."""
    world = _box(10.0, 6.0)
    xs, ys = world.cell_centres()
    wall = (np.abs(xs - 6.0) < 0.1)[None, :] & ~(np.abs(ys - 3.0) < door_m / 2)[:, None]
    world.occupied |= wall
    return world


def _room_cells(world: World) -> np.ndarray:
    xs, _ = world.cell_centres()
    return world.free & (xs[None, :] > 6.2)


def test_seen_cells_is_the_disc_in_the_open_and_stops_at_walls():
    """One full-circle scan in an empty 20 m box sees every cell within its range (up to a cell) and
    none beyond; a wall between the sensor and a cell hides the cell."""
    world = _box(20.0, 20.0)
    angles = np.linspace(-np.pi, np.pi, 4000, endpoint=False)
    seen = seen_cells(world, np.array([[10.0, 10.0, 0.3]]), angles, 4.0)
    xs, ys = world.cell_centres()
    d = np.hypot(xs[None, :] - 10.0, ys[:, None] - 10.0)
    assert seen[d < 4.0 - 0.05].all() and not seen[d > 4.0 + 0.08].any()
    xs_grid = np.broadcast_to(xs[None, :], world.shape)
    world.occupied |= (np.abs(xs_grid - 12.0) < 0.05) & (np.abs(ys[:, None] - 10.0) < 1.0)
    seen = seen_cells(world, np.array([[10.0, 10.0, 0.0]]), angles, 4.0)
    behind = (xs_grid > 12.2) & (xs_grid < 13.5) & (np.abs(ys[:, None] - 10.0) < 0.2)
    assert not seen[behind].any() and seen[(xs_grid > 11.0) & (xs_grid < 11.8) & (np.abs(ys[:, None] - 10.0) < 0.2)].all()


def test_visible_targets_agree_with_seen_cells():
    """The targets a viewpoint sees are exactly the targets of the cells its rays cross."""
    world = load_world("rooms", seed=2)
    tid = -np.ones(world.shape, np.int64)
    tid[world.free] = np.arange(int(world.free.sum())) // 7  # arbitrary grouping of free cells
    origins = np.array([[3.0, 5.5], [12.0, 5.6], [20.0, 5.4]])
    indptr, indices = visible_targets(world, tid, origins, 4.0, 720)
    for k, o in enumerate(origins):
        seen = seen_cells(world, np.array([[o[0], o[1], 0.0]]), 2 * np.pi * np.arange(720) / 720, 4.0)
        want = np.unique(tid[seen & world.free])
        np.testing.assert_array_equal(np.sort(indices[indptr[k]: indptr[k + 1]]), want)


@settings(max_examples=300, deadline=None)
@given(short=st.floats(-math.pi, math.pi), fov=st.floats(0.5, 2 * math.pi - 0.01),
       needed=st.lists(st.floats(-math.pi, math.pi), min_size=1, max_size=6))
def test_look_brings_every_needed_direction_into_view(short, fov, needed):
    """After the look-around (pre-turn, then the turn), every needed direction is within ± fov/2 of
    a heading the robot swept; no look when the turn alone sees them all."""
    d = np.array(needed)
    pre = _look(short, d, fov)
    lo, hi = min(0.0, short, pre), max(0.0, short, pre)

    def within(lo_, hi_):
        return np.mod(d - (lo_ - fov / 2), 2 * np.pi) <= (hi_ - lo_ + fov) + 1e-9

    assert within(lo, hi).all() or hi - lo + fov >= 2 * np.pi - 1e-9
    if within(min(0.0, short), max(0.0, short)).all():
        assert pre == 0.0


def test_sample_motion_look_turns_and_comes_back():
    """A look of −1 rad before a +0.5 rad turn: the heading first reaches −1 rad, then the segment's
    heading; zero looks give exactly the motion without looks."""
    poly = np.array([[0.0, 0.0], [1.0, 0.0], [1.0 + math.cos(0.5), math.sin(0.5)]])
    plain, t0 = sample_motion(poly, 0.0, 0.5, 1.0, 0.1)
    same, t1 = sample_motion(poly, 0.0, 0.5, 1.0, 0.1, pre_turns=np.zeros(3))
    np.testing.assert_array_equal(plain, same)
    looked, t2 = sample_motion(poly, 0.0, 0.5, 1.0, 0.1, pre_turns=np.array([0.0, -1.0, 0.0]))
    at_corner = np.hypot(looked[:, 0] - 1.0, looked[:, 1]) < 1e-9
    assert looked[at_corner, 2].min() == pytest.approx(-1.0, abs=1e-9)
    assert looked[-1, 2] == pytest.approx(0.5, abs=1e-9) and t2 > t0


def test_two_opt_finds_the_circle_order():
    """Points on a circle visited in a shuffled order: 2-opt returns the perimeter (the optimum)."""
    rng = np.random.default_rng(3)
    ang = np.sort(rng.uniform(0, 2 * np.pi, 25))
    pts = np.column_stack([np.cos(ang), np.sin(ang)])
    dist = np.linalg.norm(pts[:, None] - pts[None], axis=2)
    order = [0] + list(rng.permutation(np.arange(1, 25)))
    best = _two_opt(order, dist)
    length = sum(dist[a, b] for a, b in zip(best, best[1:] + best[:1]))
    assert length == pytest.approx(sum(dist[i, (i + 1) % 25] for i in range(25)), rel=1e-9)
    assert sorted(_order(dist)) == list(range(25))


def test_plan_space_leaves_out_specks_only():
    """A free speck walled in on its own is not part of the plan's space; a room is."""
    world = _box(6.0, 6.0)
    world.occupied[40:45, 40:45] = True
    world.occupied[42, 42] = False  # one free cell inside a block
    space, n, area = plan_space(world)
    assert not space[42, 42] and n == 1 and area == pytest.approx(0.0025)
    assert space.sum() == world.free.sum() - 1


def test_a_room_behind_a_wide_doorway_is_covered():
    """A 1 m doorway (robot 0.4 m across): the tour enters the room and sees it whole."""
    world = _two_rooms(1.0)
    tour = coverage_tour(world, SPEC, np.random.default_rng(0), robot_radius=0.2)
    assert tour.coverage >= 0.97 and not tour.unreachable
    seen = seen_cells(world, tour.poses, SPEC.angles(), SPEC.range_max)
    room = _room_cells(world)
    assert seen[room].mean() >= 0.97
    assert (tour.viewpoints[:, 0] > 6.0).any()  # entered, not looked into
    # the tour is closed (the last scan within a braking step of the start) and keeps the robot clear
    np.testing.assert_allclose(tour.poses[0, :2], tour.poses[-1, :2], atol=0.01)
    iy, ix = world.cell_of(tour.poses[:, :2])
    assert clearance_map(world)[iy, ix].min() >= 0.2


def test_a_room_behind_a_narrow_doorway_is_reported_unreachable(tmp_path, capsys):
    """A 0.3 m doorway (robot 0.4 m across): the room is unreachable, reported with its size and place;
    the CLI warns on stderr and still writes the log."""
    world = _two_rooms(0.3)
    regions = unreachable_space(world, 0.2)
    room_m2 = _room_cells(world).sum() * world.resolution**2
    assert len(regions) >= 1 and regions[0].area_m2 == pytest.approx(room_m2, rel=0.1)
    assert 6.0 < regions[0].centroid_xy[0] < 10.0
    plan = tmp_path / "plan.yaml"
    world.save(plan)
    code, out, err = slam(["simulate", plan, "--out", tmp_path / "log.mcap"], capsys)
    assert code == 0 and (tmp_path / "log.mcap").exists()
    warn = [ln for ln in err.splitlines() if ln.startswith("warning:")]
    assert len(warn) == 1 and "cannot be reached by a robot of radius 0.2 m" in warn[0]
    assert f"{regions[0].area_m2:.1f} m²" in warn[0]
    # a doorway of 0.6 m lets a robot of 0.1 m radius through: no warning
    _two_rooms(0.6).save(plan)
    code, out, err = slam(["simulate", plan, "--out", tmp_path / "small.mcap", "--robot-radius", "0.1"], capsys)
    assert code == 0 and "warning" not in err


def test_cli_auto_tour_prints_the_coverage_its_log_has(tmp_path, capsys):
    """`slam simulate rooms` (auto): coverage ≥ 0.95; the printed scans and coverage are those of the
    written log, recomputed from its ground-truth poses; --laps 2 doubles the tour."""
    from slam.logs import open_log

    out = tmp_path / "tour.mcap"
    code, stdout, _ = slam(["simulate", "rooms", "--out", out, "--seed", "4"], capsys)
    assert code == 0
    fields = dict(ln.split(": ", 1) for ln in stdout.splitlines() if ": " in ln)
    frames = list(open_log(out).frames())
    assert int(fields["scans"]) == len(frames)
    sensor = geo.matrix_to_xytheta(np.array([f.ground_truth @ f.base_T_sensor for f in frames]))
    world = load_world("rooms", seed=4)
    cov = scan_coverage(world, sensor, SPEC)
    assert float(fields["coverage"]) == pytest.approx(cov, abs=1e-4) and cov >= 0.95
    code, stdout2, _ = slam(["simulate", "rooms", "--out", tmp_path / "two.mcap", "--seed", "4", "--laps", "2"], capsys)
    fields2 = dict(ln.split(": ", 1) for ln in stdout2.splitlines() if ": " in ln)
    assert float(fields2["path_length_m"]) == pytest.approx(2 * float(fields["path_length_m"]), rel=1e-6)
