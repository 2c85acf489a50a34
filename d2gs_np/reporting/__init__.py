"""Reporting: plots of a run's log and the self-contained HTML report (docs/method.md §10)."""
