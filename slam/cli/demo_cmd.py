"""``slam demo``: the main job on the bundled default log (data/intel.clf.bz2).

Until the end-to-end pipeline lands this reads the Intel log through the streaming reader,
simulates a short log in a built-in world, and prints where the results are.
"""

from __future__ import annotations

from pathlib import Path

import typer

REPO_DATA = Path(__file__).resolve().parents[2] / "data"


def demo(
    out: Path = typer.Option(Path("out/demo"), "--out", help="Folder for the demo's results."),
    log: Path = typer.Option(REPO_DATA / "intel.clf.bz2", "--log", help="Log to run on (default: the bundled Intel log)."),
) -> None:
    """Run the demo on the bundled Intel log and a short simulated log; print where the results are."""
    import json
    import time

    from registration.atomic import atomic_open
    from slam.logs import open_log

    t0 = time.perf_counter()
    reader = open_log(log)
    inf = reader.info()
    typer.echo(f"log: {inf.path} ({inf.format}, {inf.scans} scans, {inf.duration_s:.0f} s, "
               f"{inf.beams_per_scan} beams, odometry {'yes' if inf.has_odometry else 'no'})")
    read_s = time.perf_counter() - t0

    from evaluation.sim import LASER_PRESETS, load_world, simulate, write_simulated_log

    out.mkdir(parents=True, exist_ok=True)
    sim_path = out / "sim_rooms.mcap"
    t1 = time.perf_counter()
    sim = simulate(load_world("rooms"), n_scans=200, spec=LASER_PRESETS["fastgpom"], seed=1)
    write_simulated_log(sim, sim_path)
    sim_s = time.perf_counter() - t1
    sim_info = open_log(sim_path).info()
    typer.echo(f"simulated: {sim_path} ({sim_info.scans} scans, ground-truth map beside it)")

    summary = {
        "log": str(log), "scans": inf.scans, "info_time_s": read_s,
        "simulated_log": str(sim_path), "simulated_scans": sim_info.scans, "simulate_time_s": sim_s,
    }
    with atomic_open(out / "summary.json") as fh:
        json.dump(summary, fh, indent=2)
    typer.echo(f"results: {out.resolve()}")


def register(app: typer.Typer, eval_app: typer.Typer) -> None:
    app.command("demo")(demo)
