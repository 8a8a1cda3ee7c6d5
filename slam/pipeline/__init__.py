"""The end-to-end SLAM pipeline: frames → odometry → keyframes → loop closures → pose graph → map."""

from .config import SlamConfig

__all__ = ["SlamConfig"]
