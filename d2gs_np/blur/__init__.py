"""Blur formation: the exposure's virtual views and poses, the blurred render, the exposure length, the endpoint models (docs/method.md §4)."""
