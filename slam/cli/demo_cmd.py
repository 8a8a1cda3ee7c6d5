"""``slam demo``: SLAM on the bundled Intel Research Lab log, scored against the published numbers.

Runs the whole pipeline (``slam run``) on ``data/intel.clf.bz2``, writes every output into
``--out``, and prints the Kümmerle relation error beside Cartographer's and Graph Mapping's.
"""

from __future__ import annotations

from pathlib import Path

import typer

REPO_DATA = Path(__file__).resolve().parents[2] / "data"


def demo(
    out: Path = typer.Option(Path("out/demo"), "--out", help="Folder for the demo's results."),
    log: Path = typer.Option(REPO_DATA / "intel.clf.bz2", "--log", help="Log to run on (default: the bundled Intel log)."),
    relations: Path = typer.Option(REPO_DATA / "intel.relations", "--relations", help="Ground-truth relations of the log."),
    max_scans: int | None = typer.Option(None, "--max-scans", min=1, help="Stop after this many scans (a quick look)."),
    quiet: bool = typer.Option(False, "--quiet", help="No progress bar."),
) -> None:
    """Run SLAM on the bundled Intel log and print the relation error beside the published ones."""
    from core.atomic import check_output_dir
    from core.trajectory import read_tum
    from evaluation.published import recognise_dataset
    from evaluation.relations import evaluate_relations, read_relations
    from slam.cli.eval_cmd import relations_table
    from slam.cli.run_cmd import load_config, run_log
    from slam.pipeline.outputs import RUN_MARKER

    cfg = load_config(None, {"max_scans": max_scans})
    check_output_dir(out, RUN_MARKER)
    typer.echo(f"slam run {log} → {out} (this takes a few minutes on 2 cores for the whole Intel log)")
    s = run_log(log, out, cfg, None, quiet)
    typer.echo(f"scans: {s['scans']}  keyframes: {s['keyframes']}  loop_closures: {s['loop_closures']}  "
               f"wall_time_s: {s['wall_time_s']:.1f}")
    res = evaluate_relations(read_tum(out / "trajectory.tum"), read_relations(relations))
    typer.echo(f"relations used: {res.n_used} (of {res.n_used + res.n_missing}; the rest lie beyond the scans processed)")
    for line in relations_table(res, recognise_dataset(relations)):
        typer.echo(line)
    typer.echo(f"results: {out.resolve()} (map.png, trajectory.tum, graph.g2o, result.mcap, summary.json)")


def register(app: typer.Typer, eval_app: typer.Typer) -> None:
    app.command("demo")(demo)
