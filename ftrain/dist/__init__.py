"""Process group over gloo, rank info, per-rank seeding, object collectives, shared-memory all-reduce, and torchrun
as the supervisor runs it (``torchrun.py``: a process of its own, never imported by the supervisor).

May import: lifeline (torch-free), proctitle, torch and the standard library only.
"""
