"""Accuracy against ground truth: points to the true surface, camera poses to the true poses."""
