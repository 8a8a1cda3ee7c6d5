"""Report figures as PNG bytes (matplotlib, Agg back end, imported lazily).

Every figure labels its axes with units, uses fonts readable at report size, and — for anything
drawn in the world frame — an equal aspect ratio so that metres look like metres. Maps are drawn
with row 0 at the bottom (the grid convention of docs/ARCHITECTURE.md: ``origin="lower"``).
"""

from __future__ import annotations

import io
from typing import Sequence

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]

__all__ = ["trajectory_map_png", "error_along_png", "roc_png", "timings_png", "map_png", "sweep_png", "grouped_bars_png",
           "lines_png"]

_RC = {
    "font.size": 12,
    "axes.titlesize": 14,
    "axes.labelsize": 12,
    "legend.fontsize": 10,
    "xtick.labelsize": 10,
    "ytick.labelsize": 10,
    "figure.dpi": 110,
}

_COLOURS = {"estimate": "#d62728", "odometry": "#ff7f0e", "ground truth": "#1f77b4"}


def _plt():
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt


def _png(fig) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", bbox_inches="tight")
    _plt().close(fig)
    return buf.getvalue()


def _extent(shape: tuple[int, ...], resolution: float, origin: Sequence[float]) -> list[float]:
    h, w = shape[:2]
    return [origin[0], origin[0] + w * resolution, origin[1], origin[1] + h * resolution]


def _figure_grid(image: Array, resolution: float) -> tuple[Array, float]:
    """*image* reduced to about one cell a pixel of the figure (max over blocks of cells, unknown NaN cells not
    counting: a one-cell wall stays visible) and the reduced cell size; a map of 34 million cells made
    matplotlib hold ~4 GB of float copies for an 800-pixel figure."""
    from mapping.occupancy_map import PNG_CELLS, max_pool

    img = np.asarray(image, float)
    block = max(1, int(np.ceil(max(img.shape) / PNG_CELLS)))
    if block == 1:
        return img, resolution
    pooled, seen = max_pool(img, np.isfinite(img), block)
    return np.where(seen, pooled, np.nan), resolution * block


def trajectory_map_png(
    paths: dict[str, Array],
    probability: Array | None = None,
    resolution: float | None = None,
    origin: Sequence[float] | None = None,
    loops: Array | None = None,
    title: str = "Trajectory",
    bg_label: str = "occupancy probability",
) -> bytes:
    """Trajectories ``{label: (N, 2+) positions [m]}`` over the occupancy-probability map (if given).

    *loops* is an optional ``(M, 2, 2)`` array of loop-closure segments (world x, y of both nodes).
    """
    plt = _plt()
    with plt.rc_context(_RC):
        fig, ax = plt.subplots(figsize=(8, 7))
        if probability is not None and resolution is not None and origin is not None:
            cmap = plt.get_cmap("gray_r").copy()
            cmap.set_bad("#dfe8f0")  # unknown cells (NaN): pale blue-grey
            grid, cell = _figure_grid(probability, resolution)
            im = ax.imshow(grid, origin="lower", cmap=cmap, vmin=0.0, vmax=1.0,
                           extent=_extent(grid.shape, cell, origin), interpolation="nearest")
            cb = fig.colorbar(im, ax=ax, fraction=0.046, pad=0.03)
            cb.set_label(bg_label)
        if loops is not None and len(loops):
            segs = np.asarray(loops, float)
            xs = np.column_stack([segs[:, 0, 0], segs[:, 1, 0], np.full(len(segs), np.nan)]).ravel()
            ys = np.column_stack([segs[:, 0, 1], segs[:, 1, 1], np.full(len(segs), np.nan)]).ravel()
            ax.plot(xs, ys, color="#2ca02c", lw=1.5, alpha=0.9, zorder=7, label=f"loop closures ({len(segs)})")
            ax.plot(segs[:, :, 0].ravel(), segs[:, :, 1].ravel(), "o", color="#2ca02c", ms=4, zorder=7,
                    markerfacecolor="none")
        for label, P in paths.items():
            P = np.asarray(P, float)
            if len(P) == 0:
                continue
            c = _COLOURS.get(label)
            style = dict(ls="--", lw=1.3, zorder=5) if label == "ground truth" else dict(lw=1.4, zorder=4)
            ax.plot(P[:, 0], P[:, 1], color=c, label=label, **style)
            ax.plot(P[0, 0], P[0, 1], "o", color=c or "k", ms=5, zorder=6)
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        ax.set_title(title)
        ax.grid(True, alpha=0.3)
        ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.09), ncol=4, frameon=False)  # below: never hides the map
        return _png(fig)


def error_along_png(series: dict[str, tuple[Array, Array]], ylabel: str, title: str, points: bool = False) -> bytes:
    """Error curves ``{label: (time [s], error)}`` against time since the first stamp (*points*: markers only)."""
    plt = _plt()
    with plt.rc_context(_RC):
        fig, ax = plt.subplots(figsize=(9, 4))
        t0 = min(float(np.min(t)) for t, _ in series.values() if len(t))
        for label, (t, e) in series.items():
            order = np.argsort(t)
            style = dict(ls="none", marker=".", ms=3, alpha=0.6) if points else dict(lw=1.0)
            ax.plot(np.asarray(t)[order] - t0, np.asarray(e)[order], color=_COLOURS.get(label),
                    label=f"{label} (rmse {np.sqrt(np.mean(np.square(e))):.3g})", **style)
        ax.set_xlabel("time since start [s]")
        ax.set_ylabel(ylabel)
        ax.set_title(title)
        allv = np.concatenate([np.asarray(e, float) for _, e in series.values()])
        pos = allv[allv > 0]
        if points and pos.size and pos.max() > 100 * np.median(pos):  # errors spanning decades: log axis
            ax.set_yscale("log")
            ax.set_ylim(bottom=max(pos.min(), 1e-4) / 2)
        else:
            ax.set_ylim(bottom=0)
        ax.grid(True, alpha=0.3)
        ax.legend(loc="best")
        return _png(fig)


def roc_png(curves: dict[str, tuple[Array, Array, float]], title: str = "Map ROC against ground truth") -> bytes:
    """ROC curves ``{label: (fpr, tpr, auc)}`` with the chance diagonal."""
    plt = _plt()
    with plt.rc_context(_RC):
        fig, ax = plt.subplots(figsize=(5.5, 5.5))
        ax.plot([0, 1], [0, 1], ls="--", color="#999999", lw=1, label="chance (AUC 0.5)")
        for label, (fpr, tpr, auc) in curves.items():
            ax.plot(fpr, tpr, lw=2, label=f"{label} (AUC {auc:.3f})")
        ax.set_xlim(-0.01, 1.0)
        ax.set_ylim(0.0, 1.02)
        ax.set_aspect("equal")
        ax.set_xlabel("false-positive rate (free cells called occupied)")
        ax.set_ylabel("true-positive rate")
        ax.set_title(title)
        ax.grid(True, alpha=0.3)
        ax.legend(loc="lower right")
        return _png(fig)


def timings_png(timings: dict[str, float], title: str = "Stage timings") -> bytes:
    """Horizontal bars of wall-clock seconds per pipeline stage, largest first."""
    plt = _plt()
    total = timings.get("total")
    items = sorted(((k, v) for k, v in timings.items() if k != "total"), key=lambda kv: kv[1])
    with plt.rc_context(_RC):
        fig, ax = plt.subplots(figsize=(8, 0.5 * len(items) + 1.5))
        names = [k for k, _ in items]
        vals = np.array([v for _, v in items], float)
        bars = ax.barh(names, vals, color="#4c72b0")
        for b, v in zip(bars, vals):
            ax.text(b.get_width(), b.get_y() + b.get_height() / 2, f" {v:.3g} s", va="center", fontsize=10)
        ax.set_xlabel("wall-clock time [s]")
        ax.set_title(f"{title} (total {total if total is not None else vals.sum():.3g} s)")
        ax.set_xlim(0, vals.max() * 1.2 if vals.size and vals.max() > 0 else 1)
        ax.grid(True, axis="x", alpha=0.3)
        return _png(fig)


def map_png(image: Array, resolution: float, origin: Sequence[float], label: str, title: str, cmap: str = "viridis") -> bytes:
    """A scalar grid (e.g. the GP variance) in world coordinates with a colour bar."""
    plt = _plt()
    with plt.rc_context(_RC):
        fig, ax = plt.subplots(figsize=(8, 7))
        grid, cell = _figure_grid(image, resolution)
        im = ax.imshow(grid, origin="lower", cmap=cmap, extent=_extent(grid.shape, cell, origin), interpolation="nearest")
        cb = fig.colorbar(im, ax=ax, fraction=0.046, pad=0.03)
        cb.set_label(label)
        ax.set_aspect("equal")
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        ax.set_title(title)
        return _png(fig)


def sweep_png(rows: Sequence[dict], swept: Sequence[str], x: str, y: str, xlabel: str, ylabel: str,
              title: str = "Parameter sweep") -> bytes:
    """Points ``(row[x], row[y])`` of a parameter grid; one line per setting of all but the last swept
    name, joined along the last one, each point labelled with its value. Missing values (None) are skipped."""
    plt = _plt()
    swept = list(swept)
    last, others = (swept[-1], swept[:-1]) if swept else (None, [])
    series: dict[tuple, list[dict]] = {}
    for r in rows:
        series.setdefault(tuple(r[n] for n in others), []).append(r)
    with plt.rc_context(_RC):
        fig, ax = plt.subplots(figsize=(7, 5.5))
        for key, rs in series.items():
            pts = [(r[x], r[y], r[last] if last else None) for r in rs if r[x] is not None and r[y] is not None]
            if not pts:
                continue
            label = ", ".join(f"{n}={v:g}" for n, v in zip(others, key)) or (last or "base setting")
            ax.plot([p[0] for p in pts], [p[1] for p in pts], "o-", lw=1.5, ms=6, label=label)
            for px, py, v in pts:
                if v is not None:
                    ax.annotate(f"{v:g}", (px, py), textcoords="offset points", xytext=(5, 5), fontsize=9)
        ax.set_ylim(-0.02, 1.05)
        if x == "recall":
            ax.set_xlim(-0.02, 1.05)
        ax.set_xlabel(xlabel)
        ax.set_ylabel(ylabel)
        ax.set_title(title)
        ax.grid(True, alpha=0.3)
        if ax.lines:
            ax.legend(loc="lower left", title=f"points labelled by {last}" if others else None)
        return _png(fig)


def grouped_bars_png(groups: dict[str, dict[str, float | None]], ylabel: str, title: str,
                     reference: dict[str, float] | None = None, reference_label: str = "published") -> bytes:
    """Bars ``groups[group][label]`` side by side per group (e.g. relation error [m] per log, one bar per
    setting), with ``reference[group]`` as a hatched grey bar beside them (e.g. a published figure).
    Missing values (None) leave a gap."""
    plt = _plt()
    names = list(groups)
    labels = list(dict.fromkeys(k for g in groups.values() for k in g))
    ref = {k: v for k, v in (reference or {}).items() if k in groups and v is not None}
    n_bars = len(labels) + (1 if ref else 0)
    width = 0.8 / max(n_bars, 1)
    x = np.arange(len(names), dtype=float)
    with plt.rc_context(_RC):
        fig, ax = plt.subplots(figsize=(max(6.0, 1.2 * len(names) * max(n_bars, 1) * 0.5 + 3), 5))
        for j, lab in enumerate(labels):
            vals = np.array([np.nan if groups[g].get(lab) is None else float(groups[g][lab]) for g in names])
            ax.bar(x - 0.4 + width * (j + 0.5), vals, width, label=lab)
        if ref:
            vals = np.array([ref.get(g, np.nan) for g in names], float)
            ax.bar(x - 0.4 + width * (len(labels) + 0.5), vals, width, color="#bbbbbb", hatch="//",
                   edgecolor="#555555", label=reference_label)
        ax.set_xticks(x)
        ax.set_xticklabels(names, rotation=20 if len(names) > 4 else 0, ha="right" if len(names) > 4 else "center")
        ax.set_ylabel(ylabel)
        ax.set_title(title)
        ax.grid(True, axis="y", alpha=0.3)
        if labels or ref:
            ax.legend(fontsize=9)
        return _png(fig)


def lines_png(series: dict[str, list[tuple[float, float]]], xlabel: str, ylabel: str, title: str) -> bytes:
    """One line per series through its ``(x, y)`` points (sorted by x), e.g. a metric per log against a swept value."""
    plt = _plt()
    with plt.rc_context(_RC):
        fig, ax = plt.subplots(figsize=(7, 5))
        for label, pts in series.items():
            pts = sorted(p for p in pts if p[1] is not None and np.isfinite(p[1]))
            if pts:
                ax.plot([p[0] for p in pts], [p[1] for p in pts], "o-", lw=1.5, ms=6, label=label)
        ax.set_xlabel(xlabel)
        ax.set_ylabel(ylabel)
        ax.set_title(title)
        ax.grid(True, alpha=0.3)
        if ax.lines:
            ax.legend(fontsize=9)
        return _png(fig)
