"""g2o pose-graph files: ``VERTEX_SE2``, ``EDGE_SE2``, ``VERTEX_SE3:QUAT``, ``EDGE_SE3:QUAT`` (+ priors, FIX).

Format (Kümmerle et al., "g2o: A general framework for graph optimization", ICRA 2011, and g2o's
``types_slam2d`` / ``types_slam3d``):

* ``VERTEX_SE2 id x y θ`` — ``EDGE_SE2 i j dx dy dθ I11 I12 I13 I22 I23 I33`` (upper triangle, row-major,
  order x, y, θ).
* ``VERTEX_SE3:QUAT id x y z qx qy qz qw`` — ``EDGE_SE3:QUAT i j dx dy dz qx qy qz qw`` + the 21 upper-triangle
  information entries (order x, y, z, then rotation).
* ``EDGE_PRIOR_SE2 id x y θ`` + 6 entries; ``EDGE_SE3_PRIOR id p x y z qx qy qz qw`` + 21 entries with an
  identity ``PARAMS_SE3OFFSET p 0 0 0 0 0 0 1``; ``FIX id`` holds a node fixed.

**Edge kinds and robust kernels** (our extension): a comment line ``# gpslam:edge kind=loop kernel=cauchy:1.0``
applies to the next edge line. g2o and GTSAM ignore ``#`` lines. Without a tag an edge is ``odometry`` when
``j == i + 1`` and ``loop`` otherwise, so tags are only written where the kind differs from that default or a
kernel is set. Numbers are written with Python's shortest round-trip ``repr``: a read → write → read round trip
is bit-exact.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Iterable, Iterator

import numpy as np

from core.atomic import atomic_open
from core.errors import GraphFormatError
from core.numbers import c_floats, c_int
from core.textfile import text_lines

from .costs import sesync_weights
from .posegraph import KINDS, PRIOR_NODE, PoseGraph, RobustKernel

__all__ = ["read_g2o", "write_g2o", "TAG_PREFIX", "ParsedGraph", "graph_lines", "parse_numbers", "parse_id",
           "format_numbers", "build_graph", "parse_tag", "format_tag"]

TAG_PREFIX = "# gpslam:edge"

_TRIU3 = np.triu_indices(3)
_TRIU6 = np.triu_indices(6)


def upper_to_full(values: np.ndarray, n: int) -> np.ndarray:
    """Row-major upper-triangle entries ``(..., n(n+1)/2)`` → symmetric ``(..., n, n)``."""
    iu = np.triu_indices(n)
    M = np.zeros(values.shape[:-1] + (n, n))
    M[..., iu[0], iu[1]] = values
    M[..., iu[1], iu[0]] = values
    return M


def full_to_upper(M: np.ndarray) -> np.ndarray:
    n = M.shape[-1]
    iu = np.triu_indices(n)
    return M[..., iu[0], iu[1]]


@dataclass
class ParsedGraph:
    """Raw records of a graph file before the PoseGraph is built."""

    path: str
    dim: int | None = None
    vertices: list[tuple[int, list[float], int]] = field(default_factory=list)  # id, params, line
    # i, j, params, information entries (upper triangle, row-major, as g2o writes them), kind, kernel, line
    edges: list[tuple[int, int, list[float], list[float], str | None, RobustKernel | None, int]] = field(
        default_factory=list
    )
    fixed: list[int] = field(default_factory=list)

    def set_dim(self, dim: int, lineno: int) -> None:
        if self.dim is None:
            self.dim = dim
        elif self.dim != dim:
            raise GraphFormatError(self.path, f"line {lineno}", f"mixes {self.dim}D and {dim}D records")


def parse_tag(path: str, lineno: int, text: str) -> tuple[str | None, RobustKernel | None]:
    """Parse ``# gpslam:edge kind=K kernel=NAME:k`` (both optional)."""
    kind: str | None = None
    kernel: RobustKernel | None = None
    for tok in text[len(TAG_PREFIX):].split():
        key, _, val = tok.partition("=")
        if key == "kind" and val in KINDS:
            kind = val
        elif key == "kernel":
            name, _, k = val.partition(":")
            try:
                kernel = RobustKernel(name, float(k) if k else 1.0)
            except (ValueError, Exception) as exc:  # noqa: BLE001 - re-raised with position
                raise GraphFormatError(path, f"line {lineno}", f"bad kernel {val!r}: {exc}") from None
        else:
            raise GraphFormatError(path, f"line {lineno}", f"bad gpslam edge tag {tok!r} (expected kind=…, kernel=…)")
    return kind, kernel


def format_tag(kind: str, default_kind: str, kernel: RobustKernel | None) -> str | None:
    parts = []
    if kind != default_kind:
        parts.append(f"kind={kind}")
    if kernel is not None:
        parts.append(f"kernel={kernel.name}:{kernel.k!r}")
    return f"{TAG_PREFIX} {' '.join(parts)}" if parts else None


def graph_lines(path: str) -> Iterator[tuple[int, str]]:
    """``(line number, stripped text)`` of the non-blank lines of a graph file (UTF-8; errors name the line)."""
    for lineno, line in text_lines(path, GraphFormatError, "a g2o or TORO graph file"):
        s = line.strip()
        if s:
            yield lineno, s


def parse_numbers(path: str, lineno: int, fields: list[str], n: int, what: str) -> list[float]:
    """*n* finite numbers (C locale grammar, :mod:`core.numbers`) of a record, or a GraphFormatError."""
    if len(fields) != n:
        raise GraphFormatError(path, f"line {lineno}", f"{what}: expected {n} numbers, got {len(fields)}")
    try:
        vals = c_floats(fields)
    except ValueError as exc:
        raise GraphFormatError(path, f"line {lineno}", f"{what}: {exc}") from None
    if not all(np.isfinite(vals)):
        raise GraphFormatError(path, f"line {lineno}", f"{what}: non-finite value")
    return vals


def parse_id(path: str, lineno: int, s: str, what: str) -> int:
    """A vertex id (a non-negative integer, C locale grammar), or a GraphFormatError."""
    try:
        v = c_int(s)
    except ValueError:
        raise GraphFormatError(path, f"line {lineno}", f"{what}: expected an integer id, got {s!r}") from None
    if v < 0:
        raise GraphFormatError(path, f"line {lineno}", f"{what}: negative id {v}")
    return v


def build_graph(p: ParsedGraph) -> PoseGraph:
    """Turn parsed records into a PoseGraph.

    A file with VERTEX lines declares its nodes: an edge to any other id is an error (a typo must not
    add a node without a pose). A file without any (SE-Sync's) has the nodes its edges name, in
    sorted-id order.
    """
    if p.dim is None:
        raise GraphFormatError(p.path, None, "no vertices or edges found")
    g = PoseGraph(p.dim)
    seen: dict[int, int] = {}
    for vid, par, lineno in p.vertices:
        if vid in seen:
            raise GraphFormatError(p.path, f"line {lineno}", f"duplicate vertex {vid} (first on line {seen[vid]})")
        seen[vid] = lineno
        if p.dim == 3 and np.linalg.norm(par[3:]) < 1e-12:
            raise GraphFormatError(p.path, f"line {lineno}", "zero quaternion")
        g.add_node(vid, params=par)
    if seen:
        for i, j, *_, lineno in p.edges:
            for v in (i, j):
                if v != PRIOR_NODE and v not in seen:
                    raise GraphFormatError(p.path, f"line {lineno}", f"edge {i} → {j} names vertex {v}, which no "
                                           "VERTEX line declares")
    missing = sorted(({e[1] for e in p.edges} | {e[0] for e in p.edges if e[0] != PRIOR_NODE}) - set(seen))
    for vid in missing:
        g.add_node(vid)
    infos = np.zeros((0, g.dof, g.dof))
    if p.edges:
        infos = upper_to_full(np.asarray([e[3] for e in p.edges], dtype=float), g.dof)
        # Only an edge without positive SE-Sync weights is unusable by every back end; one whose whole
        # information is indefinite is refused by GTSAM alone (PoseGraph.indefinite_edges).
        kappa, tau = sesync_weights(infos, p.dim)
        bad = np.flatnonzero(~((kappa > 0) & (tau > 0) & np.isfinite(kappa) & np.isfinite(tau)))
        if bad.size:
            e = p.edges[int(bad[0])]
            k, t = kappa[bad[0]], tau[bad[0]]
            raise GraphFormatError(p.path, f"line {e[6]}", f"information matrix gives no positive SE-Sync weights "
                                   f"(κ = {k:.6g}, τ = {t:.6g}; Rosen et al. 2019, eq. 14): no back end can use it")
    for (i, j, par, _, kind, kernel, lineno), info in zip(p.edges, infos):
        if p.dim == 3 and np.linalg.norm(par[3:]) < 1e-12:
            raise GraphFormatError(p.path, f"line {lineno}", "zero quaternion")
        if i == j:
            raise GraphFormatError(p.path, f"line {lineno}", f"self-loop edge {i} → {j}")
        if kind == "prior" and i != PRIOR_NODE or kind not in (None, "prior") and i == PRIOR_NODE:
            raise GraphFormatError(p.path, f"line {lineno}", f"edge kind {kind!r} does not fit this record")
        g.add_edge(i, j, None, info, kind, kernel, params=par)
    for vid in p.fixed:
        if vid not in g._index:
            raise GraphFormatError(p.path, None, f"FIX of unknown vertex {vid}")
    g.fixed_ids = list(p.fixed)
    return g


def read_g2o(path: str | os.PathLike[str]) -> PoseGraph:
    """Read a g2o file (2D or 3D). Raises :class:`GraphFormatError` naming the file and line."""
    path_s = str(path)
    p = ParsedGraph(path_s)
    pending: tuple[str | None, RobustKernel | None] | None = None
    offsets_ok: set[str] = set()
    for lineno, s in graph_lines(path_s):
        if s.startswith("#"):
            if s.startswith(TAG_PREFIX):
                pending = parse_tag(path_s, lineno, s)
            continue
        f = s.split()
        tag = f[0]
        if tag == "VERTEX_SE2":
            p.set_dim(2, lineno)
            if len(f) != 5:
                raise GraphFormatError(path_s, f"line {lineno}", f"VERTEX_SE2 needs id x y theta, got {len(f) - 1} fields")
            p.vertices.append((parse_id(path_s, lineno, f[1], tag), parse_numbers(path_s, lineno, f[2:], 3, tag), lineno))
        elif tag == "VERTEX_SE3:QUAT":
            p.set_dim(3, lineno)
            if len(f) != 9:
                raise GraphFormatError(path_s, f"line {lineno}", f"VERTEX_SE3:QUAT needs id x y z qx qy qz qw, got {len(f) - 1} fields")
            p.vertices.append((parse_id(path_s, lineno, f[1], tag), parse_numbers(path_s, lineno, f[2:], 7, tag), lineno))
        elif tag in ("EDGE_SE2", "EDGE_SE3:QUAT"):
            dim = 2 if tag == "EDGE_SE2" else 3
            p.set_dim(dim, lineno)
            npar, nfo = (3, 6) if dim == 2 else (7, 21)
            if len(f) != 3 + npar + nfo:
                raise GraphFormatError(path_s, f"line {lineno}", f"{tag} needs {2 + npar + nfo} fields, got {len(f) - 1}")
            i, j = parse_id(path_s, lineno, f[1], tag), parse_id(path_s, lineno, f[2], tag)
            vals = parse_numbers(path_s, lineno, f[3:], npar + nfo, tag)
            kind, kernel = pending if pending else (None, None)
            pending = None
            p.edges.append((i, j, vals[:npar], vals[npar:],
                            kind, kernel, lineno))
        elif tag == "EDGE_PRIOR_SE2":
            p.set_dim(2, lineno)
            if len(f) != 11:
                raise GraphFormatError(path_s, f"line {lineno}", f"EDGE_PRIOR_SE2 needs 10 fields, got {len(f) - 1}")
            j = parse_id(path_s, lineno, f[1], tag)
            vals = parse_numbers(path_s, lineno, f[2:], 9, tag)
            _, kernel = pending if pending else (None, None)
            pending = None
            p.edges.append((PRIOR_NODE, j, vals[:3], vals[3:], "prior", kernel, lineno))
        elif tag == "EDGE_SE3_PRIOR":
            p.set_dim(3, lineno)
            if len(f) != 31:
                raise GraphFormatError(path_s, f"line {lineno}", f"EDGE_SE3_PRIOR needs 30 fields, got {len(f) - 1}")
            j = parse_id(path_s, lineno, f[1], tag)
            if f[2] not in offsets_ok:
                raise GraphFormatError(path_s, f"line {lineno}", f"EDGE_SE3_PRIOR: unknown or non-identity offset {f[2]}")
            vals = parse_numbers(path_s, lineno, f[3:], 28, tag)
            _, kernel = pending if pending else (None, None)
            pending = None
            p.edges.append((PRIOR_NODE, j, vals[:7], vals[7:], "prior", kernel, lineno))
        elif tag == "PARAMS_SE3OFFSET":
            vals = parse_numbers(path_s, lineno, f[2:], 7, tag)
            if vals != [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]:
                raise GraphFormatError(path_s, f"line {lineno}", "only identity PARAMS_SE3OFFSET is supported")
            offsets_ok.add(f[1])
        elif tag == "FIX":
            if len(f) < 2:
                raise GraphFormatError(path_s, f"line {lineno}", "FIX needs at least one vertex id")
            p.fixed.extend(parse_id(path_s, lineno, x, tag) for x in f[1:])
        else:
            raise GraphFormatError(path_s, f"line {lineno}", f"unknown record {tag!r} (expected VERTEX_SE2, EDGE_SE2, "
                                   "VERTEX_SE3:QUAT, EDGE_SE3:QUAT, EDGE_PRIOR_SE2, EDGE_SE3_PRIOR, FIX)")
    return build_graph(p)


def format_numbers(values: Iterable[float]) -> str:
    """Numbers as ``repr`` (the shortest text that reads back bit for bit), space-separated."""
    return " ".join(repr(float(v)) for v in values)


def write_g2o(graph: PoseGraph, path: str | os.PathLike[str], *, vertices: bool = True) -> None:
    """Write *graph* as g2o (atomically). Nodes without a pose get no VERTEX line."""
    dim = graph.dim
    vtag, etag = ("VERTEX_SE2", "EDGE_SE2") if dim == 2 else ("VERTEX_SE3:QUAT", "EDGE_SE3:QUAT")
    npar = graph.node_params.tolist()
    ids = graph.node_ids.tolist()
    ei, ej = (a.tolist() for a in graph.edge_ids)
    epar = graph.edge_params.tolist()
    info_u = full_to_upper(graph.edge_arrays().information).tolist()
    kinds = graph.edge_kinds
    kernels = graph.edge_kernels
    lines: list[str] = []
    if dim == 3 and "prior" in kinds:
        lines.append("PARAMS_SE3OFFSET 0 0 0 0 0 0 0 1")
    if vertices:
        for vid, par in zip(ids, npar):
            if all(np.isfinite(par)):
                lines.append(f"{vtag} {vid} {format_numbers(par)}")
    for i, j, par, inf, kind, kernel in zip(ei, ej, epar, info_u, kinds, kernels):
        default = "prior" if i == PRIOR_NODE else ("odometry" if j == i + 1 else "loop")
        tag = format_tag(kind, default, kernel)
        if tag:
            lines.append(tag)
        if kind == "prior":
            lines.append(f"EDGE_PRIOR_SE2 {j} {format_numbers(par)} {format_numbers(inf)}" if dim == 2
                         else f"EDGE_SE3_PRIOR {j} 0 {format_numbers(par)} {format_numbers(inf)}")
        else:
            lines.append(f"{etag} {i} {j} {format_numbers(par)} {format_numbers(inf)}")
    if graph.fixed_ids:
        lines.append("FIX " + " ".join(str(v) for v in graph.fixed_ids))
    with atomic_open(path, "w") as fh:
        fh.write("\n".join(lines) + "\n")
