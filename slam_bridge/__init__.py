"""slam_bridge: keyframe bundle adjustment with barrier-term fusion of GPS, DEM, odometry and
building models (Salehi 2018, chapters 1-3 and appendices B-C), fed by geoseg's networks."""

import logging

logging.getLogger(__name__).addHandler(logging.NullHandler())
