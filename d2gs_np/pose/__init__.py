"""Camera poses from images (docs/method.md §5): settings (config), correspondences, tracks, the adjustment
of the given poses, the reprojection solver (Gauss-Newton / LM; its CasADi functions in symbolic), the SfM
bundle, the LM core and robust loss both solvers share (lm), single-pose fits."""
