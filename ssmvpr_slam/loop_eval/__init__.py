"""`loop-eval`: the loop-closure-detection benchmark, run through the detector `run` builds.

Loop-closure-detection papers (DBoW2, iBoW-LCD, FILD, FAB-MAP) stream one sequence and report
the maximum recall at 100 % precision; a SLAM user also needs precision and recall at the
decision the detector actually ships. `loop-eval` streams image sequences through the exact
`LoopDetector` a run builds (same config layers, PCA warm-up or codebooks, sequence matcher,
calibrated decision) and reports both, against ground truth given as two frame-aligned passes,
poses, or a published loop matrix.
"""
