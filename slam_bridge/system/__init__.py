"""System layer: the image SLAM's entry point (``image_slam``: inputs, run), the sensor logs it
reads (``sensor_logs``) and the files it writes (``outputs``)."""
