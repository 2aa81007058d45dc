"""Tools around training: the throughput benchmark, learning-curve plots, and storage outages on demand (an S3
server behind a proxy that refuses) for tests and benchmarks.

May import: train and everything below it.
"""
