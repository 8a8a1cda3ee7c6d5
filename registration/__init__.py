"""Rigid registration of point sets, and the shared base layer of gpslam.

``registration`` is the bottom package: besides alignment (SVD/Horn, SVD-ICP, KISS-ICP
odometry) it holds the four modules every other package shares and may import —
:mod:`registration.geometry` (SE(2)/SE(3)), :mod:`registration.frame` (``Frame``),
:mod:`registration.errors` (project exceptions) and :mod:`registration.atomic` (atomic output).
They live here because ``registration`` may import no other gpslam package.
"""
