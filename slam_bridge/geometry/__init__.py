"""Geometry layer: SO(3)/SE(3) (``lie``), the pinhole camera (``camera``), triangulation,
two-view initialisation and PnP (``multiview``), and the per-index segment sums they share with
the bundle adjustment (``sums``). Imports nothing of slam_bridge but :mod:`slam_bridge.errors`."""
