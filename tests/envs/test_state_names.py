"""Every env of the repository names its state dimensions (axis labels, tables)."""

from __future__ import annotations

import gymnasium
import pytest

from qtl import envs


@pytest.mark.parametrize("env_id", sorted(envs.ENV_IDS))
def test_state_names_match_the_observation(env_id):
    with gymnasium.make(env_id) as env:
        names = type(env.unwrapped).state_names
        assert len(names) == env.observation_space.shape[0]
        assert len(set(names)) == len(names) and all(isinstance(n, str) and n for n in names)
