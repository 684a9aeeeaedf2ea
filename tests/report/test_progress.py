"""Where a sweep stands: what each planned run has made (fake run directories)."""

from __future__ import annotations

from pathlib import Path

from qtl.recorder import TIMINGS_FILE
from qtl.report.progress import PlannedRun, progress_markdown, sweep_progress


def _fake_run(run_dir: Path, episodes: int, seconds: list[float]) -> None:
    (run_dir / "checkpoints").mkdir(parents=True)
    for episode in range(episodes):
        (run_dir / "checkpoints" / f"episode_{episode:04d}.pt").write_bytes(b"")
    rows = ["episode,model_fit_s,policy_search_s,episode_s", *(f"{i},1,2,{s}" for i, s in enumerate(seconds))]
    (run_dir / TIMINGS_FILE).write_text("\n".join(rows) + "\n")


def test_progress_counts_checkpointed_episodes_and_their_recorded_time(tmp_path):
    plan = [PlannedRun(tmp_path / f"seed_{s}", (f"seed={s}",), episodes=3) for s in range(3)]
    _fake_run(plan[0].run_dir, 3, [3600.0, 1800.0, 1800.0])
    _fake_run(plan[1].run_dir, 1, [900.0, 50.0])  # a second episode recorded but not yet checkpointed
    progress = sweep_progress(plan)
    assert [p.done for p in progress] == [3, 1, 0]
    assert [p.finished for p in progress] == [True, False, False]
    assert [p.seconds for p in progress] == [7200.0, 900.0, 0.0]
    text = progress_markdown({"targets": progress}, tmp_path)
    assert "1 of 3 runs finished, 1 begun, 1 not begun; 4 of 9 episodes made (2.2 h recorded)" in text
    assert "| seed_1 | 1 / 3" in text and "not begun" in text
