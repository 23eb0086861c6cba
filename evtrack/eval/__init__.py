"""Evaluation: accuracy metrics, benchmark runs, their tables, plots and videos."""
