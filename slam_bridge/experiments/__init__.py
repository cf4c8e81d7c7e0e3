"""Experiments on the synthetic world: the only part of slam_bridge that imports geoseg.synth.

* :mod:`slam_bridge.experiments.landmarks`: points sampled on the city and their observations;
* :mod:`slam_bridge.experiments.simulated_tracks`: those observations served to the SLAM loop;
* :mod:`slam_bridge.experiments.fusion_ch3`: the chapter-3 fusion experiment (thesis §3.7).
"""
