"""Tools around training: the throughput benchmark and learning-curve plots.

May import: train and everything below it.
"""
