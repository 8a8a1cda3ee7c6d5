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
