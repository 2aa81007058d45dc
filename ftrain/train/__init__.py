"""Training: the loop, hooks (logging, evaluation, policy snapshots), MuJoCo envs with exact state, PPO.

May import: policy, ckpt, comm, config, errors, errorfile, files, heartbeat, track, redact, procfs, terminal.
"""
