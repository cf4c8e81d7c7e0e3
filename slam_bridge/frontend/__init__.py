"""Observation sources of the SLAM loop: simulated landmark tracks and image tracks."""
