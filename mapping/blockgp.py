"""Local GP prediction over beam-ordered samples: overlapping angular blocks, solved in one batch.

Exploits locality (the screening effect of a Matérn kernel with dense samples, cf. Vecchia / local
GP experts): the ring samples of Fast-GPOM are ordered by beam, and a test cell on beam sector j
is predicted by an exact GP (R&W Alg. 2.1) trained only on the samples of beams
[j·S − O, (j+1)·S + O). All blocks are padded to one size (padding rows are identity rows that do
not couple) and factorised by a single batched LAPACK call. ``tests/test_mapping_fastgpom.py``
and ``benchmarks/mapping.py`` measure the difference to the one-GP prediction.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from .gp import GPHyperparameters

Array = NDArray[np.float64]


def block_gp_predict(
    hyp: GPHyperparameters,
    X: Array,
    y: Array,
    x_beam: NDArray[np.int64],
    Xs: Array,
    s_beam: NDArray[np.int64],
    n_beams: int,
    block: int = 24,
    overlap: int = 16,
) -> tuple[Array, Array]:
    """Latent mean and variance at ``Xs`` from local GPs over beam blocks.

    Args:
        X, y: training points (n, 2) and labels (n,); ``x_beam`` their beam index.
        Xs: test points (m, 2); ``s_beam`` the beam sector each lies in.
        n_beams: number of beams; block / overlap: beams per block and extra beams on each side.
    """
    kern = hyp.kernel
    nb = max(1, -(-n_beams // block))
    sblk = np.minimum(s_beam // block, nb - 1).astype(np.int64)
    present = np.bincount(sblk, minlength=nb) > 0  # only blocks that hold test points
    used = np.flatnonzero(present)
    qb = (np.cumsum(present) - 1)[sblk]
    lo = used * block - overlap
    hi = (used + 1) * block + overlap
    order = np.argsort(x_beam, kind="stable")
    xb_sorted = x_beam[order]
    s = np.searchsorted(xb_sorted, lo, "left")
    e = np.searchsorted(xb_sorted, hi, "left")
    cnt = e - s
    P = max(1, int(cnt.max()))
    pos = s[:, None] + np.arange(P)[None, :]
    tmask = np.arange(P)[None, :] < cnt[:, None]
    tidx = order[np.minimum(pos, len(order) - 1)]
    Xb = X[tidx]  # (nu, P, 2)
    # kernel entries in float32 (relative error ~1e-7·σf², far below σn²); solves in float64
    Xb32 = Xb.astype(np.float32)
    yb = np.where(tmask, y[tidx], 0.0)
    dx = Xb32[:, :, None, 0] - Xb32[:, None, :, 0]
    dy = Xb32[:, :, None, 1] - Xb32[:, None, :, 1]
    dx *= dx
    dy *= dy
    dx += dy
    K = kern.of_distance_inplace(np.sqrt(dx, out=dx)).astype(np.float64)
    K *= tmask[:, :, None] & tmask[:, None, :]
    ii = np.arange(P)
    K[:, ii, ii] += np.where(tmask, hyp.sigma_n**2, 1.0)  # padding rows: identity, uncoupled
    Kinv = np.linalg.inv(K)  # (nu, P, P)
    alpha = np.einsum("bij,bj->bi", Kinv, yb)
    # kernel rows of every test point to its block's training points, in one gather
    Xg = Xb32[qb]  # (m, P, 2)
    Xs32 = Xs.astype(np.float32)
    dx = Xs32[:, None, 0] - Xg[:, :, 0]
    dy = Xs32[:, None, 1] - Xg[:, :, 1]
    dx *= dx
    dy *= dy
    dx += dy
    Ks = kern.of_distance_inplace(np.sqrt(dx, out=dx)).astype(np.float64)
    Ks *= tmask[qb]
    mean = np.einsum("mp,mp->m", Ks, alpha[qb])
    KsKinv = np.matmul(Ks[:, None, :], Kinv[qb])[:, 0, :]  # (m, P): batched row-vector products
    var = kern.variance - np.einsum("mp,mp->m", KsKinv, Ks)
    return mean, np.maximum(var, 0.0)
