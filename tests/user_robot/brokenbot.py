"""A user's module with a bug: it does not import."""

import gymnasium

gymnasium.register(id="Broken-v0", entry_point="brokenbot:Nothing")
ROBOT = undefined_robot_name  # noqa: F821
