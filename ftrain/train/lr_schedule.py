"""Linear learning-rate decay (``algorithm.schedule=linear``): from ``algorithm.learning_rate`` at the first
iteration to zero at iteration ``algorithm.schedule_iterations``.

Why: a step size large enough to learn fast early makes PPO's late updates overshoot, and the policy oscillates
around a good gait instead of settling on it (SB3's and CleanRL's MuJoCo PPOs anneal for the same reason; rsl-rl has
only a fixed and a KL-adaptive rate). The rate is a function of the iteration count alone, set before each update:
the same on every rank and in a resumed run, with no state of its own; the horizon is a key of its own rather than
the run's ``iterations``, which a config sets to the run it was tuned for. An ``iterations=N`` override without one
of the horizon sets the horizon to N too (``ftrain.config.load_config``): a short run anneals over itself, and, so
set, lengthened, over its new length (``ftrain.ckpt.resume``).
"""

from __future__ import annotations

from rsl_rl.algorithms import PPO

from ftrain.config import AlgorithmConfig


class LinearSchedule:
    def __init__(self, config: AlgorithmConfig) -> None:
        self.initial = config.learning_rate
        self.iterations = config.schedule_iterations

    def apply(self, alg: PPO, iteration: int) -> None:
        """Set the rate for the update of iteration ``iteration + 1`` (``iteration`` completed so far)."""
        alg.learning_rate = self.initial * max(0.0, 1.0 - iteration / self.iterations)
        for group in alg.optimizer.param_groups:
            group["lr"] = alg.learning_rate


def build_lr_schedule(config: AlgorithmConfig) -> LinearSchedule | None:
    return LinearSchedule(config) if config.schedule == "linear" else None


def horizon_notice(config: AlgorithmConfig, iterations: int) -> str | None:
    """The line that says a linear schedule's horizon is not the run's length (``iterations=200`` on a config that
    anneals over 1954: the rate ends far from zero; a run lengthened past its horizon trains on at rate zero)."""
    horizon = config.schedule_iterations
    if config.schedule != "linear" or horizon == iterations:
        return None
    fix = f"set algorithm.schedule_iterations={iterations} to anneal over this run"
    if horizon > iterations:
        final = config.learning_rate * (1.0 - (iterations - 1) / horizon)
        return (
            f"learning rate: algorithm.schedule_iterations={horizon} but iterations={iterations}, so the rate ends "
            f"at {final:.3g}, not near 0: {fix}"
        )
    return (
        f"learning rate: algorithm.schedule_iterations={horizon} but iterations={iterations}, so the last "
        f"{iterations - horizon} iterations run at rate 0 and change nothing: {fix}"
    )
