"""Test and bench support, outside the SLAM: ``bal`` (a reader of Bundle Adjustment in the Large
problems) and ``scenes`` (synthetic street scenes with known cameras and points). Only tests and
benches import it."""
