"""Rigid registration of point sets: closed-form alignment (SVD/Horn), SVD-ICP point-to-point and
point-to-plane, the correlative search, registration covariance and KISS-ICP odometry. Stands on
:mod:`core` only."""
