"""Other tools' formats in and out: COLMAP sparse models, DyBluRF / Stereo Blur folders, TUM trajectories (docs/dataset_format.md §9-11)."""
