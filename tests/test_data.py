"""TransitionDataset: episodes in, GP pairs out, state round trip, bad episodes named."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from qtl.data import TransitionDataset


def episode(length: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return rng.normal(size=(length + 1, 3)), rng.uniform(-1, 1, size=(length, 1))


def test_pairs_are_state_action_and_difference():
    data = TransitionDataset(3, 1)
    (s0, a0), (s1, a1) = episode(4, 0), episode(6, 1)
    data.add_episode(s0, a0)
    data.add_episode(s1, a1)
    x, u, delta = data.tensors()
    assert len(data) == 10 and data.num_episodes == 2
    assert x.shape == (10, 3) and u.shape == (10, 1) and delta.shape == (10, 3)
    torch.testing.assert_close(x[4], torch.as_tensor(s1[0]))  # no pair straddles two episodes
    torch.testing.assert_close(delta[4], torch.as_tensor(s1[1] - s1[0]))
    torch.testing.assert_close(u[:4], torch.as_tensor(a0))


def test_state_round_trip():
    data = TransitionDataset(3, 1)
    data.add_episode(*episode(5, 2))
    again = TransitionDataset.from_state(data.state())
    for a, b in zip(data.tensors(), again.tensors(), strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)


@pytest.mark.parametrize(
    ("states", "actions", "message"),
    [
        (np.zeros((5, 2)), np.zeros((4, 1)), "states must be `T\\+1 x 3`"),
        (np.zeros((5, 3)), np.zeros((4, 2)), "actions must be `T x 1`"),
        (np.zeros((5, 3)), np.zeros((5, 1)), "needs 6 states, got 5"),
        (np.full((5, 3), np.nan), np.zeros((4, 1)), "states contain non-finite"),
        (np.zeros((1, 3)), np.zeros((0, 1)), "at least one transition"),
    ],
)
def test_bad_episodes_are_named(states, actions, message):
    with pytest.raises(ValueError, match=message):
        TransitionDataset(3, 1).add_episode(states, actions)


def test_empty_dataset_and_malformed_state():
    with pytest.raises(ValueError, match="holds no episodes"):
        TransitionDataset(3, 1).tensors()
    with pytest.raises(ValueError, match="malformed TransitionDataset state"):
        TransitionDataset.from_state({"state_dim": 3})
