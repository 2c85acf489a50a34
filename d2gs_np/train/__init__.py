"""Training: the model (model.py), its loss terms (terms.py), step plugins (plugins.py) and the
trainer that runs them (trainer.py); configuration, stages, progressive schedule, densification,
pruning, run log and atomic checkpoints."""
