"""Evaluation: trajectory and relation metrics, map ROC/AUC, loop scoring, the 2D laser simulator, reports."""
