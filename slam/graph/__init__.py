"""Pose graphs: the :class:`PoseGraph` data model, g2o/TORO IO, initialisation and cost functions."""

from .g2o import read_g2o, write_g2o
from .posegraph import KERNELS, KINDS, PRIOR_NODE, Edge, EdgeArrays, GraphError, PoseGraph, RobustKernel
from .toro import read_toro, write_toro

__all__ = ["PoseGraph", "Edge", "EdgeArrays", "RobustKernel", "GraphError", "KINDS", "KERNELS", "PRIOR_NODE",
           "read_g2o", "write_g2o", "read_toro", "write_toro", "read_graph"]


def read_graph(path):  # type: ignore[no-untyped-def]
    """Read a g2o or TORO file, chosen by content (``VERTEX2``/``EDGE2`` records mean TORO)."""
    from core.errors import GraphFormatError

    from .g2o import graph_lines

    for _, line in graph_lines(str(path)):
        if not line.startswith("#"):
            return read_toro(path) if line.split()[0] in ("VERTEX2", "EDGE2") else read_g2o(path)
    raise GraphFormatError(str(path), None, "empty graph file")
