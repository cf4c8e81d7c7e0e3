"""The keyframe SLAM: map, tracking, mapping, windows, fusion and the loop that runs them."""
