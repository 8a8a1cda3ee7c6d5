"""gpslam's SLAM layer: log readers and writers, pose graphs, back ends, pipeline and CLI."""

__version__ = "0.1.0"
