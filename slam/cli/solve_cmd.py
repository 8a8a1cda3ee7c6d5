"""``slam solve GRAPH``: optimise a g2o/TORO pose graph and print one JSON line of costs and timing."""

from __future__ import annotations

from enum import Enum
from pathlib import Path

import typer

from .options import Backend, real


class Init(str, Enum):
    odometry = "odometry"
    chordal = "chordal"
    file = "file"


class Robust(str, Enum):
    none = "none"
    huber = "huber"
    cauchy = "cauchy"


def solve(
    graph_path: Path = typer.Argument(..., metavar="GRAPH", help="g2o (VERTEX_SE2/EDGE_SE2, SE3:QUAT) or TORO (VERTEX2/EDGE2) file."),
    backend: Backend = typer.Option(Backend.gtsam, "--backend", help="gtsam (Levenberg-Marquardt) or chordal (our Gauss-Newton)."),
    init: Init = typer.Option(Init.chordal, "--init", help="odometry, chordal or file (the file's VERTEX poses)."),
    robust: Robust = typer.Option(Robust.none, "--robust", help="none, huber or cauchy: kernel on loop edges (gtsam only)."),
    robust_k: float = typer.Option(1.0, "--robust-k", parser=real(0.0, above=True),
                                   help="Kernel threshold in standard deviations (> 0)."),
    out: Path | None = typer.Option(None, "--out", help="Write the optimised graph (g2o) here."),
    allow_disconnected: bool = typer.Option(False, "--allow-disconnected", help="Solve a graph whose parts no "
                                            "edge joins, holding each part at its first node (their relative "
                                            "placement is then arbitrary); refused by default."),
) -> None:
    """Optimise a pose graph (g2o or TORO) with GTSAM's Levenberg-Marquardt or our chordal Gauss-Newton, from an
    odometry, chordal or the file's own initial guess, and print one JSON line: the graph's size, the SE-Sync
    objective and GTSAM's χ² of the solution (null when an edge's information is not positive definite),
    the iterations and the solver time. --out writes the optimised graph as g2o.

    A graph whose parts no edge joins is refused (--allow-disconnected holds each part at its first node).
    """
    import json

    from core.atomic import check_output_file
    from core.errors import ConfigError, GraphFormatError
    from slam.graph import GraphError, RobustKernel, read_graph, write_g2o
    from slam.graph.costs import gtsam_error, sesync_objective
    from slam.graph.init import initial_poses

    if out is not None:
        check_output_file(out)
    backend, init, robust = backend.value, init.value, robust.value  # type: ignore[assignment]
    if robust != "none" and backend != "gtsam":
        raise ConfigError("--robust needs --backend gtsam (the chordal solver minimises the plain SE-Sync objective)")
    graph = read_graph(graph_path)
    apart = graph.disconnection()
    if apart is not None:
        if not allow_disconnected:
            raise GraphFormatError(graph_path, None, f"{apart}; nothing places them relative to each other (give "
                                                     "--allow-disconnected to hold each at its first node)")
        typer.echo(f"warning: {graph_path}: {apart}; each is held at its first node (--allow-disconnected), "
                   "so their relative placement is arbitrary", err=True)
    if backend == "gtsam":
        from slam.backends.gtsam_backend import refuse_indefinite

        try:
            refuse_indefinite(graph)
        except GraphError as exc:
            raise GraphFormatError(graph_path, None, str(exc)) from None
    kernel = None if robust == "none" else RobustKernel(robust, robust_k)
    P0 = initial_poses(graph, init)
    if backend == "chordal":
        from slam.backends.chordal import solve_chordal

        r = solve_chordal(graph, P0)
        poses, iterations, time_s = r.poses, r.iterations, r.time_s
    else:
        from slam.backends.gtsam_backend import optimize

        g = optimize(graph, P0, robust=kernel)
        poses, iterations, time_s = g.poses, g.iterations, g.time_s
    result = graph.with_poses(poses)
    if kernel is not None:
        result.set_kernel(kernel, ("loop",))
    record = {
        "graph": str(graph_path),
        "backend": backend,
        "init": init,
        "robust": robust,
        "nodes": graph.num_nodes,
        "edges": graph.num_edges,
        "sesync_objective": sesync_objective(graph, poses),
        # GTSAM's χ² needs every information matrix positive definite (null otherwise, see the warning)
        "gtsam_error": None if len(graph.indefinite_edges()) else gtsam_error(result, poses),
        "iterations": iterations,
        "time_s": time_s,
    }
    if out is not None:
        write_g2o(result, out)
        record["out"] = str(out)
    typer.echo(json.dumps(record))


def register(app: typer.Typer, eval_app: typer.Typer) -> None:
    app.command("solve")(solve)
