"""Submap fuser: equivalence with a single map, pose updates without GP work, selective recomposition."""

from __future__ import annotations

import numpy as np
import pytest

from core.geometry import xytheta_to_matrix
from mapping.fastgpom import FastGPOM
from mapping.submaps import SubmapFuser
from tests.test_mapping_fastgpom import HYP, box_world, cast


@pytest.fixture(autouse=True)
def single_blas_thread():
    """Batched small LAPACK calls thrash with several BLAS threads on the shared 2-core machine."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(1):
        yield

POSES = [(-1.5, -1.0, 0.2), (-1.0, 1.0, -0.4), (1.0, -2.0, 1.0), (2.0, 2.0, -2.5)]


def _scans():
    geom, occ, _ = box_world(0.05)
    return geom, [(cast(geom, occ, p, n_beams=241), xytheta_to_matrix(*p)) for p in POSES]


def test_single_identity_submap_equals_direct_map():
    """One submap anchored at the world origin on a cell-aligned grid reproduces the direct Fast-GPOM
    map exactly (BCM information form is a sum; resampling is the identity)."""
    geom, scans = _scans()
    direct = FastGPOM(geom, hyperparameters=HYP)
    fuser = SubmapFuser(geom, submap_half_size=4.0, hyperparameters=HYP)
    fuser.add_submap(0, np.eye(4))
    for f, T in scans:
        direct.update(f, T)
        fuser.add_scan(0, f, T)
    a, b = direct.to_map(), fuser.to_map()
    assert np.array_equal(a.observed, b.observed)
    np.testing.assert_allclose(b.mean[a.observed], a.mean[a.observed], atol=1e-9)
    np.testing.assert_allclose(b.variance[a.observed], a.variance[a.observed], rtol=1e-9)


def test_update_poses_runs_no_gp_and_shifts_exactly(monkeypatch):
    """Moving one anchor by a whole number of cells shifts that submap's contribution by exactly those
    cells, re-places only that submap, and never calls the GP."""
    geom, scans = _scans()
    fuser = SubmapFuser(geom, submap_half_size=4.0, hyperparameters=HYP)
    for k, (f, T) in enumerate(scans):
        fuser.add_submap(k, T)
        fuser.add_scan(k, f, T)
    fuser.to_map()
    before = fuser.placed_values(2)
    import mapping.fastgpom as fg

    def boom(*a, **k):
        raise AssertionError("GP evaluated during update_poses")

    monkeypatch.setattr(fg, "block_gp_predict", boom)
    monkeypatch.setattr(fg.FastGPOM, "local_estimate", boom)
    shift = xytheta_to_matrix(0.0, 3 * 0.05, 0.0)  # +3 rows in world y
    anchors = {k: sm.world_T_anchor for k, sm in fuser.submaps.items()}
    anchors[2] = shift @ anchors[2]
    anchors[1] = anchors[1] @ xytheta_to_matrix(1e-5, 0.0, 0.0)  # below tolerance
    assert fuser.update_poses(anchors) == 1
    after = fuser.placed_values(2)
    assert np.array_equal(np.sort(after[0]), np.sort(before[0] + 3 * geom.shape[1]))
    np.testing.assert_allclose(np.sort(after[2]), np.sort(before[2]))


def test_incremental_equals_full_recompose():
    """After several pose updates the incrementally maintained global grid equals a from-scratch recomposition."""
    geom, scans = _scans()
    fuser = SubmapFuser(geom, submap_half_size=4.0, hyperparameters=HYP)
    for k, (f, T) in enumerate(scans):
        fuser.add_submap(k, T)
        fuser.add_scan(k, f, T)
    fuser.to_map()
    rng = np.random.default_rng(3)
    for _ in range(3):
        anchors = {k: xytheta_to_matrix(*rng.normal(0, [0.1, 0.1, 0.05])) @ sm.world_T_anchor
                   for k, sm in fuser.submaps.items()}
        fuser.update_poses(anchors)
    inc_info, inc_prec = fuser.info.copy(), fuser.prec.copy()
    fuser.recompose()
    np.testing.assert_allclose(inc_prec, fuser.prec, atol=1e-6)
    np.testing.assert_allclose(inc_info, fuser.info, atol=1e-6)


def test_scan_added_to_a_placed_submap_replaces_its_contribution():
    """A submap that receives a scan after it was placed is taken out of the global grid before its
    grid changes, so the incremental grid still equals a from-scratch recomposition (a stale
    contribution would leave the old values in, or subtract the new ones)."""
    geom, scans = _scans()
    fuser = SubmapFuser(geom, submap_half_size=4.0, hyperparameters=HYP)
    for k, (f, T) in enumerate(scans[:-1]):
        fuser.add_submap(k, T)
        fuser.add_scan(k, f, T)
    fuser.to_map()
    f, T = scans[-1]
    fuser.add_scan(0, f, T)
    m = fuser.to_map()
    inc_info, inc_prec = fuser.info.copy(), fuser.prec.copy()
    fuser.recompose()
    np.testing.assert_allclose(inc_prec, fuser.prec, atol=1e-6)
    np.testing.assert_allclose(inc_info, fuser.info, atol=1e-6)
    assert m.observed.sum() == (fuser.prec > 1e-9).sum()


def test_sealed_submaps_keep_the_map_and_leave_no_residue():
    """Sealing stores a placed submap in float32: the fused map moves by < 1e-6 relative, the global grid
    never holds a residue of the float64 values (after moves it equals a recomposition, and the cells
    seen are the same), and a scan added to a sealed submap accumulates in float64 again."""
    geom, scans = _scans()
    plain = SubmapFuser(geom, submap_half_size=4.0, hyperparameters=HYP)
    sealed = SubmapFuser(geom, submap_half_size=4.0, hyperparameters=HYP)
    for k, (f, T) in enumerate(scans):
        for fuser in (plain, sealed):
            fuser.add_submap(k, T)
            fuser.add_scan(k, f, T)
        sealed.to_map()  # placed in float64 first: sealing must take that contribution out
        sealed.seal(k)
    assert all(sm.mapper.grid.prec.dtype == np.float32 for sm in sealed.submaps.values())
    rng = np.random.default_rng(5)
    anchors = {k: xytheta_to_matrix(*rng.normal(0, [0.1, 0.1, 0.05])) @ sm.world_T_anchor
               for k, sm in plain.submaps.items()}
    a, b = plain.to_map(), sealed.to_map()
    plain.update_poses(anchors)
    sealed.update_poses(anchors)
    a, b = plain.to_map(), sealed.to_map()
    assert np.array_equal(a.observed, b.observed)
    np.testing.assert_allclose(b.probability, a.probability, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(b.variance[a.observed], a.variance[a.observed], rtol=1e-6)
    inc_prec = sealed.prec.copy()
    sealed.recompose()
    np.testing.assert_allclose(inc_prec, sealed.prec, atol=1e-9)
    f, T = scans[0]
    sealed.add_scan(0, f, T)
    assert sealed.submaps[0].mapper.grid.prec.dtype == np.float64


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_resampling_kernel_is_the_numpy_forms_cells_bit_for_bit(dtype):
    """The compiled resampling of a submap onto the world grid picks, for every world cell of the window, the
    submap cell that ``GridGeometry.window_in_frame`` + ``world_to_cell`` + ``inside`` pick (observed cells
    only), in the same order: random anchors, windows partly outside the submap, cell centres on cell borders."""
    from core.geometry import inverse
    from mapping.grid import GridGeometry
    from mapping.kernels import resample_cells

    rng = np.random.default_rng(7)
    world = GridGeometry((-12.35, 3.1), 0.05, (400, 500))
    sub = GridGeometry((-4.0, -4.0), 0.05, (160, 160))
    for k in range(40):
        prec = (rng.random(sub.shape) < 0.3).astype(dtype) * rng.random(sub.shape).astype(dtype)
        # quarter turns put centres exactly on the submap's cell borders; the rest at random headings
        theta = (k % 4) * np.pi / 2 if k < 8 else rng.uniform(-np.pi, np.pi)
        T = xytheta_to_matrix(np.array([rng.uniform(-10, 10), rng.uniform(5, 20), theta]))
        rows, cols = world.window(T[:2, 3], rng.uniform(2, 8))
        A = inverse(T)
        x, y = world.window_in_frame(rows, cols, A)
        iy, ix = sub.world_to_cell(np.stack([x, y], -1))
        sel = np.flatnonzero(sub.inside(iy, ix))
        want_local = (iy.ravel()[sel] * sub.shape[1] + ix.ravel()[sel]).astype(np.int32)
        keep = prec.reshape(-1)[want_local] > 0
        sel, want_local = sel[keep], want_local[keep]
        w = cols.stop - cols.start
        want_g = (rows.start + sel // w) * world.shape[1] + cols.start + sel % w
        g, local = resample_cells(rows.start, cols.start, rows.stop - rows.start, w, world.shape[1],
                                  world.origin[0], world.origin[1], world.resolution, A[0, 0], A[0, 1], A[1, 0],
                                  A[1, 1], A[0, 3], A[1, 3], sub.origin[0], sub.origin[1], sub.resolution, prec)
        assert len(want_g) > 0
        np.testing.assert_array_equal(g, want_g)
        np.testing.assert_array_equal(local, want_local)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_adding_a_placed_contribution_is_numpys_fancy_add_bit_for_bit(dtype):
    """The compiled add / subtract of a placed submap equals numpy's ``flat[g] += sign · values[local]`` over
    unique cells, for open (float64) and sealed (float32) submap grids; adding then subtracting restores the
    global grid exactly where it held sums of such values (here: zeros)."""
    from mapping.kernels import add_placed

    rng = np.random.default_rng(3)
    g = rng.permutation(5000)[:1200].astype(np.int32)
    local = rng.integers(0, 900, 1200).astype(np.int32)
    sub_info, sub_prec = rng.normal(size=900).astype(dtype), rng.random(900).astype(dtype)
    info, prec = rng.normal(size=5000), rng.random(5000)
    want_info, want_prec = info.copy(), prec.copy()
    for sign in (1.0, -1.0):
        want_info[g] += sign * sub_info[local]
        want_prec[g] += sign * sub_prec[local]
        add_placed(info, prec, g, local, sub_info, sub_prec, sign)
        np.testing.assert_array_equal(info, want_info)
        np.testing.assert_array_equal(prec, want_prec)
    zero_info, zero_prec = np.zeros(5000), np.zeros(5000)
    add_placed(zero_info, zero_prec, g, local, sub_info, sub_prec, 1.0)
    add_placed(zero_info, zero_prec, g, local, sub_info, sub_prec, -1.0)
    assert not zero_info.any() and not zero_prec.any()
