"""Tools around training: the throughput benchmark, learning-curve plots, and for tests and benchmarks storage
outages on demand (an S3 server behind a proxy that refuses) and a private etcd server.

May import: train, ckpt, config, values, errors, files, progress.
"""
