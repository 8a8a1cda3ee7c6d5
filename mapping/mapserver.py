"""ROS map_server maps: a YAML file plus a PGM/PNG image. The one reader/writer of the project.

Reading follows ROS 1 ``map_server/src/image_loader.cpp`` (the convention of every STDR and
Fast-GPOM map): the grey value of a pixel is the mean of its channels — in ``trinary`` mode the
alpha channel is averaged in too (a documented quirk of map_server kept "to preserve existing
behaviour"), in ``scale``/``raw`` mode it is not —, ``negate`` flips it (255 − grey), and

    p_occ = (255 − grey) / 255;  occupied (100) if p_occ > occupied_thresh,
    free (0) if p_occ < free_thresh, otherwise unknown (−1)  [trinary]
    or 1 + 98·(p_occ − free)/(occ − free)                    [scale; unknown if alpha == 0]

Image row 0 is the top (largest y); arrays here are ``[iy, ix]`` with row 0 at the origin (the
lower-left pixel), see ``docs/ARCHITECTURE.md`` — the flip happens only in this module.
``origin`` is the world pose (x, y, yaw) of the lower-left corner of the lower-left pixel.

Writing follows ``map_saver``: occupied → 0 (black), free → 254, unknown → 205 (grey), with
``occupied_thresh`` / ``free_thresh`` in the YAML, so that map_server reads the same classes back.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from core.atomic import atomic_path
from core.errors import MapFormatError

__all__ = ["MapServerMap", "read_map_server", "write_map_server", "classes_from_probability",
           "UNKNOWN", "FREE", "OCCUPIED"]

UNKNOWN, FREE, OCCUPIED = -1, 0, 100
_MODES = ("trinary", "scale", "raw")


@dataclass
class MapServerMap:
    """A map as map_server loads it.

    Attributes:
        occupancy: float64 ``(H, W)`` p_occ = (255 − grey)/255 in [0, 1] after ``negate`` (what
            map_server thresholds), row 0 = lowest y.
        classes: int8 ``(H, W)`` OccupancyGrid values: −1 unknown, 0 free, 100 occupied (and
            1…99 in ``scale`` mode, raw grey in ``raw`` mode).
        resolution: metres per cell.
        origin: ``(3,)`` x, y (m), yaw (rad) of the lower-left corner of cell ``[0, 0]``.
        occupied_thresh, free_thresh, negate, mode: the YAML parameters used.
        image_path: the image file that was read.
    """

    occupancy: NDArray[np.float64]
    classes: NDArray[np.int8]
    resolution: float
    origin: NDArray[np.float64]
    occupied_thresh: float
    free_thresh: float
    negate: bool
    mode: str = "trinary"
    image_path: str = ""

    @property
    def shape(self) -> tuple[int, int]:
        return (int(self.classes.shape[0]), int(self.classes.shape[1]))

    @property
    def extent(self) -> tuple[float, float]:
        """Width and height of the map in metres."""
        return (self.shape[1] * self.resolution, self.shape[0] * self.resolution)


def _load_yaml(path: Path) -> dict:
    import yaml

    try:
        text = path.read_text()
    except FileNotFoundError:
        raise MapFormatError(path, None, "no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise MapFormatError(path, None, f"cannot read map yaml ({exc})") from None
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}" if mark is not None else None
        raise MapFormatError(path, where, f"invalid YAML ({getattr(exc, 'problem', exc)})") from None
    if not isinstance(doc, dict):
        raise MapFormatError(path, None, "expected a YAML mapping with image, resolution, origin")
    return doc


def _yaml_line(path: Path, key: str) -> str | None:
    try:
        for i, line in enumerate(path.read_text().splitlines(), 1):
            if line.lstrip().startswith(f"{key}:"):
                return f"line {i}"
    except OSError:
        pass
    return None


def _number(path: Path, doc: dict, key: str, default: float | None = None) -> float:
    if key not in doc:
        if default is None:
            raise MapFormatError(path, None, f"missing required key '{key}'")
        return default
    v = doc[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(float(v)):
        raise MapFormatError(path, _yaml_line(path, key), f"'{key}' must be a finite number, got {v!r}")
    return float(v)


def _read_pixels(yaml_path: Path, image_path: Path) -> tuple[NDArray[np.float64], int]:
    """Return the pixels as float64 ``(rows, cols, channels)`` in image order, and the channel count."""
    from PIL import Image, UnidentifiedImageError

    if not image_path.exists():
        raise MapFormatError(yaml_path, _yaml_line(yaml_path, "image"), f"image file {image_path} does not exist")
    try:
        with Image.open(image_path) as im:
            im.load()
            mode = im.mode
            if mode == "P":
                im = im.convert("RGBA" if "transparency" in im.info else "RGB")
            elif mode == "1":
                im = im.convert("L")
            elif mode == "PA":
                im = im.convert("RGBA")
            elif mode not in ("L", "LA", "RGB", "RGBA"):
                raise MapFormatError(image_path, None, f"unsupported image mode {mode} (expected 8-bit grey, RGB or RGBA)")
            arr = np.asarray(im, dtype=np.float64)
    except MapFormatError:
        raise
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as exc:
        raise MapFormatError(image_path, None, f"cannot decode image ({exc})") from None
    if arr.ndim == 2:
        arr = arr[:, :, None]
    if arr.shape[0] == 0 or arr.shape[1] == 0:
        raise MapFormatError(image_path, None, "image is empty")
    return arr, arr.shape[2]


def read_map_server(yaml_path: str | Path) -> MapServerMap:
    """Load a map_server YAML + image exactly as ROS 1 map_server does (see module docstring).

    Raises:
        MapFormatError: missing/invalid YAML keys, missing or undecodable image, bad thresholds.
    """
    path = Path(yaml_path)
    doc = _load_yaml(path)
    if "image" not in doc or not isinstance(doc["image"], str) or not doc["image"]:
        raise MapFormatError(path, _yaml_line(path, "image"), "missing or empty 'image' entry")
    res = _number(path, doc, "resolution")
    if res <= 0:
        raise MapFormatError(path, _yaml_line(path, "resolution"), f"resolution must be > 0, got {res}")
    origin = doc.get("origin")
    if (not isinstance(origin, (list, tuple)) or len(origin) != 3
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in origin)):
        raise MapFormatError(path, _yaml_line(path, "origin"), f"'origin' must be [x, y, yaw], got {origin!r}")
    occ_th = _number(path, doc, "occupied_thresh", 0.65)
    free_th = _number(path, doc, "free_thresh", 0.196)
    if not (0.0 <= free_th <= occ_th <= 1.0):
        raise MapFormatError(path, _yaml_line(path, "free_thresh"),
                             f"need 0 <= free_thresh <= occupied_thresh <= 1, got {free_th}, {occ_th}")
    negate_raw = doc.get("negate", 0)
    if negate_raw not in (0, 1, True, False):
        raise MapFormatError(path, _yaml_line(path, "negate"), f"'negate' must be 0 or 1, got {negate_raw!r}")
    negate = bool(negate_raw)
    mode = str(doc.get("mode", "trinary")).lower()
    if mode not in _MODES:
        raise MapFormatError(path, _yaml_line(path, "mode"), f"'mode' must be one of {_MODES}, got {mode!r}")

    image_path = Path(doc["image"])
    if not image_path.is_absolute():
        image_path = path.parent / image_path
    arr, n = _read_pixels(path, image_path)
    has_alpha = n in (2, 4)
    avg_channels = n if (mode == "trinary" or not has_alpha) else n - 1
    color_avg = arr[:, :, :avg_channels].sum(axis=2) / avg_channels
    alpha = arr[:, :, n - 1] if n > 1 else np.full(color_avg.shape, 255.0)
    if negate:
        color_avg = 255.0 - color_avg
    occ = (255.0 - color_avg) / 255.0
    if mode == "raw":
        classes = np.trunc(color_avg).astype(np.uint8).astype(np.int8)  # map_server stores the byte as int8
    else:
        classes = np.full(occ.shape, UNKNOWN, dtype=np.int8)
        classes[occ > occ_th] = OCCUPIED
        classes[occ < free_th] = FREE
        if mode == "scale":
            mid = (occ <= occ_th) & (occ >= free_th) & (alpha >= 1.0)
            span = occ_th - free_th
            ratio = (occ - free_th) / span if span > 0 else np.zeros_like(occ)
            classes[mid] = (1 + 98 * ratio[mid]).astype(np.int8)
    return MapServerMap(
        occupancy=np.ascontiguousarray(occ[::-1]),
        classes=np.ascontiguousarray(classes[::-1]),
        resolution=res,
        origin=np.asarray(origin, dtype=np.float64),
        occupied_thresh=occ_th,
        free_thresh=free_th,
        negate=negate,
        mode=mode,
        image_path=str(image_path),
    )


def classes_from_probability(prob: ArrayLike, occupied_thresh: float = 0.65, free_thresh: float = 0.196) -> NDArray[np.int8]:
    """map_server thresholds on a probability grid: 100 if p > occ, 0 if p < free, else −1 (NaN → −1)."""
    p = np.asarray(prob, dtype=np.float64)
    out = np.full(p.shape, UNKNOWN, dtype=np.int8)
    with np.errstate(invalid="ignore"):
        out[p > occupied_thresh] = OCCUPIED
        out[p < free_thresh] = FREE
    return out


def _grey_band(occupied_thresh: float, free_thresh: float) -> tuple[int, int, int]:
    """Grey values map_server reads back as occupied, free and unknown for these thresholds."""
    g = np.arange(256, dtype=np.float64)
    p = (255.0 - g) / 255.0
    occ = np.flatnonzero(p > occupied_thresh)
    free = np.flatnonzero(p < free_thresh)
    unk = np.flatnonzero((p <= occupied_thresh) & (p >= free_thresh))
    if len(occ) == 0 or len(free) == 0 or len(unk) == 0:
        raise ValueError(f"thresholds free={free_thresh}, occupied={occupied_thresh} leave no grey value for a class")
    # map_saver's own values (0, 254, 205) when they fall into the right band, else a band member.
    occ_v = 0 if 0 in occ else int(occ[0])
    free_v = 254 if 254 in free else int(free[-1])
    unk_v = 205 if 205 in unk else int(unk[len(unk) // 2])
    return occ_v, free_v, unk_v


def write_map_server(
    yaml_path: str | Path,
    classes_or_prob: ArrayLike,
    resolution: float,
    origin: ArrayLike,
    *,
    image_name: str | None = None,
    occupied_thresh: float = 0.65,
    free_thresh: float = 0.196,
) -> None:
    """Write ``<yaml>`` and its image (``.pgm`` P5 by default, ``.png`` if *image_name* says so).

    Args:
        yaml_path: the YAML file to write; the image goes beside it.
        classes_or_prob: ``(H, W)`` grid, row 0 = lowest y. Integer input is OccupancyGrid classes
            (−1 unknown, 0…``free`` free, 100 occupied; values in between are thresholded like
            map_saver with ``occupied_thresh``/``free_thresh`` × 100). Float input is p_occ in
            [0, 1] with NaN = unknown; it is stored as grey = 255·(1 − p) *clamped into the band
            of its class*, so map_server reads back exactly the thresholded classes.
        resolution: metres per cell (> 0).
        origin: ``(x, y)`` or ``(x, y, yaw)`` of the lower-left corner of cell ``[0, 0]``.
        image_name: file name of the image (default ``<yaml stem>.pgm``).

    Both files are written to temporary names and renamed only when both are complete.
    """
    import yaml

    grid = np.asarray(classes_or_prob)
    if grid.ndim != 2 or grid.shape[0] == 0 or grid.shape[1] == 0:
        raise ValueError(f"map must be a non-empty 2-D array, got shape {grid.shape}")
    if not (resolution > 0 and math.isfinite(resolution)):
        raise ValueError(f"resolution must be a positive number, got {resolution}")
    org = np.asarray(origin, dtype=np.float64).ravel()
    if org.size == 2:
        org = np.append(org, 0.0)
    if org.size != 3 or not np.all(np.isfinite(org)):
        raise ValueError(f"origin must be (x, y[, yaw]), got {origin!r}")
    occ_v, free_v, unk_v = _grey_band(occupied_thresh, free_thresh)

    if np.issubdtype(grid.dtype, np.integer) or grid.dtype == bool:
        g = grid.astype(np.int16)
        grey = np.full(g.shape, unk_v, dtype=np.uint8)
        grey[(g >= 0) & (g <= free_thresh * 100.0)] = free_v
        grey[g >= occupied_thresh * 100.0] = occ_v
    else:
        p = grid.astype(np.float64)
        finite = np.isfinite(p)
        if np.any(finite & ((p < 0) | (p > 1))):
            raise ValueError("probabilities must lie in [0, 1] (NaN = unknown)")
        cls = classes_from_probability(p, occupied_thresh, free_thresh)
        gv = np.where(finite, np.rint(255.0 * (1.0 - np.where(finite, p, 0.5))), float(unk_v))
        # Clamp each grey into the band its class occupies when read back (rounding may cross it).
        bands = np.arange(256, dtype=np.float64)
        pb = (255.0 - bands) / 255.0
        occ_hi = float(np.flatnonzero(pb > occupied_thresh).max())      # largest grey still occupied
        free_lo = float(np.flatnonzero(pb < free_thresh).min())         # smallest grey still free
        unk = np.flatnonzero((pb <= occupied_thresh) & (pb >= free_thresh))
        gv = np.where(cls == OCCUPIED, np.minimum(gv, occ_hi), gv)
        gv = np.where(cls == FREE, np.maximum(gv, free_lo), gv)
        gv = np.where(cls == UNKNOWN, np.clip(gv, unk.min(), unk.max()), gv)
        gv = np.where(finite, gv, float(unk_v))
        grey = gv.astype(np.uint8)

    ypath = Path(yaml_path)
    name = image_name or (ypath.stem + ".pgm")
    ipath = ypath.parent / name
    img = np.ascontiguousarray(grey[::-1])  # image row 0 = top = largest y
    doc = {
        "image": name,
        "mode": "trinary",
        "resolution": float(resolution),
        "origin": [float(v) for v in org],
        "negate": 0,
        "occupied_thresh": float(occupied_thresh),
        "free_thresh": float(free_thresh),
    }
    with atomic_path(ipath) as tmp_img, atomic_path(ypath) as tmp_yaml:
        if name.lower().endswith(".pgm"):
            h, w = img.shape
            with open(tmp_img, "wb") as fh:
                fh.write(f"P5\n# CREATOR: gpslam write_map_server {resolution:.6f} m/pix\n{w} {h}\n255\n".encode())
                fh.write(img.tobytes())
        else:
            from PIL import Image

            fmt = "PNG" if name.lower().endswith(".png") else None
            if fmt is None:
                raise ValueError(f"image name must end in .pgm or .png, got {name!r}")
            Image.fromarray(img, mode="L").save(tmp_img, format=fmt)
        with open(tmp_yaml, "w") as fh:
            yaml.safe_dump(doc, fh, sort_keys=False, default_flow_style=None)
