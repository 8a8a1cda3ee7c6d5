"""Log-odds baseline: inverse sensor model along beams, clamping, and separation of walls from free space."""

from __future__ import annotations

import numpy as np
import pytest

from core.frame import Frame
from core.geometry import xytheta_to_matrix
from mapping.config import MappingConfig
from mapping.grid import GridGeometry
from mapping.logodds import LogOddsGrid
from tests.test_mapping_fastgpom import box_world, cast


@pytest.fixture(autouse=True)
def single_blas_thread():
    """Batched small LAPACK calls thrash with several BLAS threads on the shared 2-core machine."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(1):
        yield


def test_single_beam_free_then_occupied():
    """One beam along +x hitting at 1.02 m: cells it crosses get l_free once, the hit cell l_occ, cells
    behind the hit and beside the beam stay 0."""
    g = GridGeometry((-0.5, -0.5), 0.1, (10, 30))
    f = Frame(0.0, np.array([[1.02, 0.0]]), angles=np.array([0.0]), ranges=np.array([1.02]), max_range=4.0)
    m = LogOddsGrid(g)
    m.update(f, np.eye(4))
    lc = m.config.logodds
    iy, ix = g.world_to_cell(np.array([[0.05, 0.0], [0.55, 0.0], [1.02, 0.0], [1.5, 0.0], [0.5, 0.3]]))
    np.testing.assert_allclose(m.logodds[iy, ix], [lc.l_free, lc.l_free, lc.l_occ, 0.0, 0.0])


def test_clamping():
    """Repeating the same scan never pushes the log odds outside [l_min, l_max]."""
    geom, occ, _ = box_world(0.1)
    f = cast(geom, occ, (0.0, 0.0, 0.0), n_beams=91)
    m = LogOddsGrid(geom)
    for _ in range(20):
        m.update(f, xytheta_to_matrix(0.0, 0.0, 0.0))
    lc = m.config.logodds
    assert m.logodds.min() >= lc.l_min and m.logodds.max() <= lc.l_max
    assert m.logodds.min() == lc.l_min and m.logodds.max() == lc.l_max


def test_separates_walls_from_free():
    """After scans from a few poses, observed cells rank walls above free space (AUC ≥ 0.95)."""
    from mapping.roc import roc_auc

    geom, occ, known = box_world(0.05)
    m = LogOddsGrid(geom, MappingConfig())
    for p in [(-2.0, -2.0, 0.3), (2.2, 2.2, -2.0), (0.0, 2.0, -1.5)]:
        m.update(cast(geom, occ, p), xytheta_to_matrix(*p))
    mp = m.to_map()
    sel = mp.observed & known
    assert roc_auc(mp.probability[sel], occ[sel]) >= 0.95
