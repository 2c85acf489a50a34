"""Evaluating a run: metrics, the evaluation of a trained run against a scene, the two-stage baseline (docs/method.md §10)."""
