"""Map export round trips (map_server yaml/pgm, npz, MCAP OccupancyGrid), ROC/AUC, BCM and the CLI."""

from __future__ import annotations

import numpy as np
import pytest

from mapping.bcm import add_estimate, fuse, mean_variance, probit_squash
from mapping.grid import GridGeometry
from mapping.occupancy_map import OccupancyMap, export_map, load_npz, write_occupancy_grid
from mapping.roc import map_roc, resample_to_grid, roc_auc, roc_curve


@pytest.fixture(autouse=True)
def single_blas_thread():
    """Batched small LAPACK calls thrash with several BLAS threads on the shared 2-core machine."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(1):
        yield


def _random_map(rng, shape=(37, 53)):
    g = GridGeometry((-1.3, 2.05), 0.05, shape)
    mean = rng.normal(0, 1, shape)
    var = rng.uniform(0.01, 2, shape)
    obs = rng.random(shape) > 0.2
    return OccupancyMap(g, probit_squash(mean, var), mean, var, obs, "fastgpom")


def test_map_server_round_trip(tmp_path, rng):
    """map.yaml + map.pgm load back (mapping.mapserver) to exactly the exported occupancy classes and geometry."""
    from mapping.mapserver import read_map_server

    m = _random_map(rng)
    export_map(m, tmp_path, images=False)
    back = read_map_server(tmp_path / "map.yaml")
    np.testing.assert_array_equal(back.classes, m.classes())
    assert back.resolution == pytest.approx(m.resolution)
    np.testing.assert_allclose(back.origin[:2], m.origin)


def test_npz_round_trip_and_images(tmp_path, rng):
    """map.npz restores every array bit-exactly; map.png and variance.png are written as PNG files."""
    m = _random_map(rng)
    files = export_map(m, tmp_path)
    b = load_npz(tmp_path / "map.npz")
    for k in ("probability", "mean", "variance", "observed"):
        np.testing.assert_array_equal(getattr(b, k), getattr(m, k))
    assert b.geometry == m.geometry and b.method == "fastgpom"
    for name in ("map.png", "variance.png"):
        assert (tmp_path / name) in files and (tmp_path / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_bad_npz_names_file_and_key(tmp_path):
    """A map.npz without 'probability' raises MapFormatError naming the file and the key."""
    from core.errors import MapFormatError

    p = tmp_path / "bad.npz"
    np.savez(p, observed=np.ones((2, 2), bool))
    with pytest.raises(MapFormatError, match="bad.npz.*probability"):
        load_npz(p)


def test_occupancy_grid_mcap_decodes_with_rosbags(tmp_path, rng):
    """The nav_msgs/OccupancyGrid written to MCAP decodes with rosbags to the same classes, size,
    resolution and origin (row 0 = lowest y, as OccupancyGrid.data)."""
    from mcap.reader import make_reader
    from rosbags.typesys import Stores, get_typestore

    from slam.logs.mcap_writer import McapLogWriter

    m = _random_map(rng)
    path = tmp_path / "map.mcap"
    with McapLogWriter(path) as w:
        write_occupancy_grid(m, w, topic="/map", stamp=12.5)
    ts = get_typestore(Stores.ROS2_HUMBLE)
    with open(path, "rb") as fh:
        msgs = [(ch.topic, sc.name, msg.data) for sc, ch, msg in make_reader(fh).iter_messages()]
    assert len(msgs) == 1 and msgs[0][0] == "/map" and msgs[0][1] == "nav_msgs/msg/OccupancyGrid"
    grid = ts.deserialize_cdr(msgs[0][2], "nav_msgs/msg/OccupancyGrid")
    assert (grid.info.width, grid.info.height) == (m.geometry.shape[1], m.geometry.shape[0])
    assert grid.info.resolution == pytest.approx(m.resolution)
    assert (grid.info.origin.position.x, grid.info.origin.position.y) == pytest.approx(tuple(m.origin))
    np.testing.assert_array_equal(np.asarray(grid.data, np.int8).reshape(m.geometry.shape), m.classes())
    assert grid.header.stamp.sec == 12 and grid.header.stamp.nanosec == 500_000_000


def test_auc_matches_sklearn(rng):
    """AUC and ROC points equal scikit-learn's roc_auc_score / roc_curve, including tied scores."""
    from sklearn.metrics import roc_auc_score
    from sklearn.metrics import roc_curve as sk_roc

    y = rng.random(2000) < 0.3
    s = np.round(rng.normal(y * 1.0, 1.0), 1)  # rounding creates ties
    assert roc_auc(s, y) == pytest.approx(roc_auc_score(y, s), abs=1e-12)
    fpr, tpr, _ = roc_curve(s, y)
    f2, t2, _ = sk_roc(y, s, drop_intermediate=False)
    np.testing.assert_allclose(fpr, f2)
    np.testing.assert_allclose(tpr, t2)


def test_map_roc_ignores_unknown_and_perfect_map():
    """A map equal to the ground truth has AUC 1, its inverse 0, and unknown ground-truth cells never count."""
    gt = np.array([[100, 0, -1], [0, 100, -1]], np.int8)
    p = np.array([[0.9, 0.1, 0.99], [0.2, 0.8, 0.0]])
    assert map_roc(p, gt)[2] == 1.0
    assert map_roc(1 - p, gt)[2] == 0.0


def test_resample_identity_and_shift():
    """Resampling onto the same grid is the identity on observed cells; a grid shifted by whole cells
    reads the shifted cells, and cells outside the map get 0.5."""
    p = np.arange(12, dtype=float).reshape(3, 4) / 12
    obs = np.ones((3, 4), bool)
    np.testing.assert_array_equal(resample_to_grid(p, obs, np.array([0.0, 0.0]), 0.5, (3, 4), np.array([0.0, 0.0]), 0.5), p)
    r = resample_to_grid(p, obs, np.array([0.0, 0.0]), 0.5, (3, 4), np.array([0.5, 0.0]), 0.5)
    np.testing.assert_array_equal(r[:, :3], p[:, 1:])
    assert np.all(r[:, 3] == 0.5)


def test_bcm_fusion_identities(rng):
    """BCM: fusing with an infinite-variance estimate changes nothing; fusing two equal estimates halves the
    variance; information-form accumulation equals pairwise fusion; the squash is 0.5 at μ = 0 and
    approaches Φ(μ/σ) for α → ∞."""
    m1, v1 = rng.normal(size=50), rng.uniform(0.1, 2, 50)
    m2, v2 = rng.normal(size=50), rng.uniform(0.1, 2, 50)
    m, v = fuse(m1, v1, m2, np.full(50, np.inf))
    np.testing.assert_allclose(m, m1)
    np.testing.assert_allclose(v, v1)
    m, v = fuse(m1, v1, m1, v1)
    np.testing.assert_allclose(v, v1 / 2)
    info, prec = np.zeros(50), np.zeros(50)
    add_estimate(info, prec, m1, v1)
    add_estimate(info, prec, m2, v2)
    mi, vi = mean_variance(info, prec)
    mf, vf = fuse(m1, v1, m2, v2)
    np.testing.assert_allclose(mi, mf)
    np.testing.assert_allclose(vi, vf)
    assert np.all(probit_squash(np.zeros(5), np.ones(5)) == 0.5)
    from scipy.stats import norm

    np.testing.assert_allclose(probit_squash(m1, v1, alpha=1e6), norm.cdf(m1 / np.sqrt(v1)), atol=1e-6)


def test_cli_map_and_eval(tmp_path):
    """`slam map` on a simulated MCAP log writes every export file, and `slam eval map` prints `auc: X`
    with the map agreeing with the simulator's ground truth on the observed cells (AUC > 0.9)."""
    from typer.testing import CliRunner

    from evaluation.sim import LASER_PRESETS, load_world
    from evaluation.sim.simulate import simulate
    from slam.cli import app
    from slam.logs.simulated import write_simulated_log

    world = load_world("rooms", 0.05, seed=2)
    sim = simulate(world, n_scans=40, spec=LASER_PRESETS["fastgpom"], seed=2)
    log = tmp_path / "sim.mcap"
    write_simulated_log(sim, log)
    out = tmp_path / "out"
    runner = CliRunner()
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text("gp:\n  hyperparameters: fixed\n")
    r = runner.invoke(app, ["map", str(log), "--out", str(out), "--every", "4", "--config", str(cfg)])
    assert r.exit_code == 0, r.output
    for name in ("map.pgm", "map.yaml", "map.png", "variance.png", "map.npz", "map.mcap", "mapping_config.yaml"):
        assert (out / name).exists(), name
    gt_yaml = next(tmp_path.glob("*_map.yaml"))
    r = runner.invoke(app, ["eval", "map", str(out / "map.npz"), str(gt_yaml), "--plot", str(tmp_path / "roc.png")])
    assert r.exit_code == 0, r.output
    auc = float(next(line for line in r.output.splitlines() if line.startswith("auc: ")).split()[1])
    assert 0.0 <= auc <= 1.0
    from mapping.mapserver import read_map_server

    m = load_npz(out / "map.npz")
    gt = read_map_server(gt_yaml)
    p = resample_to_grid(m.probability, m.observed, m.origin, m.resolution, gt.shape, gt.origin[:2], gt.resolution)
    o = resample_to_grid(m.observed.astype(float), np.ones_like(m.observed), m.origin, m.resolution, gt.shape,
                         gt.origin[:2], gt.resolution)
    assert map_roc(np.where(o == 1, p, np.nan), gt.classes)[2] > 0.9
    # The other scores of the same run: auc_observed is the AUC over the observed cells just computed, and
    # coverage the observed share of the ground truth's free cells.
    got = {line.split(":")[0]: line.split(":", 1)[1].split()[0] for line in r.output.splitlines() if ":" in line}
    assert float(got["auc_observed"]) == pytest.approx(map_roc(np.where(o == 1, p, np.nan), gt.classes)[2], abs=1e-6)
    free = gt.classes == 0
    assert float(got["coverage"]) == pytest.approx((free & (o == 1)).sum() / free.sum(), abs=1e-4)
    assert 0.5 <= float(got["accuracy"]) <= 1.0 and 0.0 < float(got["f1"]) <= 1.0


def test_cli_map_tum_poses_equal_ground_truth(tmp_path):
    """`slam map --poses FILE.tum` with the simulator's ground truth written as TUM builds the same map as
    `--poses ground_truth` (stamps matched to scans)."""
    from typer.testing import CliRunner

    from core.trajectory import Trajectory, write_tum
    from evaluation.sim import LASER_PRESETS, load_world
    from evaluation.sim.simulate import simulate
    from slam.cli import app
    from slam.logs.simulated import write_simulated_log

    world = load_world("rooms", 0.05, seed=4)
    sim = simulate(world, n_scans=12, spec=LASER_PRESETS["fastgpom"], seed=4)
    log = tmp_path / "sim.mcap"
    write_simulated_log(sim, log)
    write_tum(tmp_path / "gt.tum", Trajectory(sim.stamps, sim.ground_truth))
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text("gp:\n  hyperparameters: fixed\n")
    runner = CliRunner()
    for name, poses in (("a", "ground_truth"), ("b", str(tmp_path / "gt.tum"))):
        r = runner.invoke(app, ["map", str(log), "--out", str(tmp_path / name), "--poses", poses, "--config", str(cfg),
                                "--every", "3"])
        assert r.exit_code == 0, r.output
    a, b = load_npz(tmp_path / "a" / "map.npz"), load_npz(tmp_path / "b" / "map.npz")
    assert a.geometry == b.geometry
    np.testing.assert_allclose(a.probability, b.probability, atol=1e-9)


def test_max_pooling_keeps_every_one_cell_wall_and_leaves_free_blocks_free():
    """A 4000 × 3000 free map with a one-cell wall row, a one-cell wall column and an unobserved corner, pooled
    by 5: the wall is in every pooled row / column it crosses, nothing else rises above the free value, and a
    block is unobserved exactly when none of its cells was observed."""
    from mapping.occupancy_map import max_pool

    p = np.full((4000, 3000), 0.05)
    p[1234, :] = 0.95
    p[:, 2718] = 0.9
    obs = np.ones(p.shape, bool)
    obs[:1000, :1000] = False
    q, seen = max_pool(p, obs, 5)
    assert q.shape == seen.shape == (800, 600)
    assert np.all(q[1234 // 5, 200:] == 0.95) and np.all(q[200:, 2718 // 5][q[200:, 2718 // 5] < 0.95] == 0.9)
    free = np.ones(q.shape, bool)
    free[1234 // 5, :] = False
    free[:, 2718 // 5] = False
    assert np.all(q[free & seen] == 0.05)
    assert not seen[:200, :200].any() and seen[200:, :].all() and seen[:, 200:].all()
    # A partly observed block counts its observed cells only.
    obs2 = np.zeros((10, 10), bool)
    obs2[0, 0] = True
    q2, seen2 = max_pool(np.where(obs2, 0.2, 0.99), obs2, 5)
    assert q2[0, 0] == 0.2 and seen2.tolist() == [[True, False], [False, False]]
    # Sizes that are not multiples of the block, and no mask.
    q3, none = max_pool(np.arange(7 * 11, dtype=float).reshape(7, 11), None, 3)
    assert none is None and q3.shape == (3, 4) and q3[-1, -1] == 76.0 and q3[0, 0] == 24.0


def test_the_png_of_a_large_map_shows_its_walls(tmp_path):
    """map.png of a 200 m × 150 m map at 5 cm (4000 × 3000 cells, ~840 px wide figure): a one-cell wall across
    the map is drawn as dark pixels along most of the axes width."""
    import matplotlib.image as mpimg

    p = np.full((3000, 4000), 0.05)
    p[1501, :] = 0.95  # an odd row: keeping every other cell would drop it
    m = OccupancyMap(GridGeometry((0.0, 0.0), 0.05, p.shape), p, None, None, np.ones(p.shape, bool), "logodds")
    export_map(m, tmp_path)
    img = mpimg.imread(tmp_path / "map.png")[..., :3].mean(axis=2)
    dark_per_row = (img < 0.3).sum(axis=1)
    spanning = np.flatnonzero(dark_per_row > 400)  # the axes' top and bottom spines, and the wall between them
    assert len(spanning) >= 2, dark_per_row.max()
    top, bottom = spanning.min(), spanning.max()
    inside = spanning[(spanning > top + 5) & (spanning < bottom - 5)]
    assert len(inside) and abs(inside.mean() - 0.5 * (top + bottom)) < 5  # the wall, halfway up the map


def test_map_scores_in_closed_form():
    """Four free and two occupied known cells, one unknown: a perfect map observed everywhere scores 1 on every
    count; unobserved cells drag the AUC towards 0.5 but not the AUC of the observed cells; the best accuracy
    and F1 are those of the best threshold, counted by hand."""
    from mapping.roc import map_scores

    gt = np.array([[0, 0, 0, 0, 100, 100, -1]], dtype=np.int8)
    perfect = np.array([[0.1, 0.2, 0.1, 0.3, 0.9, 0.8, 0.5]])
    s = map_scores(perfect, np.ones(gt.shape, bool), gt)
    assert (s.auc, s.auc_observed, s.coverage, s.accuracy, s.f1) == (1.0, 1.0, 1.0, 1.0, 1.0)
    assert 0.3 < s.f1_threshold <= 0.8 and 0.3 < s.accuracy_threshold <= 0.8
    # Two free cells and one occupied unobserved (p = 0.5 there).
    obs = np.array([[True, True, False, False, True, False, True]])
    p = np.where(obs, perfect, 0.5)
    s = map_scores(p, obs, gt)
    assert s.auc_observed == 1.0 and s.coverage == 0.5
    # Scores: free 0.1 0.2 0.5 0.5, occupied 0.9 0.5 → Mann–Whitney: 8 pairs, 6 wins, 2 ties: (6 + 1) / 8.
    assert s.auc == pytest.approx(7 / 8)
    # Best threshold 0.9: TP 1, FP 0, FN 1, TN 4 → accuracy 5/6, F1 2/3; at 0.5: TP 2, FP 2 → accuracy 4/6, F1 2/3.
    assert s.accuracy == pytest.approx(5 / 6) and s.accuracy_threshold == pytest.approx(0.9)
    assert s.f1 == pytest.approx(2 / 3)
    # All observed cells of one class: no AUC of the observed cells.
    only_free = np.array([[True, True, True, True, False, False, False]])
    assert map_scores(perfect, only_free, gt).auc_observed is None


def test_map_scores_coverage_leaves_out_specks_of_free_space():
    """A 2 × 2 m free room (walled) and one free cell walled in beside it: at the plan's resolution the speck
    is not free space, so a map that saw the room whole has coverage 1; counting every free cell, 1600/1601."""
    from mapping.roc import free_space, map_scores

    gt = np.full((44, 50), 100, dtype=np.int8)
    gt[2:42, 2:42] = 0  # 40 × 40 cells of 5 cm
    gt[20, 46] = 0  # the speck, behind the wall
    space, n, area = free_space(gt, 0.05)
    assert space.sum() == 1600 and n == 1 and area == pytest.approx(0.0025) and not space[20, 46]
    obs = gt == 0
    obs[20, 46] = False
    p = np.where(gt == 0, 0.1, 0.9)
    assert map_scores(p, obs, gt, 0.05).coverage == 1.0
    assert map_scores(p, obs, gt).coverage == pytest.approx(1600 / 1601)


def test_cli_map_plot_trajectory_draws_the_path(tmp_path):
    """`slam map --plot-trajectory` draws the robot's path on map.png: red pixels where the plain map has
    none, as many as a line along the path's length at the figure's scale."""
    import matplotlib.image as mpimg
    from typer.testing import CliRunner

    from evaluation.sim import LASER_PRESETS, load_world
    from evaluation.sim.simulate import simulate
    from slam.cli import app
    from slam.logs.simulated import write_simulated_log

    world = load_world("rooms", 0.05, seed=3)
    sim = simulate(world, n_scans=200, spec=LASER_PRESETS["fastgpom"], seed=3)
    log = tmp_path / "sim.mcap"
    write_simulated_log(sim, log)
    runner = CliRunner()

    def red_pixels(folder, *extra):
        r = runner.invoke(app, ["map", str(log), "--out", str(folder), "--every", "5", "--method", "logodds", *extra])
        assert r.exit_code == 0, r.output
        img = mpimg.imread(folder / "map.png")[..., :3]
        return int(((img[..., 0] > 0.6) & (img[..., 1] < 0.4) & (img[..., 2] < 0.4)).sum())

    assert red_pixels(tmp_path / "plain") == 0
    path_m = float(np.sum(np.linalg.norm(np.diff(sim.ground_truth[::5, :2, 3], axis=0), axis=1)))
    assert path_m > 2.0  # the tour moves
    assert red_pixels(tmp_path / "with", "--plot-trajectory") > 10 * path_m
