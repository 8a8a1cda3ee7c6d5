"""Connected components of a pose graph, and the nodes that fix the gauge of each.

A pose graph determines its poses only up to one rigid motion per connected component (Grisetti et
al., "A tutorial on graph-based SLAM", 2010, §IV-B: H is singular along the gauge). A component with a
prior edge or a FIX'ed node is held by it; every other component needs one node held. A connected
graph without priors or FIX is held at its first node, as before; a graph with more free components
than that has parts whose relative placement nothing in the file determines.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray
from scipy.sparse.csgraph import connected_components

__all__ = ["component_labels", "free_component_anchors"]


def component_labels(n: int, ii: NDArray[np.int64], jj: NDArray[np.int64]) -> NDArray[np.int64]:
    """Component label (0, 1, … in order of first node) of each of *n* nodes joined by edges (ii, jj) of
    node indices; prior edges (ii < 0) join nothing."""
    keep = ii >= 0
    A = sp.coo_matrix((np.ones(int(keep.sum())), (ii[keep], jj[keep])), shape=(n, n))
    _, labels = connected_components(A, directed=False)
    _, first = np.unique(labels, return_index=True)  # relabel by first node, so labels are stable
    order = np.argsort(first)
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return rank[labels].astype(np.int64)


def free_component_anchors(labels: NDArray[np.int64], held: NDArray[np.int64]) -> NDArray[np.int64]:
    """The first node (index) of every component that contains none of the *held* node indices."""
    n_comp = int(labels.max()) + 1 if labels.size else 0
    free = np.ones(n_comp, dtype=bool)
    free[labels[held]] = False
    _, first = np.unique(labels, return_index=True)
    return np.sort(first[free]).astype(np.int64)
