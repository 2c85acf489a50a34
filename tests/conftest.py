"""Shared pytest set-up: make helper modules in tests/ importable (``import render_fixtures``)."""
import os
import sys

sys.path.insert(0, os.path.dirname(__file__))
os.environ.setdefault("MPLBACKEND", "Agg")
