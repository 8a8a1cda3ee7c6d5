"""The map container (μ, σ², p on a world grid) and its export / import.

Files written by :func:`export_map` (all through ``core.atomic``):
``map.pgm`` + ``map.yaml`` (ROS map_server, via :mod:`mapping.mapserver`), ``map.png`` (probability
with a colour bar), ``variance.png`` (GP maps only), ``map.npz`` (every array + geometry, the input
of ``slam eval map``). :func:`write_occupancy_grid` adds a ``nav_msgs/OccupancyGrid`` to an MCAP writer.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from core.atomic import atomic_path
from core.errors import MapFormatError

from .grid import GridGeometry

Array = NDArray[np.float64]

NPZ_KEYS = ("probability", "observed", "origin", "resolution")


@dataclass
class OccupancyMap:
    """An occupancy map in the world frame.

    Attributes:
        geometry: grid geometry (origin of the lower-left corner, m; resolution m/cell; shape).
        probability: ``(H, W)`` occupancy probability in [0, 1]; 0.5 where never observed.
        mean, variance: GP latent mean (+1 occupied … −1 free) and variance; None for log-odds maps.
        observed: ``(H, W)`` bool, cells updated at least once.
        method: ``fastgpom``, ``gpom`` or ``logodds``.
    """

    geometry: GridGeometry
    probability: Array
    mean: Array | None = None
    variance: Array | None = None
    observed: NDArray[np.bool_] | None = None
    method: str = ""

    def __post_init__(self) -> None:
        if self.observed is None:
            self.observed = np.ones(self.geometry.shape, bool)

    @property
    def resolution(self) -> float:
        return self.geometry.resolution

    @property
    def origin(self) -> Array:
        return np.array(self.geometry.origin, dtype=float)

    def classes(self, occupied_thresh: float = 0.65, free_thresh: float = 0.35) -> NDArray[np.int8]:
        """OccupancyGrid classes: 100 where p > occupied_thresh, 0 where p < free_thresh, −1 otherwise
        and wherever the cell was never observed."""
        out = np.full(self.geometry.shape, -1, np.int8)
        out[self.probability > occupied_thresh] = 100
        out[self.probability < free_thresh] = 0
        out[~self.observed] = -1
        return out

    def crop_observed(self, margin_cells: int = 2) -> "OccupancyMap":
        """The smallest sub-map holding every observed cell (plus a margin)."""
        ys, xs = np.nonzero(self.observed)
        if len(ys) == 0:
            return self
        h, w = self.geometry.shape
        y0, y1 = max(0, ys.min() - margin_cells), min(h, ys.max() + 1 + margin_cells)
        x0, x1 = max(0, xs.min() - margin_cells), min(w, xs.max() + 1 + margin_cells)
        r = self.resolution
        g = GridGeometry((self.geometry.origin[0] + x0 * r, self.geometry.origin[1] + y0 * r), r, (y1 - y0, x1 - x0))
        cut = (slice(y0, y1), slice(x0, x1))
        return OccupancyMap(g, self.probability[cut], None if self.mean is None else self.mean[cut],
                            None if self.variance is None else self.variance[cut], self.observed[cut], self.method)


def save_npz(m: OccupancyMap, path: str | Path) -> None:
    """``map.npz``: probability, observed, origin (x, y), resolution, method, and mean/variance if present."""
    arrays = dict(probability=m.probability, observed=m.observed, origin=m.origin,
                  resolution=np.array(m.resolution), method=np.array(m.method))
    if m.mean is not None:
        arrays.update(mean=m.mean, variance=m.variance)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, **arrays)


def load_npz(path: str | Path) -> OccupancyMap:
    """Inverse of :func:`save_npz`; raises MapFormatError naming the missing key."""
    p = Path(path)
    try:
        z = np.load(p, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise MapFormatError(p, None, f"not a readable .npz map ({exc})") from None
    with z:
        for k in NPZ_KEYS:
            if k not in z.files:
                raise MapFormatError(p, f"key {k!r}", f"missing; a map.npz holds {', '.join(NPZ_KEYS)}")
        prob = np.asarray(z["probability"], float)
        if prob.ndim != 2:
            raise MapFormatError(p, "key 'probability'", f"expected a 2-D array, got shape {prob.shape}")
        origin = np.asarray(z["origin"], float).ravel()
        geom = GridGeometry((float(origin[0]), float(origin[1])), float(z["resolution"]), prob.shape)
        mean = np.asarray(z["mean"]) if "mean" in z.files else None
        var = np.asarray(z["variance"]) if "variance" in z.files else None
        method = str(z["method"]) if "method" in z.files else ""
        return OccupancyMap(geom, prob, mean, var, np.asarray(z["observed"], bool), method)


PNG_CELLS = 800  # cells along the longer side of a map's PNG: about the figure's width in pixels


def max_pool(img: Array, mask: NDArray[np.bool_] | None, block: int) -> tuple[Array, NDArray[np.bool_] | None]:
    """*img* reduced by the maximum over ``block × block`` cells, and *mask* (True: observed) by any: a
    one-cell wall of a large map survives the reduction to the figure's pixels, where keeping every
    k-th cell (what nearest-neighbour display does) drops it. Cells outside *mask* do not count (a
    block with none observed is unobserved). Done in bands of *block* rows, so the extra memory is one
    band, not a copy of the map."""
    if block <= 1:
        return img, mask
    h, w = img.shape
    H, W = -(-h // block), -(-w // block)
    out = np.full((H, W), -np.inf)
    for r in range(H):
        band = np.asarray(img[r * block:(r + 1) * block], dtype=float)
        if mask is not None:
            band = np.where(mask[r * block:(r + 1) * block], band, -np.inf)
        pad = W * block - w
        if pad:
            band = np.pad(band, ((0, 0), (0, pad)), constant_values=-np.inf)
        out[r] = band.reshape(band.shape[0], W, block).max(axis=(0, 2))
    seen = np.isfinite(out)
    return np.where(seen, out, 0.0), (seen if mask is not None else None)


def _save_png(img: Array, path: Path, extent: tuple[float, float, float, float], label: str, cmap: str,
              vmin: float | None, vmax: float | None, mask: NDArray[np.bool_] | None,
              trajectory_xy: Array | None = None) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    # The figure is ~840 px wide: a map of more cells than that is max-pooled to about one cell a pixel
    # (walls, one cell thick, stay visible at any map size; matplotlib's float copies stay small).
    h, w = img.shape
    img, mask = max_pool(img, mask, max(1, int(np.ceil(max(h, w) / PNG_CELLS))))
    data = np.ma.masked_array(img, mask=None if mask is None else ~mask)
    fig, ax = plt.subplots(figsize=(7, 7 * h / max(w, 1) + 0.5), dpi=120)
    cm = plt.get_cmap(cmap).with_extremes(bad="#b0b0b0")
    im = ax.imshow(data, origin="lower", extent=extent, cmap=cm, vmin=vmin, vmax=vmax, interpolation="nearest")
    if trajectory_xy is not None and len(trajectory_xy):
        ax.plot(trajectory_xy[:, 0], trajectory_xy[:, 1], "-", color="tab:red", lw=0.8, label="trajectory")
        ax.set_xlim(extent[0], extent[1])
        ax.set_ylim(extent[2], extent[3])
    fig.colorbar(im, ax=ax, label=label, shrink=0.8)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)


def export_map(m: OccupancyMap, out_dir: str | Path, occupied_thresh: float = 0.65, free_thresh: float = 0.35,
               images: bool = True, trajectory_xy: Array | None = None) -> list[Path]:
    """Write map.yaml + map.pgm, map.npz and (with *images*) map.png and variance.png into *out_dir*;
    *trajectory_xy* ``(N, 2)`` (m), when given, is drawn on map.png."""
    from .mapserver import write_map_server

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written = [out / "map.yaml", out / "map.pgm", out / "map.npz"]
    cls = m.classes(occupied_thresh, free_thresh)
    write_map_server(out / "map.yaml", cls, m.resolution, (*m.origin, 0.0),
                     occupied_thresh=occupied_thresh, free_thresh=free_thresh)
    save_npz(m, out / "map.npz")
    if images:
        ext = m.geometry.extent
        _save_png(m.probability, out / "map.png", ext, "occupancy probability", "gray_r", 0.0, 1.0, None,
                  None if trajectory_xy is None else np.asarray(trajectory_xy, dtype=float)[:, :2])
        written.append(out / "map.png")
        if m.variance is not None:
            _save_png(m.variance, out / "variance.png", ext, "GP variance σ²", "viridis", None, None, m.observed)
            written.append(out / "variance.png")
    return written


def write_occupancy_grid(m: OccupancyMap, writer, topic: str = "/map", frame_id: str = "map", stamp: float = 0.0,
                         occupied_thresh: float = 0.65, free_thresh: float = 0.35) -> None:
    """Write the map as one ``nav_msgs/OccupancyGrid`` through an open MCAP writer.

    *writer* is a ``slam.logs.mcap_writer.McapLogWriter`` (passed in: ``mapping`` does not import
    ``slam``); cell classes as :meth:`OccupancyMap.classes`, origin = the grid's lower-left corner.
    """
    origin = np.eye(4)
    origin[:2, 3] = m.origin
    writer.write_occupancy_grid(topic, stamp, frame_id, m.resolution, origin, m.classes(occupied_thresh, free_thresh))
