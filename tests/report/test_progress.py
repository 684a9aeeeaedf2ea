"""Where a sweep stands: what each planned run has made (fake run directories)."""

from __future__ import annotations

from pathlib import Path

from qtl.recorder import METRICS_FILE, TIMINGS_FILE
from qtl.report.progress import PlannedRun, progress_markdown, remaining_hours, sweep_progress


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
    # To go, at the finished run's 3600, 1800, 1800 s: seed_1's episodes 1-2 (3600 s) and seed_2's 0-2 (7200 s): 3.0 h.
    assert remaining_hours(progress) == 3.0
    assert ("1 of 3 runs finished, 1 begun, 1 not begun; 4 of 9 episodes made (2.2 h recorded; ~3.0 h of one core "
            "to go at the finished runs' time per episode)") in text
    assert "| seed_1 | 1 / 3" in text and "not begun" in text


def test_the_time_to_go_averages_each_episode_over_the_finished_runs_and_needs_one(tmp_path):
    plan = [PlannedRun(tmp_path / f"seed_{s}", (f"seed={s}",), episodes=2) for s in range(4)]
    _fake_run(plan[0].run_dir, 1, [100.0])  # begun only: no pace before a run has finished
    assert remaining_hours(sweep_progress(plan)) is None
    assert "h of one core to go" not in progress_markdown({"targets": sweep_progress(plan)})
    _fake_run(plan[1].run_dir, 2, [1000.0, 3000.0])
    _fake_run(plan[2].run_dir, 2, [2600.0, 4200.0])  # episode means 1800 and 3600 s
    # seed_0 needs episode 1 (3600 s), seed_3 both (5400 s): 9000 s.
    assert remaining_hours(sweep_progress(plan)) == 2.5
    _fake_run(plan[3].run_dir, 2, [1.0, 1.0])
    done = sweep_progress(plan[1:])
    assert remaining_hours(done) == 0.0 and "to go" not in progress_markdown({"targets": done})


def test_a_run_kept_without_its_checkpoints_counts_its_metrics_rows(tmp_path):
    # A finished sweep in git keeps each run's CSVs and config, not its checkpoints (docs/experiments/README.md).
    plan = [PlannedRun(tmp_path / f"seed_{s}", (f"seed={s}",), episodes=3) for s in range(2)]
    plan[0].run_dir.mkdir()
    (plan[0].run_dir / METRICS_FILE).write_text("episode,return\n0,1.0\n1,2.0\n2,3.0\n")
    (plan[0].run_dir / TIMINGS_FILE).write_text("episode,episode_s\n0,10\n1,20\n2,30\n")
    _fake_run(plan[1].run_dir, 1, [5.0, 6.0])  # checkpoints where present say what a resume continues from
    (plan[1].run_dir / METRICS_FILE).write_text("episode,return\n0,1.0\n1,2.0\n")
    progress = sweep_progress(plan)
    assert [(p.done, p.finished, p.seconds) for p in progress] == [(3, True, 60.0), (1, False, 5.0)]
