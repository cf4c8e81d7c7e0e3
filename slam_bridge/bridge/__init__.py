"""The bridge from the networks to the fusion (thesis chapter 4).

:mod:`~slam_bridge.bridge.evidence` gathers the networks' per-pixel outputs on the map points,
:mod:`~slam_bridge.bridge.facades` reads the GIS building model and
:mod:`~slam_bridge.bridge.association` decides which points may be constrained to which facade.
"""
