"""MuJoCo's warnings as Python warnings: MuJoCo's own handler prints each one to stdout (with a blank line) every
time and appends it to ``MUJOCO_LOG.TXT`` in the working directory; a Python warning shows once per process and
can be filtered.
"""

from __future__ import annotations

import warnings

import mujoco


class MujocoWarning(UserWarning):
    """A warning from MuJoCo (model compilation or simulation)."""


IGNORED = ("compiler attribute 'settotalmass' is deprecated",)
"""Beginnings of warnings nobody can act on: gymnasium's own HalfCheetah model uses settotalmass."""


def route_mujoco_warnings() -> None:
    """Send MuJoCo's warnings through ``warnings`` from now on (call before making an env)."""
    mujoco.set_mju_user_warning(_warn)


def _warn(message: str) -> None:
    if not message.startswith(IGNORED):
        warnings.warn(message, MujocoWarning, stacklevel=1)
