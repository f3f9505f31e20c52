"""Evaluation: trajectory error metrics (pure) and the files an evaluation leaves (TUM, JSON, PNG)."""
