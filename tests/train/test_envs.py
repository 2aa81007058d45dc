"""Environment state restores bit for bit into a freshly made env, across episode boundaries."""

import pytest
import torch

from ftrain.train.envs import MujocoVecEnv, take_rows


def _rollout(env: MujocoVecEnv, actions: list[torch.Tensor]) -> list[tuple]:
    out = []
    for action in actions:
        obs, rewards, dones, extras = env.step(action)
        out.append(
            (obs["policy"].clone(), rewards.clone(), dones.clone(), extras["time_outs"].clone(), extras["episodes"])
        )
    return out


@pytest.mark.parametrize("env_id", ["HalfCheetah-v5", "Hopper-v5", "Walker2d-v5", "Ant-v5"])
def test_state_roundtrip_is_bitwise(env_id: str) -> None:
    kwargs = {"max_episode_steps": 25}  # several time-limit resets inside the compared window
    env = MujocoVecEnv(env_id, 3, seed=7, kwargs=kwargs)
    generator = torch.Generator().manual_seed(0)

    def actions(n: int) -> list[torch.Tensor]:
        return [torch.rand(3, env.num_actions, generator=generator) * 2.4 - 1.2 for _ in range(n)]

    _rollout(env, actions(31))
    state = env.get_state()
    future = actions(60)
    expected = _rollout(env, future)

    fresh = MujocoVecEnv(env_id, 3, seed=12345, kwargs=kwargs)
    fresh.set_state(state)
    got = _rollout(fresh, future)

    assert sum(len(step[4][0]) for step in expected) >= 3, "the window should cross episode boundaries"
    for (o1, r1, d1, t1, e1), (o2, r2, d2, t2, e2) in zip(expected, got, strict=True):
        assert torch.equal(o1, o2)
        assert torch.equal(r1, r2)
        assert torch.equal(d1, d2)
        assert torch.equal(t1, t2)
        assert e1 == e2


def test_restore_without_derived_quantities_is_not_exact_for_ant() -> None:
    """Guards the reason MuJoCo's derived quantities are saved: Ant's reward reads xpos, so dropping them changes the
    next step."""
    env = MujocoVecEnv("Ant-v5", 1, seed=3)
    for _ in range(5):
        env.step(torch.full((1, env.num_actions), 0.5))
    state = env.get_state()
    action = torch.full((1, env.num_actions), -0.5)
    _, expected_reward, _, _ = env.step(action)

    fresh = MujocoVecEnv("Ant-v5", 1, seed=3)
    state["derived"] = torch.zeros_like(state["derived"])
    fresh.set_state(state)
    _, reward, _, _ = fresh.step(action)
    assert not torch.equal(reward, expected_reward)


def test_state_of_another_env_is_refused() -> None:
    state = MujocoVecEnv("Hopper-v5", 2, seed=1).get_state()
    with pytest.raises(ValueError, match="Hopper-v5"):
        MujocoVecEnv("Walker2d-v5", 2, seed=1).set_state(state)


def test_random_states_survive_as_words_at_the_edges_of_128_bits() -> None:
    env = MujocoVecEnv("HalfCheetah-v5", 2, seed=1)
    generators = [base.np_random.bit_generator for base in env._bases]
    edges = [(2**128 - 1, 2**127 + 1, 1, 2**32 - 1), (2**63, 2**64 - 1, 0, 0)]  # the increment is always odd
    for generator, (state, inc, has_uint32, uinteger) in zip(generators, edges, strict=True):
        generator.state = {
            "bit_generator": "PCG64",
            "state": {"state": state, "inc": inc},
            "has_uint32": has_uint32,
            "uinteger": uinteger,
        }
    expected = [generator.state for generator in generators]
    saved = env.get_state()
    assert saved["rng"].dtype == torch.int64 and saved["rng"].shape == (2, 6)
    assert saved["rng"].tolist() == [[-1, -1, -(2**63), 1, 1, 2**32 - 1], [0, -(2**63), 0, -1, 0, 0]]  # format 3

    fresh = MujocoVecEnv("HalfCheetah-v5", 2, seed=2)
    fresh.set_state(saved)
    assert [base.np_random.bit_generator.state for base in fresh._bases] == expected

    older = MujocoVecEnv("HalfCheetah-v5", 2, seed=3)
    older.set_state({**saved, "rng": expected})  # state format 2 kept numpy's state dicts
    assert [base.np_random.bit_generator.state for base in older._bases] == expected


def test_environments_move_between_vector_envs_by_index_bit_for_bit() -> None:
    """Two vector envs of 4 (two ranks' shares of 8) and one of 8 seeded as their union step alike; the rows 2-5 of
    the two, taken into a third of 4 (a resize's share), go on as rows 2-5 of the one of 8 (``take_rows``)."""
    kwargs = {"max_episode_steps": 20}
    whole = MujocoVecEnv("Hopper-v5", 8, seed=100, kwargs=kwargs)
    parts = [MujocoVecEnv("Hopper-v5", 4, seed=100 + 4 * part, kwargs=kwargs) for part in range(2)]
    generator = torch.Generator().manual_seed(0)
    for _ in range(30):
        action = torch.rand(8, whole.num_actions, generator=generator) * 2 - 1
        whole.step(action)
        for part, env in enumerate(parts):
            env.step(action[4 * part : 4 * part + 4])
    middle = MujocoVecEnv("Hopper-v5", 4, seed=999, kwargs=kwargs)
    middle.set_state(take_rows([env.get_state() for env in parts], 2, 4))
    for _ in range(30):  # across time limits and the terminations of a hopper
        action = torch.rand(8, whole.num_actions, generator=generator) * 2 - 1
        expected = whole.step(action)
        got = middle.step(action[2:6])
        assert torch.equal(got[0]["policy"], expected[0]["policy"][2:6])
        assert torch.equal(got[1], expected[1][2:6]) and torch.equal(got[2], expected[2][2:6])
