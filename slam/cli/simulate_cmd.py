"""``slam simulate WORLD --out LOG.mcap``: a simulated 2D laser log with ground truth and its map."""

from __future__ import annotations

from pathlib import Path

import typer

from .options import alphas as parse_alphas
from .options import real


def simulate(
    world: str = typer.Argument(..., help="rooms | corridor | obstacles, or a ROS map_server .yaml file."),
    out: Path = typer.Option(..., "--out", "-o", help="Output MCAP log; the ground-truth map goes beside it as <stem>_map.pgm/.yaml."),
    seed: int = typer.Option(0, "--seed", min=0, help="Seed of the world, the path and all noise."),
    scans: int = typer.Option(1000, "--scans", min=1, help="Number of laser scans."),
    sensor: str = typer.Option("fastgpom", "--sensor", help="Laser preset: fastgpom, sick_lms, hokuyo_utm30."),
    range_noise: float | None = typer.Option(None, "--range-noise", parser=real(0.0),
                                             help="Gaussian range noise σ in m (default: the preset's)."),
    odom_noise: str | None = typer.Option(None, "--odom-noise",
                                          help="Odometry noise α1,α2,α3,α4 (Probabilistic Robotics §5.4), default 0.005,0.0005,0.01,0.001."),
    resolution: float | None = typer.Option(None, "--resolution", parser=real(0.0, above=True),
                                            help="World cell size in m (procedural default 0.05; a yaml map is resampled)."),
) -> None:
    """Simulate a robot touring WORLD with a 2D laser and drifting wheel odometry; write an MCAP log."""
    import time

    from evaluation.sim import LASER_PRESETS, load_world
    from evaluation.sim.simulate import DEFAULT_ODOM_NOISE, map_paths, simulate as run_sim, write_simulated_log
    from registration.atomic import check_output_file
    from registration.errors import ConfigError

    for path in (out, *map_paths(out)):
        check_output_file(path)
    if sensor not in LASER_PRESETS:
        raise ConfigError(f"--sensor must be one of {', '.join(LASER_PRESETS)}, got {sensor!r}")
    alphas = DEFAULT_ODOM_NOISE
    if odom_noise is not None:
        try:
            alphas = parse_alphas(odom_noise)
        except ValueError as exc:
            raise ConfigError(f"--odom-noise: {exc} (four finite numbers >= 0)") from None
    t0 = time.perf_counter()
    w = load_world(world, resolution=resolution, seed=seed)
    sim = run_sim(w, n_scans=scans, spec=LASER_PRESETS[sensor], seed=seed, range_noise=range_noise, odom_noise=alphas)
    write_simulated_log(sim, out)
    yaml_path, _ = map_paths(out)
    gt = sim.ground_truth[:, :2, 3]
    length = float(sum(((gt[1:] - gt[:-1]) ** 2).sum(axis=1) ** 0.5)) if len(gt) > 1 else 0.0
    typer.echo(f"world: {w.name} {w.shape[1]}x{w.shape[0]} cells at {w.resolution} m")
    typer.echo(f"sensor: {sensor} ({sim.spec.num_beams} beams, {sim.spec.range_max} m, {sim.spec.rate_hz} Hz)")
    typer.echo(f"path_length_m: {length:.2f}")
    typer.echo(f"log: {out}")
    typer.echo(f"map: {yaml_path}")
    typer.echo(f"scans: {len(sim)}")
    typer.echo(f"time_s: {time.perf_counter() - t0:.2f}")


def register(app: typer.Typer, eval_app: typer.Typer) -> None:
    app.command("simulate")(simulate)
