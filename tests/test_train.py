"""The CLI's resume helpers: which keys a resumed run may change."""

from __future__ import annotations

import pytest

from qtl.errors import CheckpointError
from qtl.loop import run
from qtl.train import resume_config
from tests.helpers import tiny_config


def test_resume_may_change_how_a_run_runs_but_not_what_it_learns(tmp_path):
    run(tiny_config("episodes=0"), tmp_path)
    cfg = resume_config(tmp_path, [f"resume={tmp_path}", "episodes=3", "threads=2", "device=cuda:0"])
    assert (cfg.episodes, cfg.threads, cfg.device, cfg.resume) == (3, 2, "cuda:0", str(tmp_path))
    with pytest.raises(CheckpointError, match="cannot change 'seed'"):
        resume_config(tmp_path, ["seed=4"])
