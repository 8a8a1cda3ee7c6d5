"""Pose-graph back ends: GTSAM (batch LM/GN, iSAM2) and the hand-written chordal Gauss-Newton solver."""
