"""Camera poses from images: correspondences, tracks, the adjustment of the given poses, the reprojection solver (Gauss-Newton / LM), the SfM bundle, single-pose fits (docs/method.md §5)."""
