"""RunState: a checkpoint's dict read back equals the state saved, and a run resumes from it."""

from __future__ import annotations

import torch

from qtl.build import build, transfer_plan
from qtl.checkpoint import latest_checkpoint, load_checkpoint, rng_state
from qtl.loop import run
from qtl.run_state import RunState
from tests.helpers import tiny_config


def assert_same_checkpoint(a: object, b: object) -> None:
    """Two checkpoint dicts (nested dicts, lists, tensors, primitives) equal exactly."""
    assert type(a) is type(b)
    if isinstance(a, dict):
        assert list(a) == list(b)
        for key in a:
            assert_same_checkpoint(a[key], b[key])
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b)
        for x, y in zip(a, b, strict=True):
            assert_same_checkpoint(x, y)
    elif isinstance(a, torch.Tensor):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    else:
        assert a == b or (a != a and b != b)  # NaN (an initial episode's predicted return) equals itself here


def test_a_checkpoint_loads_into_the_state_that_saves_it_again(tmp_path):
    cfg = tiny_config("episodes=1")
    run(cfg, tmp_path)
    saved = load_checkpoint(latest_checkpoint(tmp_path))
    parts = build(cfg)
    state = RunState.load(saved, parts, transfer_plan(cfg, parts))
    assert state.episodes == state.resumed_at == 2 and len(state.records.rows) == 2 and state.theta is not None
    assert_same_checkpoint(rng_state(), saved["rng"])  # the global RNG streams restored
    again = state.save(tmp_path / "again", cfg)
    assert again.name == "episode_0001.pt"
    assert_same_checkpoint(load_checkpoint(again), saved)


def test_a_fresh_state_holds_lines_1_and_2_only(tmp_path):
    cfg = tiny_config("episodes=1")
    parts = build(cfg)
    state = RunState.fresh(parts, transfer_plan(cfg, parts))
    assert state.episodes == 0 and state.resumed_at is None and len(state.data) == 0
    assert state.theta is None and state.previous is None and state.records.rows == []
    initial = parts.initial_policy().state_dict()  # PILCO's ψ_0 (no transfer)
    for name, value in state.policy.state_dict().items():
        torch.testing.assert_close(value, initial[name], rtol=0, atol=0)


def test_a_run_resumes_from_a_saved_state_as_from_its_own_checkpoint(tmp_path):
    cfg = tiny_config("episodes=1")
    run(tiny_config("episodes=2"), tmp_path / "whole")
    run(cfg, tmp_path / "split")
    parts = build(cfg)
    state = RunState.load(load_checkpoint(latest_checkpoint(tmp_path / "split")), parts, transfer_plan(cfg, parts))
    copy = tmp_path / "copy"
    state.save(copy, cfg)  # the state alone (no CSV, no events): resume rebuilds the records from it
    run(tiny_config("episodes=2"), copy, resume=True)
    assert (copy / "metrics.csv").read_text() == (tmp_path / "whole" / "metrics.csv").read_text()
