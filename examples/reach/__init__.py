"""A two-link arm that learns to touch one target after another, registered with gymnasium on import.

``env.id=examples.reach:Reach-v0`` makes gymnasium (and ftrain, in every process) import this package, whose import
registers ``Reach-v0``. Copy the directory, rename it, and register your own robot the same way.
"""

import gymnasium

gymnasium.register(id="Reach-v0", entry_point="examples.reach.env:ReachEnv", max_episode_steps=200)
