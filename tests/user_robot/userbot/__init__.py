"""Registers the test robots: importing ``userbot`` (``env.id=userbot:Arm-v0``) makes their ids known."""

import gymnasium

gymnasium.register(id="Arm-v0", entry_point="userbot.envs:Arm", max_episode_steps=40)
gymnasium.register(id="ForgetfulArm-v0", entry_point="userbot.envs:ForgetfulArm", max_episode_steps=40)
gymnasium.register(id="MemoryArm-v0", entry_point="userbot.envs:MemoryArm", max_episode_steps=40)
gymnasium.register(id="DictArm-v0", entry_point="userbot.envs:DictArm", max_episode_steps=40)
gymnasium.register(id="NotMujoco-v0", entry_point="userbot.envs:NotMujoco", max_episode_steps=40)
gymnasium.register(id="EndlessArm-v0", entry_point="userbot.envs:Arm")  # no time limit
