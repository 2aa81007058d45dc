"""Experiment trackers (W&B, MLflow) fed from rank 0 off the training thread: one tracker run per training run.

May import: config, values, errors, files, redact.
"""
