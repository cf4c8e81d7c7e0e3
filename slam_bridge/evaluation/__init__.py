"""Evaluation layer: ``metrics`` (pose errors, similarity alignment, inlier counts against ground
truth), ``tracks`` (the front end's tracks against the true poses) and ``tables_ch3`` (the
chapter-3 experiment's summaries, tables and plots)."""
