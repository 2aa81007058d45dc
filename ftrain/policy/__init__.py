"""Policies outside the loop: the actor model, loading from any ftrain URL, rollouts, export, play, snapshots.

May import: ckpt, config, errors, progress.
"""
