"""Training: the loop, hooks (logging, evaluation, policy snapshots), MuJoCo envs with exact state, PPO.

May import: policy, ckpt, dist, config, errors, errorfile, heartbeat.
"""
