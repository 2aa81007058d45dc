"""`ftrain supervise`: main loop, attempts and process discovery, hang detection, node coordination, events.

May import: ckpt (the storage's lease), config, errors, errorfile, heartbeat, identity, lifeline, log_dir_lock,
procfs, proctitle (torchrun's agent is found by its title), progress, redact, terminal, warm. Besides them, the
standard library: no torch, mujoco or rsl-rl (a test checks).
"""
