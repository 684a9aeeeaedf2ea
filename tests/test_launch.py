"""Which overrides make two runs different runs (`qtl.launch.effective`); `ensure_run` itself: test_demo."""

from __future__ import annotations

from qtl.launch import effective


def test_only_overrides_that_change_what_a_run_learns_count():
    made = ["seed=0", "recipe=mc_pilco", "hydra.run.dir=/x", "progress=false", "threads=1", "episodes=9",
            "resume=auto", "keep_checkpoints=2"]
    assert effective(made) == ["recipe=mc_pilco", "seed=0"]
    assert effective(["seed=1", "resume=auto"]) != effective(["seed=0"])
    assert effective(["task.horizon=100"]) != effective([])
    assert effective(["seed=0", "--", "recipe=mc_pilco"]) == effective(["seed=0", "recipe=mc_pilco"])
