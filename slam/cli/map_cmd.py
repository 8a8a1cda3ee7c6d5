"""``slam map LOG --out DIR`` (occupancy map from a log with given poses) and ``slam eval map``."""

from __future__ import annotations

from enum import Enum
from pathlib import Path

import typer

from .options import real


#: Files every map folder holds: an existing folder with them is an earlier map, which a new one replaces.
MAP_MARKER = ("mapping_config.yaml", "map.npz")


class Method(str, Enum):
    fastgpom = "fastgpom"
    gpom = "gpom"
    logodds = "logodds"


def _single_blas_thread():
    from slam.blas import single_blas_thread

    return single_blas_thread()


def _poses_for(frames, source: str, max_dt: float):
    """(frame, world_T_base) pairs: from the frames' ground truth / odometry, or a TUM file by stamp."""
    import numpy as np

    from core.errors import ConfigError

    if source in ("ground_truth", "odometry"):
        attr = "ground_truth" if source == "ground_truth" else "odom"
        out = [(f, getattr(f, attr)) for f in frames if getattr(f, attr) is not None]
        if not out:
            raise ConfigError(f"--poses {source}: the log has no {source.replace('_', ' ')} poses")
        return out
    from core.trajectory import read_tum

    traj = read_tum(source)  # in stamp order
    st = traj.stamps
    out = []
    for f in frames:
        j = int(np.clip(np.searchsorted(st, f.stamp), 1, len(st) - 1)) if len(st) > 1 else 0
        cand = [k for k in (j - 1, j) if 0 <= k < len(st)]
        k = min(cand, key=lambda c: abs(st[c] - f.stamp))
        if abs(st[k] - f.stamp) <= max_dt:
            out.append((f, traj.poses[k]))
    if not out:
        raise ConfigError(f"{source}: no pose within {max_dt} s of any scan stamp")
    return out


def map_command(
    log: Path = typer.Argument(..., help="Robot log (CARMEN, MCAP, ROS 1 bag) with 2D laser scans."),
    out: Path = typer.Option(..., "--out", help="Output directory."),
    method: Method = typer.Option(Method.fastgpom, "--method", help="fastgpom, gpom or logodds."),
    resolution: float = typer.Option(0.05, "--resolution", parser=real(0.0, above=True), help="Cell size in metres."),
    poses: str = typer.Option("ground_truth", "--poses", help="ground_truth, odometry, or a TUM trajectory file."),
    topic: str | None = typer.Option(None, "--topic", help="Laser topic (MCAP / ROS 1)."),
    every: int = typer.Option(1, "--every", min=1, help="Use every n-th scan."),
    max_range: float = typer.Option(10.0, "--max-range", parser=real(0.0, above=True),
                                    help="Ranges beyond this (m) count as no return."),
    max_dt: float = typer.Option(0.05, "--max-dt", parser=real(0.0), help="Largest |scan stamp − TUM stamp| accepted (s)."),
    config: Path | None = typer.Option(None, "--config", help="Mapping configuration YAML (mapping.config.MappingConfig)."),
    plot_trajectory: bool = typer.Option(False, "--plot-trajectory", help="Draw the robot's path on map.png."),
) -> None:
    """Build an occupancy map from a log with given poses; writes map.pgm/.yaml/.png/.npz, variance.png, map.mcap."""
    import time

    import numpy as np
    import yaml

    from core.atomic import atomic_directory, check_output_dir
    from core.errors import ConfigError
    from core.yaml_config import load_yaml
    from mapping.beams import clip_range
    from mapping.config import MappingConfig
    from mapping.fastgpom import FastGPOM
    from mapping.gpom import ClassicGPOM
    from mapping.grid import GridGeometry
    from mapping.logodds import LogOddsGrid
    from mapping.occupancy_map import export_map, write_occupancy_grid
    from slam.logs import open_log
    from slam.logs.mcap_writer import McapLogWriter

    check_output_dir(out, MAP_MARKER)
    cfg = MappingConfig()
    if config is not None:
        cfg = load_yaml(MappingConfig, config)
    cfg = cfg.model_copy(update={"method": method.value, "resolution_m": resolution})
    reader = open_log(log, topic)
    frames = [clip_range(f, max_range) for i, f in enumerate(reader.frames()) if i % every == 0]
    frames = [f for f in frames if f.ranges is not None]
    if not frames:
        raise ConfigError(f"{log}: no 2D laser scans to map")
    pairs = _poses_for(frames, poses, max_dt)
    sensor_xy = np.array([(T @ f.base_T_sensor)[:2, 3] for f, T in pairs])
    geom = GridGeometry.covering(sensor_xy.min(0), sensor_xy.max(0), resolution, margin=max_range + resolution)
    mapper = {"fastgpom": FastGPOM, "gpom": ClassicGPOM, "logodds": LogOddsGrid}[method.value](geom, cfg)
    t0 = time.perf_counter()
    with _single_blas_thread():
        for f, T in pairs:
            mapper.update(f, T)
    dt = time.perf_counter() - t0
    m = mapper.to_map().crop_observed()
    with atomic_directory(out, MAP_MARKER) as tmp:  # all files or none; an earlier map folder is replaced
        path_xy = np.array([T[:2, 3] for _, T in pairs]) if plot_trajectory else None
        export_map(m, tmp, cfg.occupied_thresh, cfg.free_thresh, trajectory_xy=path_xy)
        with McapLogWriter(tmp / "map.mcap") as w:
            write_occupancy_grid(m, w, stamp=float(pairs[-1][0].stamp), occupied_thresh=cfg.occupied_thresh,
                                 free_thresh=cfg.free_thresh)
        with open(tmp / "mapping_config.yaml", "w") as fh:
            yaml.safe_dump(cfg.model_dump(mode="json"), fh, sort_keys=False)
    typer.echo(f"method: {method.value}")
    typer.echo(f"scans: {len(pairs)}")
    typer.echo(f"grid: {m.geometry.shape[1]}x{m.geometry.shape[0]} at {resolution} m")
    typer.echo(f"update_ms_per_scan: {1e3 * dt / len(pairs):.2f}")
    typer.echo(f"out: {out}")


def eval_map(
    map_npz: Path = typer.Argument(..., help="map.npz written by slam map."),
    gt_yaml: Path = typer.Argument(..., help="Ground-truth map_server YAML (+ image)."),
    plot: Path | None = typer.Option(None, "--plot", help="Save the ROC curve as a PNG."),
) -> None:
    """Scores of a map against a ground truth (unknown ground-truth cells ignored): ``auc`` (unobserved cells
    at p = 0.5), ``auc_observed`` (the cells the map observed), ``coverage`` (the ground truth's free space
    observed, isolated specks of free cells left out) and the best-threshold ``accuracy`` and ``f1`` (occupied class)."""
    from core.atomic import check_output_file
    from core.errors import MapFormatError
    from mapping.mapserver import read_map_server
    from mapping.occupancy_map import load_npz
    from mapping.roc import map_roc, map_scores, observed_on_grid, resample_to_grid

    if plot is not None:
        check_output_file(plot)
    m = load_npz(map_npz)
    gt = read_map_server(gt_yaml)
    if abs(gt.origin[2]) > 1e-12:
        raise MapFormatError(gt_yaml, "origin", "a rotated ground-truth origin (yaw ≠ 0) is not supported")
    p = resample_to_grid(m.probability, m.observed, m.origin, m.resolution, gt.shape, gt.origin[:2], gt.resolution)
    obs = observed_on_grid(m.observed, m.origin, m.resolution, gt.shape, gt.origin[:2], gt.resolution)
    sc = map_scores(p, obs, gt.classes, gt.resolution)
    auc = sc.auc
    typer.echo(f"auc: {auc:.6f}")
    typer.echo(f"auc_observed: {'–' if sc.auc_observed is None else f'{sc.auc_observed:.6f}'}")
    typer.echo(f"coverage: {sc.coverage:.4f}")
    typer.echo(f"accuracy: {sc.accuracy:.4f} (occupied at p ≥ {sc.accuracy_threshold:.3f})")
    typer.echo(f"f1: {sc.f1:.4f} (occupied at p ≥ {sc.f1_threshold:.3f})")
    if plot is not None:
        import matplotlib

        fpr, tpr, _ = map_roc(p, gt.classes)
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        from core.atomic import atomic_path

        fig, ax = plt.subplots(figsize=(5, 5), dpi=120)
        ax.plot(fpr, tpr, label=f"AUC = {auc:.4f}")
        ax.plot([0, 1], [0, 1], "k:", lw=0.8)
        ax.set_xlabel("false positive rate")
        ax.set_ylabel("true positive rate")
        ax.set_title(f"ROC: {map_npz.name} vs {gt_yaml.name}")
        ax.legend(loc="lower right")
        fig.tight_layout()
        with atomic_path(plot) as tmp:
            fig.savefig(tmp, format="png")
        plt.close(fig)
        typer.echo(f"plot: {plot}")


def register(app: typer.Typer, eval_app: typer.Typer) -> None:
    app.command("map")(map_command)
    eval_app.command("map")(eval_map)
