"""The hanging-start Pendulum-v1 of the pendulum example: only its reset differs from gymnasium's."""

from __future__ import annotations

import math

import gymnasium
import numpy as np
import pytest
from gymnasium.envs.classic_control.pendulum import PendulumEnv

from qtl.envs.pendulum_hanging import ANGLE_SPREAD, SPEED_SPREAD, HangingStart

ENV_ID = "qtl.envs.pendulum_hanging:PendulumHanging-v1"


def test_the_reset_hangs_the_pendulum_and_is_seeded():
    env = gymnasium.make(ENV_ID)
    obs, _ = env.reset(seed=3)
    theta, speed = env.unwrapped.state
    assert abs(theta - math.pi) <= ANGLE_SPREAD and abs(speed) <= SPEED_SPREAD
    np.testing.assert_allclose(obs, [math.cos(theta), math.sin(theta), speed], rtol=1e-6)
    again, _ = gymnasium.make(ENV_ID).reset(seed=3)
    np.testing.assert_array_equal(obs, again)
    assert not np.array_equal(obs, env.reset(seed=4)[0])
    assert env.spec.max_episode_steps == 200 and env.action_space == PendulumEnv().action_space


def test_it_steps_as_pendulum_v1_from_the_same_state():
    hanging, plain = gymnasium.make(ENV_ID), gymnasium.make("Pendulum-v1")
    hanging.reset(seed=0)
    plain.reset(seed=0)
    plain.unwrapped.state = hanging.unwrapped.state.copy()
    for u in (1.5, -2.0, 0.3):
        a, b = hanging.step(np.array([u], dtype=np.float32)), plain.step(np.array([u], dtype=np.float32))
        np.testing.assert_array_equal(a[0], b[0])
        assert a[1:4] == b[1:4]


def test_it_wraps_only_a_pendulum():
    with pytest.raises(ValueError, match="wraps gymnasium's PendulumEnv"):
        HangingStart(gymnasium.make("MountainCarContinuous-v0"))
    with pytest.raises(ValueError, match="spreads must be >= 0"):
        HangingStart(PendulumEnv(), angle_spread=-0.1)
