"""Two hinges that learn to hold joint angles, with and without Python state MuJoCo does not hold."""

from pathlib import Path

import gymnasium
import numpy as np
from gymnasium import spaces
from gymnasium.envs.mujoco import MujocoEnv

HERE = Path(__file__).parent


class Arm(MujocoEnv):
    """Reward: minus the distance of the joint angles from ``target`` (zero), minus a little effort."""

    metadata = {"render_modes": ["human", "rgb_array", "depth_array", "rgbd_tuple"], "render_fps": 50}

    def __init__(self, xml_file: str = "robot.xml", **kwargs) -> None:
        observations = spaces.Box(-np.inf, np.inf, (6,), np.float64)
        super().__init__(str(HERE / xml_file), frame_skip=2, observation_space=observations, **kwargs)
        self.target = np.zeros(2)

    def step(self, action):
        self.do_simulation(action, self.frame_skip)
        reward = -np.linalg.norm(self.data.qpos - self.target) - 0.01 * np.square(action).sum()
        return self._observe(), reward, False, False, {}

    def reset_model(self):
        self.set_state(self.init_qpos + self.np_random.uniform(-0.5, 0.5, 2), self.init_qvel)
        return self._observe()

    def _observe(self):
        return np.concatenate([self.data.qpos, self.data.qvel, self.target])


class ForgetfulArm(Arm):
    """A random target per episode and a count of the steps held near it: Python state, which it does not offer."""

    def reset_model(self):
        self.target = self.np_random.uniform(-1, 1, 2)
        self.held = 0
        return super().reset_model()

    def step(self, action):
        observation, reward, terminated, truncated, info = super().step(action)
        self.held = self.held + 1 if np.linalg.norm(self.data.qpos - self.target) < 0.5 else 0
        return observation, reward + 0.1 * min(self.held, 10), terminated, truncated, info


class MemoryArm(ForgetfulArm):
    """The same, offering its Python state to ftrain."""

    def ftrain_state(self):
        return {"target": self.target, "held": self.held}

    def ftrain_set_state(self, state):
        self.target, self.held = state["target"], state["held"]


class DictArm(Arm):
    """Observations in a dict: not a flat Box."""

    def __init__(self, **kwargs) -> None:
        super().__init__(**kwargs)
        self.observation_space = spaces.Dict({"angles": spaces.Box(-np.inf, np.inf, (6,), np.float64)})


class NotMujoco(gymnasium.Env):
    """Flat Box spaces, but no MuJoCo inside."""

    observation_space = spaces.Box(-1.0, 1.0, (3,), np.float32)
    action_space = spaces.Box(-1.0, 1.0, (1,), np.float32)
