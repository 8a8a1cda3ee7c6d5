"""KITTI odometry Velodyne scans (``sequences/NN/velodyne/*.bin``) as a stream of 3D Frames.

Layout (Geiger, Lenz, Urtasun, CVPR 2012, odometry devkit): ``sequences/NN/velodyne/FFFFFF.bin``
holds float32 little-endian ``(x, y, z, reflectance)`` rows in the Velodyne frame (x forward,
y left, z up; metres); ``sequences/NN/calib.txt`` has ``Tr`` (3×4, Velodyne → cam0);
``sequences/NN/times.txt`` one stamp (s) per frame; ``poses/NN.txt`` (beside ``sequences/``)
one row-major 3×4 pose of cam0 per frame, in the cam0 frame of frame 0. The SemanticKITTI layout
(Behley et al., ICCV 2019) keeps its poses, same format, in ``sequences/NN/poses.txt``; when both are
there that one is used: the official ground truth is a constant-velocity placeholder over the first
15 frames of sequence 00 (see ../shared/data/kitti_mini/SOURCE.md), SemanticKITTI's agrees with the scans.

Ground truth is expressed in the Velodyne frame: ``T_velo(k) = Tr⁻¹ · P_k · Tr`` (Tr, P_k padded
to 4×4), so that ``T_velo(0)`` is the identity when ``P_0`` is. Line k of the poses file belongs
to frame k (the file name's number), also when the frame files start later (e.g. at 000001).
The robot base of a KITTI frame is the Velodyne itself: ``base_T_sensor`` is the identity.

Memory is constant: one scan is loaded at a time; only the small pose and time tables are read
in full.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Iterator

import numpy as np

from core import geometry as geo
from core.errors import LogFormatError, TopicNotFoundError
from core.frame import Frame

from .base import LogInfo, LogReader, SkipHandler, TopicInfo, counting, lost

__all__ = ["KittiReader", "read_velodyne_bin", "read_calib", "read_kitti_poses", "KITTI_RATE_HZ"]

#: HDL-64E rotation rate; stamps are ``k / KITTI_RATE_HZ`` when there is no times.txt.
KITTI_RATE_HZ = 10.0
_TOPIC = "velodyne"
_ROW = 16  # bytes per point: 4 × float32


def read_velodyne_bin(path: str | Path, with_reflectance: bool = False):
    """Read one KITTI ``.bin`` scan.

    Returns:
        ``(N, 3)`` float64 points (m, Velodyne frame); with ``with_reflectance`` also the
        ``(N,)`` float64 reflectance in [0, 1].

    Raises:
        LogFormatError: the size is not a multiple of 16 bytes, or a coordinate is not finite.
    """
    p = Path(path)
    try:
        size = p.stat().st_size
    except OSError as exc:
        raise LogFormatError(p, None, f"cannot read: {exc.strerror or exc}") from None
    if size % _ROW:
        raise LogFormatError(p, f"byte {size - size % _ROW}",
                             f"size {size} bytes is not a multiple of 16 (x, y, z, reflectance float32 rows): truncated?")
    raw = np.fromfile(p, dtype="<f4").reshape(-1, 4)
    pts = raw[:, :3].astype(np.float64)
    if not np.isfinite(pts).all():
        bad = int(np.argmax(~np.isfinite(pts).all(axis=1)))
        raise LogFormatError(p, f"point {bad}", "coordinates must be finite")
    if with_reflectance:
        return pts, raw[:, 3].astype(np.float64)
    return pts


def _pad34(v: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :4] = v.reshape(3, 4)
    return T


def read_calib(path: str | Path) -> dict[str, np.ndarray]:
    """``calib.txt`` → ``{"P0": 4×4, …, "Tr": 4×4}`` (3×4 rows padded with ``0 0 0 1``)."""
    p = Path(path)
    out: dict[str, np.ndarray] = {}
    for i, line in enumerate(p.read_text(errors="replace").splitlines(), 1):
        if not line.strip():
            continue
        key, sep, rest = line.partition(":")
        toks = rest.split()
        if not sep or len(toks) != 12:
            raise LogFormatError(p, f"line {i}", f"expected 'KEY: 12 numbers', got {line[:40]!r}")
        try:
            v = np.array(toks, dtype=np.float64)
        except ValueError:
            raise LogFormatError(p, f"line {i}", "non-numeric calibration value") from None
        if not np.isfinite(v).all():
            raise LogFormatError(p, f"line {i}", "calibration values must be finite")
        out[key.strip()] = _pad34(v)
    return out


def read_kitti_poses(path: str | Path) -> np.ndarray:
    """``poses/NN.txt`` → ``(K, 4, 4)`` cam0 poses (row-major 3×4 per line)."""
    p = Path(path)
    lines = [ln for ln in p.read_text(errors="replace").splitlines()]
    while lines and not lines[-1].strip():
        lines.pop()
    rows = [ln.split() for ln in lines]
    for i, r in enumerate(rows, 1):
        if len(r) != 12:
            raise LogFormatError(p, f"line {i}", f"expected 12 numbers (row-major 3×4 pose), got {len(r)}")
    try:
        v = np.array(rows, dtype=np.float64).reshape(-1, 12)
    except ValueError:
        for i, r in enumerate(rows, 1):
            try:
                np.array(r, dtype=np.float64)
            except ValueError:
                raise LogFormatError(p, f"line {i}", "non-numeric pose value") from None
        raise
    if not np.isfinite(v).all():
        i = int(np.argmax(~np.isfinite(v).all(axis=1))) + 1
        raise LogFormatError(p, f"line {i}", "pose values must be finite")
    T = np.tile(np.eye(4), (len(v), 1, 1))
    T[:, :3, :4] = v.reshape(-1, 3, 4)
    return T


def _read_times(path: Path) -> np.ndarray:
    toks = path.read_text(errors="replace").split()
    try:
        t = np.array(toks, dtype=np.float64)
    except ValueError:
        for i, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
            try:
                float(line)
            except ValueError:
                if line.strip():
                    raise LogFormatError(path, f"line {i}", f"expected one stamp in seconds, got {line[:40]!r}") from None
        raise
    if not np.isfinite(t).all():
        raise LogFormatError(path, f"line {int(np.argmax(~np.isfinite(t))) + 1}", "stamps must be finite")
    return t


_NUM = re.compile(r"^\d+$")


class KittiReader(LogReader):
    """Streaming reader of a KITTI odometry Velodyne sequence (or one ``.bin`` file).

    Args:
        path: ``sequences/NN`` (with ``velodyne/`` and ``calib.txt``), its ``velodyne/`` folder,
            or one ``.bin`` scan.
        topic: None or ``"velodyne"`` (the only stream).
    """

    format = "kitti"

    def __init__(self, path: str | Path, topic: str | None = None) -> None:
        super().__init__(path, topic)
        if topic is not None and topic.strip().lstrip("/").lower() != _TOPIC:
            raise TopicNotFoundError(self.path, None, f"unknown KITTI topic {topic!r} (the only stream is 'velodyne')")
        p = self.path
        if p.is_dir():
            vel = p / "velodyne"
            if vel.is_dir():
                self.sequence_dir: Path | None = p
                self.bins = sorted(vel.glob("*.bin"))
            else:
                self.sequence_dir = p.parent if p.name == "velodyne" else None
                self.bins = sorted(p.glob("*.bin"))
        elif p.is_file():
            self.sequence_dir = p.parent.parent if p.parent.name == "velodyne" else None
            self.bins = [p]
        else:
            raise LogFormatError(p, None, "no such file or directory")
        if not self.bins:
            raise LogFormatError(p, None, "no scans: no velodyne/*.bin files")
        self._gt: np.ndarray | None | bool = False  # False = not loaded yet
        self._times: np.ndarray | None | bool = False

    # -- per-frame metadata -------------------------------------------------------------
    def frame_number(self, k: int) -> int:
        """The frame index of the k-th file (its numeric name, else its position)."""
        stem = self.bins[k].stem
        return int(stem) if _NUM.match(stem) else k

    @property
    def calib_path(self) -> Path | None:
        return self.sequence_dir / "calib.txt" if self.sequence_dir is not None else None

    @property
    def poses_path(self) -> Path | None:
        """The ground-truth poses: ``sequences/NN/poses.txt`` (SemanticKITTI) when it exists, else ``poses/NN.txt``
        beside ``sequences/`` (``sequences/NN/../../poses/NN.txt``, the odometry devkit's)."""
        if self.sequence_dir is None:
            return None
        semantic = self.sequence_dir / "poses.txt"
        if semantic.is_file():
            return semantic
        return self.sequence_dir.parent.parent / "poses" / f"{self.sequence_dir.name}.txt"

    def ground_truth_velo(self) -> np.ndarray | None:
        """``(K, 4, 4)`` ground truth ``T_velo(k) = Tr⁻¹ · P_k · Tr`` for every line of the poses file.

        None when the poses file or ``calib.txt`` (with ``Tr``) is missing.
        """
        if self._gt is False:
            gt = None
            pp, cp = self.poses_path, self.calib_path
            if pp is not None and pp.is_file() and cp is not None and cp.is_file():
                calib = read_calib(cp)
                if "Tr" not in calib:
                    raise LogFormatError(cp, None, "no 'Tr:' (Velodyne → cam0) line")
                Tr = calib["Tr"]
                gt = geo.inverse(Tr) @ read_kitti_poses(pp) @ Tr
            self._gt = gt
        return self._gt  # type: ignore[return-value]

    def _stamps(self) -> np.ndarray | None:
        if self._times is False:
            tp = self.sequence_dir / "times.txt" if self.sequence_dir is not None else None
            self._times = _read_times(tp) if tp is not None and tp.is_file() else None
        return self._times  # type: ignore[return-value]

    def stamp(self, k: int) -> float:
        """Stamp (s) of the k-th file: ``times.txt`` line, else ``frame_number / 10 Hz``."""
        num = self.frame_number(k)
        times = self._stamps()
        if times is None:
            return num / KITTI_RATE_HZ
        if num >= len(times):
            raise LogFormatError(self.sequence_dir / "times.txt", None,
                                 f"has {len(times)} stamps, frame {num} ({self.bins[k].name}) needs line {num + 1}")
        return float(times[num])

    def _gt_of(self, k: int) -> np.ndarray | None:
        gt = self.ground_truth_velo()
        if gt is None:
            return None
        num = self.frame_number(k)
        if num >= len(gt):
            raise LogFormatError(self.poses_path, None,
                                 f"has {len(gt)} poses, frame {num} ({self.bins[k].name}) needs line {num + 1}")
        return gt[num].copy()

    # -- LogReader ----------------------------------------------------------------------
    def frames(self, on_skip: SkipHandler | None = None) -> Iterator[Frame]:
        """Yield each scan: (N, 3) float64 points in the Velodyne frame, GT ``world_T_velo`` if known.

        With *on_skip*, a scan file that cannot be used (truncated, non-finite points, no stamp
        or pose line for it) is reported and skipped; ``Frame.index`` stays the file's position.
        """
        for k, b in enumerate(self.bins):
            try:
                frame = Frame(stamp=self.stamp(k), points=read_velodyne_bin(b), index=k, ground_truth=self._gt_of(k),
                              source=f"{b.name}")
            except LogFormatError as exc:
                if on_skip is None:
                    raise
                counting(on_skip, _TOPIC)(lost(exc, {_TOPIC: 1}))  # one scan file: one scan
                continue
            yield frame

    def has_ground_truth(self) -> bool:
        """True when a poses file (:attr:`poses_path`) and ``calib.txt`` are there (the frames then carry ground truth)."""
        return self.ground_truth_velo() is not None

    def scan_count_hint(self) -> int | None:
        """One scan per ``.bin`` file."""
        return len(self.bins)

    def info(self) -> LogInfo:
        """Summarise from the file sizes, checking each (a size not a multiple of 16 is an error)."""
        counts = []
        for b in self.bins:
            size = b.stat().st_size
            if size % _ROW:
                raise LogFormatError(b, f"byte {size - size % _ROW}",
                                     f"size {size} bytes is not a multiple of 16 (x, y, z, reflectance float32 rows): truncated?")
            counts.append(size // _ROW)
        has_gt = self.ground_truth_velo() is not None
        if has_gt:  # the poses file must cover every frame
            self._gt_of(max(range(len(self.bins)), key=self.frame_number))
        return LogInfo(
            path=str(self.path), format=self.format, sensor_topic=_TOPIC, scans=len(self.bins),
            beams_per_scan=int(np.median(counts)), dimension=3, start=self.stamp(0), end=self.stamp(len(self.bins) - 1),
            has_odometry=False, has_ground_truth=has_gt,
            topics=[TopicInfo(name=_TOPIC, msgtype="kitti/velodyne_bin", count=len(self.bins))],
        )
