"""Process group over gloo, rank info, per-rank seeding, object collectives, shared-memory all-reduce.

May import: torch and the standard library only.
"""
