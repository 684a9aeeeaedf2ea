"""The search's objective: the reward a particle search scores in place of the task's (MC-PILCO's shaping)."""

from __future__ import annotations

from torch import Tensor

from qtl.errors import UserError
from qtl.gaussian import Gaussian
from qtl.kernels.engine import DEFAULT_ENGINE, Engine
from qtl.rewards import AngleDistanceReward, ExpectedSaturatingReward, RewardMixture

# The search's base reward: the task's widened, the task's declared search cost, or that where it declares one.
SEARCH_COSTS = ("widened", "task", "auto")


class SearchReward:
    """(1 − w) × base + w × the task's reward: what a search scores when it is not the task's own reward.

    ``is_search_reward`` (True) and ``name`` tell it from a task's reward; ``task_reward`` is the task's,
    ``reward`` the composed one that is evaluated.
    """

    is_search_reward = True
    name = "search"

    def __init__(
        self,
        task_reward: ExpectedSaturatingReward,
        reward: ExpectedSaturatingReward | AngleDistanceReward | RewardMixture,
    ) -> None:
        self.task_reward = task_reward
        self.reward = reward

    @property
    def state_dim(self) -> int:
        """D, the state dimension."""
        return self.reward.state_dim

    def __call__(self, x: Tensor) -> Tensor:
        """r(x) `...` of states ``x`` `... x D`."""
        return self.reward(x)

    def expected(self, state: Gaussian, engine: Engine = DEFAULT_ENGINE) -> Tensor:
        """E[r(x)] `...` under the Gaussian ``state`` (the composed reward's)."""
        return self.reward.expected(state, engine)


def check_search_settings(reward_width_scale: float, reward_task_weight: float, search_cost: str) -> None:
    """The search reward's settings, checked before any work: a UserError naming what to fix."""
    if not reward_width_scale > 0:
        raise UserError(f"propagation.reward_width_scale must be > 0 (1: the task's reward), got {reward_width_scale}")
    if not 0.0 <= reward_task_weight <= 1.0:
        raise UserError(
            f"propagation.reward_task_weight must be in [0, 1] (the task's reward's share of the search reward), "
            f"got {reward_task_weight}"
        )
    if search_cost not in SEARCH_COSTS:
        raise UserError(f"propagation.search_cost must be one of {', '.join(SEARCH_COSTS)}, got {search_cost!r}")


def is_shaped(width_scale: float, task_weight: float, has_cost: bool) -> bool:
    """Whether a search scores other than the task's own reward (else :func:`search_reward` is the task's reward)."""
    return not (task_weight == 1.0 or (not has_cost and width_scale == 1.0))


def search_reward(
    reward: ExpectedSaturatingReward,
    width_scale: float = 1.0,
    task_weight: float = 0.0,
    cost: AngleDistanceReward | None = None,
) -> ExpectedSaturatingReward | SearchReward:
    """The reward a particle search scores: (1 − w) × base + w × the task's reward; the task's own where that is all.

    The base is ``cost`` (the task's declared search cost) when given, else the task's reward widened
    by ``width_scale``.
    """
    if not is_shaped(width_scale, task_weight, cost is not None):
        return reward
    base = cost if cost is not None else reward.widened(width_scale)
    return SearchReward(reward, base if task_weight == 0.0 else RewardMixture([base, reward],
                                                                              [1.0 - task_weight, task_weight]))


def objective_reward(
    reward: ExpectedSaturatingReward,
    *,
    reward_width_scale: float = 1.0,
    reward_task_weight: float = 0.0,
    search_cost: str = "widened",
    task_search_cost: AngleDistanceReward | None = None,
) -> ExpectedSaturatingReward | SearchReward:
    """The search reward of the ``propagation`` settings: the task's ``reward`` shaped (see :func:`search_reward`)."""
    check_search_settings(reward_width_scale, reward_task_weight, search_cost)
    if search_cost == "task" and task_search_cost is None:
        raise UserError("propagation.search_cost=task, but the task declares no search_reward: add "
                        "task.search_reward or set propagation.search_cost=widened (or auto)")
    cost = None if search_cost == "widened" else task_search_cost
    return search_reward(reward, reward_width_scale, reward_task_weight, cost)
