"""Synthetic pose graphs and outlier injection shared by the graph/backend tests."""

from __future__ import annotations

import numpy as np

from core import geometry as geo
from slam.graph import PoseGraph


def random_poses(rng: np.random.Generator, n: int, dim: int, step: float = 1.0) -> np.ndarray:
    """A random-walk trajectory of *n* world_T_node poses (planar when dim = 2)."""
    if dim == 2:
        xyt = np.cumsum(np.column_stack([rng.normal(0, step, (n, 2)), rng.normal(0, 0.5, n)]), axis=0)
        return geo.xytheta_to_matrix(xyt)
    P = np.empty((n, 4, 4))
    P[0] = np.eye(4)
    for k in range(1, n):
        P[k] = P[k - 1] @ geo.se3_exp(np.concatenate([rng.normal(0, step, 3), rng.normal(0, 0.4, 3)]))
    return P


def synthetic_graph(rng: np.random.Generator, n: int, dim: int, loops: int, noise: float = 0.0,
                    info: np.ndarray | None = None, with_vertices: bool = True) -> tuple[PoseGraph, np.ndarray]:
    """A chain plus *loops* random loop edges over random_poses; measurements perturbed by Exp(noise·N(0, I))."""
    P = random_poses(rng, n, dim)
    g = PoseGraph(dim)
    d = 3 if dim == 2 else 6
    info = np.eye(d) if info is None else info
    for k in range(n):
        g.add_node(k, P[k] if with_vertices else None)
    pairs = [(k, k + 1) for k in range(n - 1)]
    while len(pairs) < n - 1 + loops:
        i, j = sorted(rng.choice(n, 2, replace=False).tolist())
        if j > i + 1:
            pairs.append((i, j))
    for i, j in pairs:
        Z = geo.relative(P[i], P[j])
        if noise:
            xi = rng.normal(0, noise, d)
            Z = Z @ (geo.se2_exp(xi) if dim == 2 else geo.se3_exp(xi))
        g.add_edge(i, j, Z, info)
    return g, P


def inject_false_loops(graph: PoseGraph, fraction: float, rng: np.random.Generator) -> PoseGraph:
    """Add ``fraction · #edges`` false loop closures between random node pairs (|i − j| > 1), each claiming the
    two poses are within ±2 m with a random heading, with the median loop information of the graph."""
    g = graph.copy()
    n = g.num_nodes
    loops = [k for k, kind in enumerate(g.edge_kinds) if kind == "loop"]
    info = np.median(g.edge_arrays().information[loops], axis=0)
    ids = g.node_ids
    for _ in range(int(round(fraction * g.num_edges))):
        while True:
            i, j = rng.integers(0, n, 2)
            if abs(int(i) - int(j)) > 1:
                break
        Z = geo.xytheta_to_matrix(rng.uniform(-2, 2), rng.uniform(-2, 2), rng.uniform(-np.pi, np.pi))
        g.add_edge(int(ids[i]), int(ids[j]), Z, info, "loop")
    return g
