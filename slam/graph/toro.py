"""TORO 2D pose-graph files: ``VERTEX2 id x y θ`` and ``EDGE2 i j dx dy dθ I_xx I_xy I_yy I_tt I_xt I_yt``.

TORO (Grisetti et al., "A tree parameterization for efficiently computing maximum likelihood maps using
gradient descent", RSS 2007) orders the information entries **xx, xy, yy, θθ, xθ, yθ** — not g2o's
row-major upper triangle (xx, xy, xθ, yy, yθ, θθ); see ``../shared/data/pose_graphs/SOURCE.md``. The
PoseGraph stores the matrix in our (x, y, θ) order either way. Edge kinds use the same
``# gpslam:edge`` comment tags as :mod:`slam.graph.g2o`. Priors and 3D graphs cannot be written as TORO.
"""

from __future__ import annotations

import os

import numpy as np

from core.atomic import atomic_open
from core.errors import GraphFormatError

from .g2o import (TAG_PREFIX, ParsedGraph, build_graph, format_numbers, format_tag, full_to_upper, graph_lines, parse_id,
                  parse_numbers, parse_tag)
from .posegraph import GraphError, PoseGraph, RobustKernel

__all__ = ["read_toro", "write_toro", "toro_info_to_matrix", "matrix_to_toro_info"]


def toro_info_to_matrix(v: np.ndarray) -> np.ndarray:
    """TORO ``(I_xx, I_xy, I_yy, I_tt, I_xt, I_yt)`` (..., 6) → symmetric (..., 3, 3) in (x, y, θ) order."""
    v = np.asarray(v, dtype=float)
    xx, xy, yy, tt, xt, yt = np.moveaxis(v, -1, 0)
    return np.stack([np.stack([xx, xy, xt], -1), np.stack([xy, yy, yt], -1), np.stack([xt, yt, tt], -1)], -2)


def matrix_to_toro_info(M: np.ndarray) -> np.ndarray:
    """Inverse of :func:`toro_info_to_matrix`."""
    M = np.asarray(M, dtype=float)
    return np.stack([M[..., 0, 0], M[..., 0, 1], M[..., 1, 1], M[..., 2, 2], M[..., 0, 2], M[..., 1, 2]], -1)


def read_toro(path: str | os.PathLike[str]) -> PoseGraph:
    """Read a 2D TORO graph. Raises :class:`GraphFormatError` naming the file and line."""
    path_s = str(path)
    p = ParsedGraph(path_s, dim=2)
    pending: tuple[str | None, RobustKernel | None] | None = None
    for lineno, s in graph_lines(path_s):
        if s.startswith("#"):
            if s.startswith(TAG_PREFIX):
                pending = parse_tag(path_s, lineno, s)
            continue
        f = s.split()
        if f[0] == "VERTEX2":
            if len(f) != 5:
                raise GraphFormatError(path_s, f"line {lineno}", f"VERTEX2 needs id x y theta, got {len(f) - 1} fields")
            p.vertices.append((parse_id(path_s, lineno, f[1], "VERTEX2"), parse_numbers(path_s, lineno, f[2:], 3, "VERTEX2"), lineno))
        elif f[0] == "EDGE2":
            if len(f) != 12:
                raise GraphFormatError(path_s, f"line {lineno}", f"EDGE2 needs 11 fields, got {len(f) - 1}")
            i, j = parse_id(path_s, lineno, f[1], "EDGE2"), parse_id(path_s, lineno, f[2], "EDGE2")
            vals = parse_numbers(path_s, lineno, f[3:], 9, "EDGE2")
            kind, kernel = pending if pending else (None, None)
            pending = None
            info = full_to_upper(toro_info_to_matrix(vals[3:])).tolist()  # the parser's (g2o) order
            p.edges.append((i, j, vals[:3], info, kind, kernel, lineno))
        elif f[0] in ("VERTEX3", "EDGE3"):
            raise GraphFormatError(path_s, f"line {lineno}", f"3D TORO record {f[0]} is not supported (use g2o)")
        else:
            raise GraphFormatError(path_s, f"line {lineno}", f"unknown record {f[0]!r} (expected VERTEX2 or EDGE2)")
    return build_graph(p)


def write_toro(graph: PoseGraph, path: str | os.PathLike[str]) -> None:
    """Write a 2D *graph* as TORO (atomically)."""
    if graph.dim != 2:
        raise GraphError("TORO output supports 2D graphs only")
    if "prior" in graph.edge_kinds:
        raise GraphError("TORO has no prior edges; write g2o instead")
    lines: list[str] = []
    for vid, par in zip(graph.node_ids.tolist(), graph.node_params.tolist()):
        if all(np.isfinite(par)):
            lines.append(f"VERTEX2 {vid} {format_numbers(par)}")
    ei, ej = (a.tolist() for a in graph.edge_ids)
    info = matrix_to_toro_info(graph.edge_arrays().information).tolist()
    for i, j, par, inf, kind, kernel in zip(ei, ej, graph.edge_params.tolist(), info, graph.edge_kinds,
                                            graph.edge_kernels):
        tag = format_tag(kind, "odometry" if j == i + 1 else "loop", kernel)
        if tag:
            lines.append(tag)
        lines.append(f"EDGE2 {i} {j} {format_numbers(par)} {format_numbers(inf)}")
    with atomic_open(path, "w") as fh:
        fh.write("\n".join(lines) + "\n")
