"""Evaluation metrics and benchmark tables (the tracker issue)."""
