"""Loop closure: candidate sources, one verifier, one acceptance stage (see :mod:`slam.loops.closer`)."""

from .closer import LoopCloser
from .config import LoopConfig
from .types import LoopClosure, LoopStats

__all__ = ["LoopCloser", "LoopConfig", "LoopClosure", "LoopStats"]
