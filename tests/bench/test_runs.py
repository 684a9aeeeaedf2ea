"""The benchmarks' run helpers (qtl.bench.runs)."""

from __future__ import annotations

from qtl.bench.runs import initial_episodes


def test_a_run_counts_its_initial_episodes_from_the_overrides() -> None:
    assert initial_episodes([]) == 1 == initial_episodes(["task=cartpole_track"])
    assert initial_episodes(["random_episodes=3"]) == 3
    assert initial_episodes(["random_episodes=3", "seed=1", "random_episodes=2"]) == 2  # Hydra: the last one wins
