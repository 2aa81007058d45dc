"""The environment of ``reach.xml``: a MujocoEnv subclass with its own observation, reward and reset.

A two-link arm moves in a plane (seen from above by the model's ``top`` camera). It earns minus the distance from its
fingertip to a red target; holding the fingertip on the target for ``hold_steps`` steps earns a bonus, and a new
target appears somewhere else. The target lives in MuJoCo (a mocap body: part of the physics state ftrain saves); how
long the fingertip has held it is Python state, which ``ftrain_state``/``ftrain_set_state`` hand to ftrain so that a
resumed run continues exactly.
"""

from pathlib import Path

import numpy as np
from gymnasium import spaces
from gymnasium.envs.mujoco import MujocoEnv

MODEL = Path(__file__).with_name("reach.xml")
TARGET_RADII = (0.1, 0.35)
"""Targets appear this far from the shoulder (the arm reaches 0.4)."""
TOUCH = 0.05
"""Fingertip-to-target distance that counts as touching."""
BONUS = 5.0
"""Reward for holding a target for ``hold_steps`` steps."""


class ReachEnv(MujocoEnv):
    metadata = {"render_modes": ["human", "rgb_array", "depth_array", "rgbd_tuple"], "render_fps": 50}

    def __init__(self, hold_steps: int = 5, **kwargs) -> None:
        kwargs.setdefault("camera_name", "top")
        observations = spaces.Box(-np.inf, np.inf, shape=(11,), dtype=np.float64)
        super().__init__(str(MODEL), frame_skip=2, observation_space=observations, **kwargs)
        self.hold_steps = hold_steps
        self.held = 0
        """Steps the fingertip has touched the current target."""
        self.reached = 0
        """Targets held this episode."""

    def step(self, action):
        self.do_simulation(action, self.frame_skip)
        distance = float(np.linalg.norm(self._to_target()))
        self.held = self.held + 1 if distance < TOUCH else 0
        reward = -distance - 0.01 * float(np.square(action).sum())
        if self.held >= self.hold_steps:
            reward += BONUS
            self.reached += 1
            self.held = 0
            self._new_target()
        if self.render_mode == "human":
            self.render()
        return self._observe(), reward, False, False, {"reached": self.reached}

    def reset_model(self):
        qpos = self.init_qpos + self.np_random.uniform(-0.1, 0.1, size=self.model.nq)
        qvel = self.init_qvel + self.np_random.uniform(-0.01, 0.01, size=self.model.nv)
        self.set_state(qpos, qvel)
        self.held = self.reached = 0
        self._new_target()
        return self._observe()

    # the Python state MuJoCo does not hold, for ftrain's checkpoints (plain data: numbers, lists, dicts, arrays)
    def ftrain_state(self) -> dict:
        return {"held": self.held, "reached": self.reached}

    def ftrain_set_state(self, state: dict) -> None:
        self.held, self.reached = state["held"], state["reached"]

    def _new_target(self) -> None:
        angle = self.np_random.uniform(-np.pi, np.pi)
        radius = self.np_random.uniform(*TARGET_RADII)
        self.data.mocap_pos[0, :2] = radius * np.cos(angle), radius * np.sin(angle)

    def _to_target(self) -> np.ndarray:
        return self.data.mocap_pos[0, :2] - self.data.site("tip").xpos[:2]

    def _observe(self) -> np.ndarray:
        angles = self.data.qpos
        return np.concatenate(
            [
                np.cos(angles),
                np.sin(angles),
                self.data.qvel,
                self._to_target(),
                self.data.mocap_pos[0, :2],
                [self.held / self.hold_steps],
            ]
        )
