"""``slam simulate WORLD --out LOG.mcap``: a simulated 2D laser log with ground truth and its map."""

from __future__ import annotations

from pathlib import Path

import typer

from .options import AUTO, real, scan_count
from .options import alphas as parse_alphas


def simulate(
    world: str = typer.Argument(..., help="rooms | corridor | obstacles | ring, or a ROS map_server .yaml file."),
    out: Path = typer.Option(..., "--out", "-o", help="Output MCAP log; the ground-truth map goes beside it as <stem>_map.pgm/.yaml."),
    seed: int = typer.Option(0, "--seed", min=0, help="Seed of the world, the path and all noise."),
    scans: int = typer.Option("auto", "--scans", parser=scan_count,
                              help="Number of laser scans, or auto: exactly one coverage tour per lap."),
    laps: int = typer.Option(1, "--laps", min=1, help="With --scans auto: drive the coverage tour this many times."),
    robot_radius: float = typer.Option(0.2, "--robot-radius", parser=real(0.0, above=True),
                                       help="Robot radius in m (0.2: a small indoor robot); free space it "
                                            "cannot reach is reported."),
    sensor: str = typer.Option("fastgpom", "--sensor", help="Laser preset: fastgpom, sick_lms, hokuyo_utm30, hokuyo_urg04lx, rplidar_a2 (slow sweeps: every beam at its own time; the RPLIDAR turns clockwise, its beams listed the other way)."),
    range_noise: float | None = typer.Option(None, "--range-noise", parser=real(0.0),
                                             help="Gaussian range noise σ in m (default: the preset's)."),
    odom_noise: str | None = typer.Option(None, "--odom-noise",
                                          help="Odometry noise α1,α2,α3,α4 (Probabilistic Robotics §5.4), default 0.005,0.0005,0.01,0.001."),
    resolution: float | None = typer.Option(None, "--resolution", parser=real(0.0, above=True),
                                            help="World cell size in m (procedural default 0.05; a yaml map is resampled)."),
) -> None:
    """Simulate a robot touring WORLD with a 2D laser and drifting wheel odometry; write an MCAP log.

    By default the tour covers the world: every place the laser can see from where the robot fits is
    seen at least once; the coverage is printed, and free space the robot cannot reach is reported.
    """
    import time

    from core import geometry as geo
    from core.atomic import check_output_file
    from core.errors import ConfigError
    from evaluation.sim import LASER_PRESETS, load_world
    from evaluation.sim.coverage import plan_space, scan_coverage, unreachable_space
    from evaluation.sim.simulate import DEFAULT_ODOM_NOISE, simulate as run_sim
    from slam.logs.simulated import map_paths, write_simulated_log

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
    sim = run_sim(w, n_scans=None if scans == AUTO else scans, spec=LASER_PRESETS[sensor], seed=seed,
                  range_noise=range_noise, odom_noise=alphas, robot_radius=robot_radius, laps=laps)
    space, n_specks, specks_m2 = plan_space(w)
    if sim.tour is not None:  # the coverage tour measured both already
        coverage, unreachable = sim.tour.coverage, sim.tour.unreachable
    else:
        coverage = scan_coverage(w, geo.matrix_to_xytheta(sim.sensor_poses()), sim.spec, space)
        unreachable = unreachable_space(w, robot_radius)
    write_simulated_log(sim, out)
    yaml_path, _ = map_paths(out)
    gt = sim.ground_truth[:, :2, 3]
    length = float(sum(((gt[1:] - gt[:-1]) ** 2).sum(axis=1) ** 0.5)) if len(gt) > 1 else 0.0
    typer.echo(f"world: {w.name} {w.shape[1]}x{w.shape[0]} cells at {w.resolution} m, "
               f"{space.sum() * w.resolution**2:.1f} m² of free space")
    typer.echo(f"sensor: {sensor} ({sim.spec.num_beams} beams, {sim.spec.range_max} m, {sim.spec.rate_hz} Hz)")
    kind = f"coverage tour, laps {laps}" if scans == AUTO else "fixed number of scans"
    typer.echo(f"tour: {kind}, robot radius {robot_radius:g} m")
    typer.echo(f"path_length_m: {length:.2f}")
    typer.echo(f"duration_s: {sim.stamps[-1] - sim.stamps[0] + sim.spec.period:.1f}")
    typer.echo(f"scans: {len(sim)}")
    typer.echo(f"coverage: {coverage:.4f}")
    if n_specks:
        typer.echo(f"not counted: {n_specks} isolated specks of free space ({specks_m2:.2f} m² in all) "
                   "cut off by walls")
    if unreachable:
        total = sum(r.area_m2 for r in unreachable)
        big = unreachable[0]
        typer.echo(f"warning: {total:.1f} m² of free space ({total / max(space.sum() * w.resolution**2, 1e-12):.1%}, "
                   f"{len(unreachable)} region{'s' if len(unreachable) > 1 else ''}) cannot be reached by a robot of "
                   f"radius {robot_radius:g} m; the largest, {big.area_m2:.1f} m², around "
                   f"({big.centroid_xy[0]:.1f}, {big.centroid_xy[1]:.1f}) m", err=True)
    typer.echo(f"log: {out}")
    typer.echo(f"map: {yaml_path}")
    typer.echo(f"time_s: {time.perf_counter() - t0:.2f}")


def register(app: typer.Typer, eval_app: typer.Typer) -> None:
    app.command("simulate")(simulate)
