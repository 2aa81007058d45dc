"""MuJoCo's warnings as Python warnings: MuJoCo's own handler prints each one to stdout (with a blank line) every
time and appends it to ``MUJOCO_LOG.TXT`` in the working directory; a Python warning shows once per process and
can be filtered.
"""

from __future__ import annotations

import functools
import warnings

import mujoco


class MujocoWarning(UserWarning):
    """A warning from MuJoCo (model compilation or simulation)."""


IGNORED = r"compiler attribute 'settotalmass' is deprecated"
"""Gymnasium's own HalfCheetah model uses it: nothing a user could change."""


@functools.cache
def route_mujoco_warnings() -> None:
    """Send MuJoCo's warnings through ``warnings`` from now on (once per process; call before making an env)."""
    warnings.filterwarnings("ignore", message=IGNORED, category=MujocoWarning)
    mujoco.set_mju_user_warning(_warn)


def _warn(message: str) -> None:
    warnings.warn(message, MujocoWarning, stacklevel=1)
