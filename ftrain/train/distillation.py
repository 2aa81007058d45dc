"""rsl-rl's Distillation built from an ftrain config: a student learns to imitate a trained teacher."""

from __future__ import annotations

from rsl_rl.algorithms import Distillation
from rsl_rl.models import MLPModel
from rsl_rl.storage import RolloutStorage

from ftrain.ckpt.steps import resolve_checkpoint_url
from ftrain.comm.group import RankInfo
from ftrain.config import Config, config_from_dict
from ftrain.errors import UserError
from ftrain.policy.load import load_policy
from ftrain.policy.model import build_actor
from ftrain.train.envs import MujocoVecEnv

WHOLE_TEACHER = (
    "a teacher is the checkpoint or policy snapshot of a run (distillation needs its actor's weights): pass that"
)
"""Why an exported policy file, or any other file, is no teacher."""


def build_distillation(config: Config, env: MujocoVecEnv, info: RankInfo) -> Distillation:
    """rsl-rl's Distillation: a student like a PPO actor learns to imitate the teacher loaded from
    ``config.teacher`` (any ftrain checkpoint URL, verified by its manifest; architecture from its own config)."""
    obs = env.get_observations()
    teacher_actor, identity, missing = _teacher(config, env, obs)
    student = build_actor(config, obs, env.num_actions, obs_set="student")
    storage = RolloutStorage("distillation", env.num_envs, config.num_steps_per_env, obs, [env.num_actions])
    a = config.algorithm
    alg = Distillation(
        student,
        teacher_actor,
        storage,
        num_learning_epochs=a.num_learning_epochs,
        gradient_length=a.gradient_length,
        learning_rate=a.learning_rate,
        max_grad_norm=a.max_grad_norm,
        loss_type=a.loss_type,
        multi_gpu_cfg=info.rsl_rl_cfg(),
    )
    alg.teacher_loaded = missing is None
    alg.teacher_missing = missing
    alg.teacher_identity = identity
    return alg


def _teacher(config: Config, env: MujocoVecEnv, obs) -> tuple[MLPModel, dict, str | None]:
    """The teacher's model, its identity (with its config, so that a resume builds it where the teacher is gone), and
    why ``config.teacher`` did not load, where it did not but this run's checkpoint holds the teacher: then the model
    is built from the stored config, its weights still to come from the restore (``teacher_loaded`` stays false)."""
    try:
        teacher = load_policy(config.teacher, config.storage.options, not_a_file=WHOLE_TEACHER)
    except UserError as error:  # which setting named it: a distillation config's teacher may not be the user's own
        missing = f"teacher={config.teacher}: {error}"
        if (identity := _stored_teacher(config)) is None:
            raise UserError(missing) from None
        return build_actor(config_from_dict(identity["config"]), obs, env.num_actions), identity, missing
    _check_teacher_fits(config, env, teacher)
    identity = {"source": teacher.source, "step": teacher.step, "digest": teacher.digest}
    return teacher.actor, {**identity, "config": teacher.manifest["config"]}, None


def _stored_teacher(config: Config) -> dict | None:
    """The teacher (identity and config) that the checkpoint this run resumes from learned from, if it has one: a
    resumed student keeps its teacher, whose weights its checkpoint holds, also once the teacher's own run has deleted
    that step (its retention). Where the run resumes from (``ckpt/resume.py``): its storage's newest verified step,
    else a ``resume=`` URL's. None for a fresh run, or a checkpoint of before the teacher's config was kept."""
    sources = [config.storage.url, *([config.resume] if config.resume not in ("auto", "never") else [])]
    for url in sources:
        try:
            _, _, manifest = resolve_checkpoint_url(url, config.storage.options, log=lambda line: None)
        except UserError:
            continue
        stored = manifest.get("teacher")
        return stored if isinstance(stored, dict) and "config" in stored else None
    return None


def _check_teacher_fits(config: Config, env: MujocoVecEnv, teacher) -> None:
    teacher_obs = teacher.actor.obs_dim
    teacher_actions = teacher.actor.distribution.output_dim if teacher.actor.distribution else None
    if teacher.config.env.id != config.env.id or teacher_obs != env.num_obs or teacher_actions != env.num_actions:
        raise UserError(
            f"teacher {teacher.source} was trained on {teacher.config.env.id} (observations {teacher_obs}, actions "
            f"{teacher_actions}) but the student trains on {config.env.id} (observations {env.num_obs}, actions "
            f"{env.num_actions}): pick a teacher trained on {config.env.id}"
        )
