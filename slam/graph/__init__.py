"""Pose graphs: the :class:`PoseGraph` data model, g2o/TORO IO, initialisation and cost functions."""

from .g2o import read_g2o, write_g2o
from .posegraph import KERNELS, KINDS, PRIOR_NODE, Edge, EdgeArrays, GraphError, PoseGraph, RobustKernel
from .toro import read_toro, write_toro

__all__ = ["PoseGraph", "Edge", "EdgeArrays", "RobustKernel", "GraphError", "KINDS", "KERNELS", "PRIOR_NODE",
           "read_g2o", "write_g2o", "read_toro", "write_toro", "read_graph"]


def read_graph(path):  # type: ignore[no-untyped-def]
    """Read a g2o or TORO file, chosen by content (``VERTEX2``/``EDGE2`` records mean TORO)."""
    from pathlib import Path

    from registration.errors import GraphFormatError

    try:
        with open(Path(path)) as fh:
            for line in fh:
                tok = line.split()
                if tok and not tok[0].startswith("#"):
                    return read_toro(path) if tok[0] in ("VERTEX2", "EDGE2") else read_g2o(path)
    except OSError as exc:
        raise GraphFormatError(str(path), None, f"cannot read: {exc.strerror}") from None
    raise GraphFormatError(str(path), None, "empty graph file")
