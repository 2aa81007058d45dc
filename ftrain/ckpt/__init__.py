"""Checkpoints: step format and verification, storage (fsspec), resume selection, retention, the save path.

The save path is the manager (ranks agree) and its helper process (writes); `ftrain ckpt` lives here too.
May import: comm, config, values, errors, files, heartbeat, identity, lifeline, log_dir_lock, procfs, progress, redact.
"""
