"""``slam info LOG``: what a log holds (format, topics, duration, beams, odometry, scan count)."""

from __future__ import annotations

from pathlib import Path

import typer


def info(
    log: Path = typer.Argument(..., help="CARMEN .clf/.log[.bz2|.gz], MCAP, ROS 1 bag or KITTI sequence folder."),
    topic: str | None = typer.Option(None, "--topic", help="Sensor topic (MCAP / ROS 1); auto-detected by default."),
) -> None:
    """Print the format, topics, duration, beams per scan, whether the scans carry beam times and odometry,
    and ``scans: N``."""
    from slam.logs import open_log

    reader = open_log(log, topic)
    inf = reader.info()
    typer.echo(f"file: {inf.path}")
    typer.echo(f"format: {inf.format}")
    typer.echo(f"sensor_topic: {inf.sensor_topic}")
    typer.echo(f"dimension: {inf.dimension}D")
    for t in inf.topics:
        typer.echo(f"topic: {t.name} [{t.msgtype}] {t.count} messages")
    typer.echo(f"duration_s: {inf.duration_s:.3f}")
    if inf.beams_per_scan is not None:
        label = "beams_per_scan" if inf.dimension == 2 else "points_per_scan"
        typer.echo(f"{label}: {inf.beams_per_scan}")
    if inf.dimension == 2:
        typer.echo(f"beam_times: {_beam_times(reader)}")
    typer.echo(f"odometry: {'yes' if inf.has_odometry else 'no'}")
    typer.echo(f"ground_truth: {'yes' if inf.has_ground_truth else 'no'}")
    typer.echo(f"scans: {inf.scans}")


def _beam_times(reader) -> str:  # type: ignore[no-untyped-def]
    """Whether the first scan says when its beams were taken (what the front end deskews with)."""
    frames = reader.frames()
    try:
        first = next(iter(frames), None)
    finally:
        close = getattr(frames, "close", None)  # a reader's background thread stops here
        if close is not None:
            close()
    t = None if first is None else first.beam_times
    if t is None or not t.size:
        return "no (deskewing needs odometry.laser_revolution_s)"
    return f"yes ({1000.0 * float(t.max() - t.min()):.1f} ms a sweep; which way they run is read from the scans)"


def register(app: typer.Typer, eval_app: typer.Typer) -> None:
    app.command("info")(info)
