"""``slam eval nees``: the consistency of the front end's covariance, chain by chain, against relations (or,
where a log has none, against the run's own loop closures)."""

from __future__ import annotations

from pathlib import Path

import typer

from .eval_io import JSON_OPTION, check_json, save_json
from .options import real

__all__ = ["nees_cmd"]


def nees_cmd(
    run: Path = typer.Argument(..., help="A slam run folder (graph.g2o, node_stamps.txt, odometry.tum)."),
    relations: Path | None = typer.Argument(None, help="Ground-truth relations 't1 t2 x y z roll pitch yaw' (Kümmerle et al. 2009); without them, the run's own loop closures (graph.g2o) are the reference."),
    stamp_tol: float = typer.Option(1e-3, "--stamp-tol", parser=real(0.0), help="Stamp matching tolerance (s)."),
    heading_drift: float | None = typer.Option(None, "--heading-drift", parser=real(0.0), help="σ of the loop closer's heading rate (° per m) added to the chain's covariance; default: 0 under a walk and jitter (the run's calibration, or given), the run's config.yaml (loops.heading_drift_deg_per_m) with the edges as stated; 0: none."),
    turn_drift: float = typer.Option(0.0, "--turn-drift", parser=real(0.0), help="σ of a scale error of the odometry's rotation (rad per rad of signed turn) added to the chain's covariance (the loop closer models none; docs/LOOP_CLOSURE.md); 0: none."),
    walk: float | None = typer.Option(None, "--walk", parser=real(0.0), help="Scale of the steps' covariance before it compounds along a chain; default: the run's own calibration (summary.json chain_model), or 1 (the edges as stated) where it has none."),
    jitter: float | None = typer.Option(None, "--jitter", parser=real(0.0), help="A per-keyframe error the next step undoes: this many times the median step covariance added at both ends of every chain instead of compounded (docs/LOOP_CLOSURE.md, 'The registration's error is jitter'); default: the run's calibration, or 0."),
    fit_the_walk: bool = typer.Option(False, "--fit-walk", help="Fit the walk (overriding --walk) so that the chains of at least 101 keyframes average NEES/dof 1 against the reference (the closures, without RELATIONS), with the --jitter given or, without it, the jitter that keeps a step's stated covariance (1 − walk) / 2: the run's calibration, made against this reference."),
    reference: bool = typer.Option(True, "--reference-noise/--no-reference-noise", help="Add the relations' own error, estimated from the triangles they close among themselves (a → b, b → c, a → c), to each chain's covariance."),
    json_out: Path | None = JSON_OPTION,
) -> None:
    """Consistency of the front end's covariance: NEES/dof of its keyframe chains against the relations (or the
    run's own closures), per chain length (1 = consistent; above, overconfident; below, conservative)."""
    check_json(json_out)
    import numpy as np

    from core.errors import InputFileError
    from core.trajectory import read_node_stamps
    from evaluation.chain_model import LONG_CHAIN_KEYFRAMES
    from evaluation.nees import bin_by_length, chain_sample, closure_sample, heading_by_path, heading_fit
    from evaluation.relations import read_relations, reference_noise
    from evaluation.trajectory import nearest_indices
    from slam.graph import read_graph
    from slam.pipeline.consistency import graph_chain, graph_closures
    from slam.trajectory_io import read_trajectory

    graph = read_graph(run / "graph.g2o")
    if graph.dim != 2:
        raise InputFileError(run / "graph.g2o", None, "is not a planar graph; the NEES table is for 2D runs")
    try:
        mu, cov = graph_chain(graph)
    except ValueError as err:
        raise InputFileError(run / "graph.g2o", None, str(err)) from None
    stated = walk is None and jitter is None and not fit_the_walk
    calibrated = _run_chain_model(run) if stated else None
    if heading_drift is None:  # a walk and jitter, calibrated or given, take the heading rate's place
        heading_drift = _run_heading_drift(run) if stated and not calibrated else 0.0
    drift = float(np.radians(heading_drift))
    noise = None
    if relations is None:
        closures = graph_closures(graph)
        if not closures:
            raise InputFileError(run / "graph.g2o", None, "holds no loop closure to test the chains against; give RELATIONS")
        sample = closure_sample(mu, cov, closures, drift, turn_drift)
        source = run / "graph.g2o"
        typer.echo(f"closures: {len(sample)} (the run's own, with their covariance added to every chain); "
                   f"heading rate σ {heading_drift:g} °/m, rotation scale σ {turn_drift:g}")
    else:
        node_t = read_node_stamps(run / "node_stamps.txt", graph.node_ids)
        scans = read_trajectory(run / "odometry.tum")
        kf_scan = np.searchsorted(node_t, scans.stamps + stamp_tol, side="right") - 1
        ia, sa = nearest_indices(node_t, scans.stamps, stamp_tol)
        if len(ia) != len(node_t):
            raise InputFileError(run / "node_stamps.txt", None, "a keyframe stamp has no scan in odometry.tum")
        kf_odom = scans.poses[sa]
        rel = read_relations(relations)
        i1, s1 = nearest_indices(rel.t1, scans.stamps, stamp_tol)
        i2, s2 = nearest_indices(rel.t2, scans.stamps, stamp_tol)
        both = np.intersect1d(i1, i2)
        m1, m2 = dict(zip(i1, s1)), dict(zip(i2, s2))
        keep = [r for r in both if kf_scan[m1[r]] >= 0 and kf_scan[m2[r]] >= 0]
        if not keep:
            raise InputFileError(relations, None, f"no relation has both stamps among the scans of {run} (within --stamp-tol {stamp_tol} s)")
        pairs = np.array([(m1[r], m2[r]) for r in keep], dtype=np.int64)
        noise = reference_noise(rel) if reference else None
        sample = chain_sample(mu, cov, kf_scan, scans.poses, kf_odom, pairs, rel.deltas[keep], drift,
                              None if noise is None else noise.covariance(), turn_drift)
        source = relations
        typer.echo(f"relations: {len(sample)} (of {len(rel)}; within one keyframe interval or unmatched: {len(rel) - len(sample)}); "
                   f"heading rate σ {heading_drift:g} °/m, rotation scale σ {turn_drift:g}")
        if noise is not None:
            typer.echo(f"relations' own error, from {noise.triangles} triangles: σ {noise.sigma_translation_m:.4f} m per axis, "
                       f"{np.degrees(noise.sigma_rotation_rad):.3f}° (added to every chain)")
            if noise.sigma_translation_m < 1e-6:
                typer.echo("  (they close exactly among themselves: differences of one trajectory, whose own error, if any, "
                           "is a bias no triangle shows)")
        elif reference:
            typer.echo("relations' own error: not estimated (fewer than 20 triangles among the relations)")
    if fit_the_walk:
        walk, jitter = _fitted(sample, jitter, source)
        model = "fitted"
        typer.echo(f"walk fitted: {walk:.4g}, jitter {jitter:.4g} (chains of at least {LONG_CHAIN_KEYFRAMES} keyframes average 1)")
    elif calibrated:
        walk, jitter, model = calibrated["walk"], calibrated["jitter"], "run"
        typer.echo(f"chain model: the run's own calibration (summary.json, from {calibrated['long_chains']} closures): "
                   f"walk {walk:.4g}, jitter {jitter:.4g}")
    else:
        model = "given" if walk is not None or jitter is not None else "edges"
        walk, jitter = (1.0 if walk is None else walk), (0.0 if jitter is None else jitter)
        typer.echo(f"chain model: walk {walk:g}, jitter {jitter:g}" + (" (the edges as stated)" if model == "edges" else ""))
    rows = sample.rows(walk, jitter)
    bins = bin_by_length(rows)
    typer.echo(f"{'keyframes':>12} {'n':>6} {'NEES/dof':>9} {'median':>8} {'rms_m':>8} {'σ_m':>8} {'rms_deg':>8} {'σ_deg':>8}")
    for b in bins:
        span = f'{b.lo}+' if b.hi >= 10**8 else f'{b.lo}-{b.hi}'
        typer.echo(f"{span:>12} {b.n:>6} {b.nees_mean:>9.3f} {b.nees_median:>8.3f} {b.rms_translation_m:>8.4f} "
                   f"{b.sigma_translation_m:>8.4f} {b.rms_rotation_deg:>8.3f} {b.sigma_rotation_deg:>8.3f}")
    by_path = heading_by_path(rows)
    if by_path:
        typer.echo("heading error by odometry path between the keyframes:")
        typer.echo(f"{'path_m':>12} {'n':>6} {'med_deg':>8} {'p95_deg':>8} {'med_°/m':>8} {'p95_°/m':>8} {'σ_deg':>8}")
        for h in by_path:
            span = f"{h.lo_m:.0f}+" if not np.isfinite(h.hi_m) else f"{h.lo_m:.0f}-{h.hi_m:.0f}"
            typer.echo(f"{span:>12} {h.n:>6} {h.error_median_deg:>8.2f} {h.error_p95_deg:>8.2f} {h.rate_median_deg_per_m:>8.4f} "
                       f"{h.rate_p95_deg_per_m:>8.4f} {h.sigma_median_deg:>8.2f}")
    fit = heading_fit(rows)
    if fit is not None:
        typer.echo(f"heading error of the {fit.n} chains over {fit.min_path_m:g} m, fitted: {fit.rate_deg_per_m:+.4f} °/m of path "
                   f"{fit.scale_rad_per_rad:+.4f} rad/rad of signed turn (median |turn| {fit.turn_median_deg:.0f}°); residual "
                   f"{fit.rms_deg:.2f}° rms ({fit.rms_rate_only_deg:.2f}° with the rate alone)")
    save_json(json_out, {"reference": "relations" if relations is not None else "closures",
                          "relations" if relations is not None else "closures": len(rows),
                          "heading_drift_deg_per_m": heading_drift, "turn_drift_rad_per_rad": turn_drift,
                          "model": model, "walk": walk, "walk_fitted": fit_the_walk, "jitter": jitter,
                          "bins": [b.as_dict() for b in bins],
                          "heading_by_path": [h.as_dict() for h in by_path],
                          "heading_fit": None if fit is None else fit.as_dict(),
                          "reference_noise": None if noise is None else {
                              "sigma_translation_m": noise.sigma_translation_m,
                              "sigma_rotation_deg": float(np.degrees(noise.sigma_rotation_rad)), "triangles": noise.triangles}})


def _fitted(sample, jitter: float | None, source: Path) -> tuple[float, float]:  # type: ignore[no-untyped-def]
    """:func:`evaluation.chain_model.fit_walk` of the *sample* (walk, jitter), or a one-line error naming *source*."""
    from core.errors import InputFileError
    from evaluation.chain_model import LONG_CHAIN_KEYFRAMES, fit_walk, split_jitter

    fitted = fit_walk(sample, jitter)
    if fitted is None:
        raise InputFileError(source, None, f"fewer than 30 chains of {LONG_CHAIN_KEYFRAMES} keyframes or more to fit the walk to")
    return fitted[0], split_jitter(fitted[0]) if jitter is None else jitter


def _run_chain_model(run: Path) -> dict | None:
    """The run's own calibrated chain model (``summary.json``'s ``chain_model``), or None where it has none (no
    summary, or too few closures to calibrate on); a summary that is not one is an error naming it."""
    from core.run_summary import read_run_summary

    if not (run / "summary.json").is_file():
        return None
    return read_run_summary(run / "summary.json").chain_model


def _run_heading_drift(run: Path) -> float:
    """The heading-rate σ (°/m) of the run's own configuration (``config.yaml``), or the default one."""
    from core.errors import ConfigError
    from core.yaml_config import load_yaml
    from slam.pipeline.config import SlamConfig

    try:
        return load_yaml(SlamConfig, run / "config.yaml").loops.heading_drift_deg_per_m
    except ConfigError:
        return SlamConfig().loops.heading_drift_deg_per_m
