"""Training: configuration, stages and hooks, run log, atomic checkpoints, progressive schedule."""
