"""Fast-GPOM and classic GPOM on synthetic scans: regions A/B/C, locality error, map quality."""

from __future__ import annotations

import numpy as np
import pytest

from core.frame import Frame
from core.geometry import xytheta_to_matrix
from mapping.beams import beam_samples
from mapping.config import MappingConfig
from mapping.fastgpom import FastGPOM, fan_regions
from mapping.gp import GPHyperparameters
from mapping.gpom import ClassicGPOM
from mapping.grid import GridGeometry


@pytest.fixture(autouse=True)
def single_blas_thread():
    """Batched small LAPACK calls thrash with several BLAS threads on the shared 2-core machine."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(1):
        yield

HYP = GPHyperparameters(3.5, 1.90, 8.13, 0.226)  # the reference code's constants


def box_world(res: float = 0.05):
    """A 6 m × 6 m room (walls at x,y = ±3 m) with a 1 m square pillar centred at (1.5, 0)."""
    n = int(round(8 / res))
    geom = GridGeometry((-4.0, -4.0), res, (n, n))
    xc = geom.centres_x()
    yc = geom.centres_y()
    X, Y = np.meshgrid(xc, yc)
    occ = (np.abs(X) >= 3.0) & (np.abs(X) < 3.0 + 2 * res) & (np.abs(Y) < 3.0 + 2 * res)
    occ |= (np.abs(Y) >= 3.0) & (np.abs(Y) < 3.0 + 2 * res) & (np.abs(X) < 3.0 + 2 * res)
    occ |= (np.abs(X - 1.5) <= 0.5) & (np.abs(Y) <= 0.5)
    known = (np.abs(X) < 3.0 + 2 * res) & (np.abs(Y) < 3.0 + 2 * res)
    return geom, occ, known


def cast(geom, occ, pose, n_beams=667, fov=np.deg2rad(240), max_range=4.09, step=None):
    """Ray-march a 2D scan through an occupancy array (vectorised; test scaffolding only)."""
    step = step or geom.resolution / 4
    angles = np.linspace(-fov / 2, fov / 2, n_beams)
    s = np.arange(1, int(max_range / step) + 1) * step
    th = pose[2] + angles
    px = pose[0] + np.cos(th)[:, None] * s[None, :]
    py = pose[1] + np.sin(th)[:, None] * s[None, :]
    iy, ix = geom.world_to_cell(np.stack([px, py], -1))
    ok = geom.inside(iy, ix)
    hit = np.zeros_like(ok)
    hit[ok] = occ[iy[ok], ix[ok]]
    first = np.where(hit.any(1), hit.argmax(1), -1)
    ranges = np.where(first >= 0, s[np.maximum(first, 0)], np.inf)
    nr = first < 0
    pts = np.column_stack([np.cos(angles), np.sin(angles)])[~nr] * ranges[~nr, None]
    return Frame(stamp=0.0, points=pts, angles=angles, ranges=ranges, no_return=nr, max_range=max_range,
                 min_range=0.06)


def test_region_c_untouched_behind_wall():
    """Cells behind the pillar (seen from the robot) keep the prior after a Fast-GPOM update, while
    classic GPOM writes into them (the defect of the Fast-GPOM paper's Fig. 1)."""
    geom, occ, _ = box_world()
    pose = (-1.0, 0.0, 0.0)
    frame = cast(geom, occ, pose)
    fg = FastGPOM(geom, hyperparameters=HYP)
    fg.update(frame, xytheta_to_matrix(*pose))
    iy, ix = geom.world_to_cell(np.array([[2.5, 0.0], [2.4, 0.2], [2.2, -0.2]]))  # behind the pillar
    assert np.all(fg.grid.prec[iy, ix] == 0)
    assert np.all(fg.grid.info[iy, ix] == 0)
    front_iy, front_ix = geom.world_to_cell(np.array([[0.0, 0.0]]))  # in front: region A, observed free
    assert fg.grid.prec[front_iy, front_ix] > 0 and fg.grid.info[front_iy, front_ix] < 0
    cg = ClassicGPOM(geom, hyperparameters=HYP)
    cg.update(frame, xytheta_to_matrix(*pose))
    assert np.all(cg.grid.prec[iy, ix] > 0)


def test_regions_partition_the_fan():
    """Region A lies strictly inside the last free samples' fan, B between that and the hits; A∩B = ∅,
    and every hit point's own cell is in region B (cells containing walls are updated)."""
    geom, occ, _ = box_world()
    frame = cast(geom, occ, (-1.0, 0.3, 0.4))
    bs = beam_samples(frame, 0.05)
    hx, hy = bs.hit_xy.T
    A, B, _ = fan_regions(bs, hx, hy, 0.5 * np.sqrt(2) * 0.05)
    assert not A.any()
    assert B[1:-1].mean() > 0.99
    ix = bs.inner_xy * 0.999
    A2, B2, _ = fan_regions(bs, ix[:, 0], ix[:, 1], 0.035)
    assert A2[1:-1][bs.inner[1:-1] > 0].all() and not (A2 & B2).any()


def test_free_samples_stop_before_hit():
    """Free samples are spaced d along each beam and end at least 1.5·d (and less than 2.5·d) before the
    hit; beams without a return are sampled up to the maximum range."""
    geom, occ, _ = box_world()
    frame = cast(geom, occ, (0.0, 0.0, 0.0))
    d = 0.1
    bs = beam_samples(frame, d)
    gap = bs.outer[bs.hit] - bs.inner[bs.hit]
    assert np.all(gap >= 1.5 * d - 1e-9) and np.all(gap < 2.5 * d + 1e-9)
    r = np.hypot(*bs.free_xy.T)
    assert np.allclose(np.round(r / d), r / d)
    frame2 = Frame(0.0, np.zeros((0, 2)), angles=np.array([0.0, 0.1]), ranges=np.array([np.inf, np.inf]),
                   max_range=4.0)
    bs2 = beam_samples(frame2, d)
    assert np.allclose(bs2.inner, 4.0) and not bs2.hit.any()


def test_block_gp_close_to_exact():
    """The local-block GP (strided ring samples) agrees with one exact GP on all ring samples: region B
    means have the same sign on ≥ 98 % of cells and a median difference < 0.05 (labels ±1), and the
    fused probability maps agree on ≥ 99 % of the updated cells."""
    geom, occ, _ = box_world()
    frame = cast(geom, occ, (-1.0, 0.5, 0.3))
    pose = xytheta_to_matrix(-1.0, 0.5, 0.3)
    a = FastGPOM(geom, hyperparameters=HYP)
    cfg = MappingConfig()
    cfg.fastgpom.exact_gp = True
    b = FastGPOM(geom, cfg, hyperparameters=HYP)
    ra = a.local_estimate(frame, pose)
    rb = b.local_estimate(frame, pose)
    assert np.array_equal(ra[2], rb[2])
    inB = rb[3] != cfg.fastgpom.region_a_mean
    assert np.mean(np.sign(ra[3][inB]) == np.sign(rb[3][inB])) >= 0.98
    assert np.median(np.abs(ra[3][inB] - rb[3][inB])) < 0.05
    a.update(frame, pose)
    b.update(frame, pose)
    m = a.grid.prec > 0
    agree = (a.to_map().probability[m] > 0.5) == (b.to_map().probability[m] > 0.5)
    assert agree.mean() > 0.99


def test_map_quality_on_synthetic_room():
    """After a short loop in the room, Fast-GPOM separates walls from free space: AUC ≥ 0.95 over
    observed ground-truth-known cells, and classic GPOM also exceeds 0.9."""
    from mapping.roc import roc_auc

    geom, occ, known = box_world()
    poses = [(-2.0, -2.0, 0.3), (-2.0, 2.0, -0.5), (0.0, -2.2, 1.2), (2.2, 2.2, -2.0), (2.2, -2.2, 2.0)]
    fg = FastGPOM(geom, hyperparameters=HYP)
    cg = ClassicGPOM(geom, hyperparameters=HYP)
    for p in poses:
        f = cast(geom, occ, p)
        fg.update(f, xytheta_to_matrix(*p))
        cg.update(f, xytheta_to_matrix(*p))
    gt = np.where(occ, 100, 0).astype(np.int8)
    gt[~known] = -1
    mf = fg.to_map()
    sel = mf.observed & known
    assert roc_auc(mf.probability[sel], occ[sel]) >= 0.95
    mc = cg.to_map()
    assert roc_auc(mc.probability[sel], occ[sel]) >= 0.9


def test_region_a_prior_is_configurable():
    """After one scan every region-A cell holds exactly the configured (μ, σ²) of region A, e.g. (−1, 0.2),
    and region-B cells hold GP estimates with variance below the prior variance σf²."""
    geom, occ, _ = box_world()
    cfg = MappingConfig()
    cfg.fastgpom.region_a_variance = 0.2
    fg = FastGPOM(geom, cfg, hyperparameters=HYP)
    frame = cast(geom, occ, (-1.0, 0.0, 0.2))
    rows, cols, sel, mean, var = fg.local_estimate(frame, xytheta_to_matrix(-1.0, 0.0, 0.2))
    fg.update(frame, xytheta_to_matrix(-1.0, 0.0, 0.2))
    m = fg.to_map()
    a_cells = sel[(mean == -1.0) & (var == 0.2)]
    assert len(a_cells) > 0.5 * len(sel)
    iy, ix = np.unravel_index(a_cells, (rows.stop - rows.start, cols.stop - cols.start))
    np.testing.assert_allclose(m.mean[rows, cols][iy, ix], -1.0)
    np.testing.assert_allclose(m.variance[rows, cols][iy, ix], 0.2)
    b = var != 0.2
    assert np.all(var[b] < HYP.sigma_f**2)


def test_fit_subset_thinned_by_beam(monkeypatch):
    """The first-frame fit sees at most fit_max_points samples, thinned by whole beams: every kept beam
    contributes both its hit (+1) and its last free sample (−1)."""
    import mapping.gaussian_grid as gg
    from mapping.config import GPConfig
    from mapping.fastgpom import ring_training_set

    geom, occ, _ = box_world()
    bs = beam_samples(cast(geom, occ, (0.0, 0.0, 0.0)), 0.05)
    X, y, xb = ring_training_set(bs)
    seen = {}

    def fake_fit(Xf, yf, start, **kw):
        seen["X"], seen["y"] = Xf, yf
        return start

    monkeypatch.setattr(gg, "fit_hyperparameters", fake_fit)
    gg.initial_hyperparameters(GPConfig(fit_max_points=200), X, y, xb)
    Xf, yf = seen["X"], seen["y"]
    assert len(Xf) <= 200
    rows = {tuple(p): b for p, b in zip(X, xb)}
    kept = np.array([rows[tuple(p)] for p in Xf])
    for b in np.unique(kept):
        both = (yf[kept == b] > 0).any() and (yf[kept == b] < 0).any()
        assert both or not (bs.hit[b] and bs.inner[b] > 0)


def test_a_fit_that_calls_hits_free_gives_way_to_the_configured_values():
    """On a ring whose hits the likelihood's optimum would smooth away (the fit is forced here to a long,
    noisy model), the configured values are used instead, with a warning; a fit that separates the
    labels is kept."""
    import warnings

    from mapping import gaussian_grid
    from mapping.config import GPConfig
    from mapping.gaussian_grid import initial_hyperparameters, label_accuracy

    geom, occ, _ = box_world()
    frame = cast(geom, occ, (-1.0, 0.3, 0.4))
    from mapping.fastgpom import ring_training_set

    X, y, beams = ring_training_set(beam_samples(frame, 0.05), 2)
    smooth = GPHyperparameters(3.5, 15.0, 1.0, 0.9)
    assert label_accuracy(smooth, X, y) < label_accuracy(HYP, X, y)
    cfg = GPConfig()
    orig = gaussian_grid.fit_hyperparameters
    try:
        gaussian_grid.fit_hyperparameters = lambda *a, **k: smooth
        with pytest.warns(UserWarning, match="worse than the configured values"):
            got = initial_hyperparameters(cfg, X, y, beams)
        assert (got.length_scale, got.sigma_f, got.sigma_n) == (cfg.length_scale_m, cfg.sigma_f, cfg.sigma_n)
        sharp = GPHyperparameters(3.5, 0.1, 1.2, 0.01)
        gaussian_grid.fit_hyperparameters = lambda *a, **k: sharp
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            assert initial_hyperparameters(cfg, X, y, beams) is sharp
    finally:
        gaussian_grid.fit_hyperparameters = orig
