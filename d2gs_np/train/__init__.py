"""Training: the model (model.py), its loss terms (terms.py), step plugins (plugins.py), the run's
set-up (setup.py) and the trainer that runs the steps (trainer.py); configuration, stages,
progressive schedule, learning rates, densification, pruning, the run folder, run log and atomic
checkpoints."""
