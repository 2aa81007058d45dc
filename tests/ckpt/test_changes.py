"""What a refused resume names: the keys that keep two models from loading into each other, and only those."""

from __future__ import annotations

import json

from ftrain.ckpt.changes import config_change, model_change
from ftrain.config import load_config

from helpers import SMOKE


def test_a_model_change_names_each_key_that_decides_the_tensors_and_none_other() -> None:
    saved = load_config(SMOKE).public_dict()
    assert model_change(saved, saved) is None
    free = load_config(
        SMOKE,
        [
            "policy.obs_normalization_until=1000",
            "policy.final_noise_std=0.2",
            "algorithm.schedule=linear",
            "algorithm.schedule_iterations=8",
        ],
    ).public_dict()
    assert model_change(saved, free) is None, "when the normalizers freeze and where the noise ends: no new tensors"
    other = load_config(SMOKE, ["env.id=Hopper-v5", "policy.hidden_dims=[32,32]", "algorithm.gamma=0.9"]).public_dict()
    assert (
        model_change(saved, other) == 'env.id "HalfCheetah-v5" -> "Hopper-v5"; policy.hidden_dims [16, 16] -> [32, 32]'
    )


def test_model_change_names_a_policy_key_exactly_when_the_saved_models_would_not_be_the_same_network() -> None:
    """Every policy key of the config, changed alone. ``model_change`` names it ("another model", refused even with
    ``allow_config_change``) exactly when the models built from the two configs hold other tensors (names or
    shapes), or the saved weights loaded into the new ones compute other actions and values; a key of
    ``MODEL_FREE`` (when the normalizers freeze, a clip, where the noise starts and ends) leaves the tensors as they
    are and is a config change."""
    import torch
    from tensordict import TensorDict

    from ftrain.ckpt.changes import MODEL_FREE
    from ftrain.policy.model import build_actor, build_model
    from ftrain.values import dotted

    obs = TensorDict({"policy": torch.linspace(-3, 3, 17).unsqueeze(0)}, batch_size=[1])

    def models(config) -> dict:
        torch.manual_seed(0)
        return {"actor": build_actor(config, obs, 6), "critic": build_model(config, obs, "critic", 1)}

    def shapes(built: dict) -> dict:
        return {f"{n}.{k}": tuple(v.shape) for n, m in built.items() for k, v in m.state_dict().items()}

    other = {bool: lambda v: not v, int: lambda v: v + 1000, float: lambda v: v / 2 if v else 5.0}
    other |= {str: {"elu": "tanh", "scalar": "log"}.get, list: lambda v: [*v, 8]}
    base = load_config(SMOKE)
    checked = 0
    for key, value in dotted(base.public_dict()["policy"]).items():
        changes = [f"policy.{key}={json.dumps(other[type(value)](value))}"]
        if key == "final_noise_std":  # a ceiling needs the rate's horizon, and lies below the initial noise
            changes = ["policy.final_noise_std=0.2", "algorithm.schedule=linear", "algorithm.schedule_iterations=8"]
        changed = load_config(SMOKE, changes)
        saved, new = models(base), models(changed)
        loadable = shapes(saved) == shapes(new)
        if loadable:
            for name in new:
                new[name].load_state_dict(saved[name].state_dict())
        same = loadable and all(torch.equal(saved[name](obs), new[name](obs)) for name in new)
        named = model_change(base.public_dict(), changed.public_dict())
        assert (named is not None and f"policy.{key} " in named) == (key not in MODEL_FREE), (key, named)
        assert loadable if key in MODEL_FREE else not same, (key, loadable, same)
        checked += 1
    print(f"{checked} policy keys, each changed alone, against the models built and loaded")
    assert checked >= 8


def test_a_key_added_later_changed_alone_is_named_alone_with_the_value_it_had() -> None:
    """Keys newer than the first checkpoints are left out of the training part at their defaults: a probe's
    ``reward.normalize=true`` was told as "reward.clip (unset) -> 10.0; reward.normalize (unset) -> True". Every leaf
    under ``KEYS_ADDED_LATER`` (generated from ``Config``), changed alone: that key alone, old -> new."""
    from ftrain.config import KEYS_ADDED_LATER, Config, config_from_dict
    from ftrain.values import dotted

    defaults = Config().to_dict()
    leaves = [key for key in dotted(defaults) if any(key == k or key.startswith(f"{k}.") for k in KEYS_ADDED_LATER)]
    other = {bool: lambda v: not v, int: lambda v: v + 4, float: lambda v: v + 0.25, str: lambda v: "linear"}
    checked = 0
    for key in leaves:
        value = dotted(defaults)[key]
        if type(value) not in other or key == "env.total_envs":  # which puts env.num_envs out of the training part
            continue
        changed = Config().to_dict()
        section, _, leaf = key.rpartition(".")
        (changed[section] if section else changed)[leaf] = other[type(value)](value)
        current = config_from_dict(changed).public_dict()
        said = config_change(Config().public_dict(), current, None, None)
        old = f'"{value}"' if isinstance(value, str) else value
        assert said is not None and ";" not in said and said.startswith(f"{key} {old} -> "), (key, said)
        assert "(unset)" not in said, (key, said)
        checked += 1
    print(f"{checked} keys added later, each changed alone")
    assert checked >= 8
