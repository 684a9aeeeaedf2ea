"""The reliability table: health.csv counts summed over every run of an experiment, unfinished runs named."""

from __future__ import annotations

import json

import yaml

from qtl.health import EVENTS, GP_FIT_FAILED, JITTER, NONFINITE, SEARCH_STOPPED
from qtl.recorder import HEALTH_COLUMNS, HEALTH_FILE
from qtl.report import discover, write_report
from qtl.report.reliability import reliability, reliability_markdown
from tests.report.fakes import make_experiment, table_rows

RUNS = {"pilco": {"m2.0": {0: ([0, 10, 20], None), 1: ([0, 10, 30], None)}},
        "qtl_bayesian": {"m2.0": {0: ([10, 20, 30], None)}}}


def write_health(run_dir, rows: list[dict[str, int]]) -> None:
    lines = [",".join(HEALTH_COLUMNS)]
    for episode, counts in enumerate(rows):
        full = {"episode": episode, "resumed": 0, **dict.fromkeys(EVENTS, 0), **counts}
        lines.append(",".join(str(full[c]) for c in HEALTH_COLUMNS))
    (run_dir / HEALTH_FILE).write_text("\n".join(lines) + "\n")


def make(tmp_path):
    root = make_experiment(tmp_path, RUNS, sources=1)
    write_health(root / "source" / "seed_0", [{}, {JITTER: 4}, {}, {GP_FIT_FAILED: 1}])
    pilco = root / "target" / "pilco" / "m2.0"
    write_health(pilco / "seed_0", [{}, {NONFINITE: 2, SEARCH_STOPPED: 1}, {"resumed": 1}])
    # seed 1: made before health.csv: no record; asked for 5 episodes, has 3 (unfinished)
    (pilco / "seed_1" / ".hydra" / "config.yaml").write_text(yaml.safe_dump({"random_episodes": 1, "episodes": 4}))
    write_health(root / "target" / "qtl_bayesian" / "m2.0" / "seed_0", [{}, {JITTER: 1, "resumed": 1}, {}])
    return root


def test_counts_are_summed_per_part(tmp_path):
    parts = reliability(discover(make(tmp_path)))
    source, target, both = parts["source"], parts["target"], parts["all"]
    assert (source.runs, source.episodes, source.recorded) == (1, 4, 4)
    assert (target.runs, target.episodes, target.recorded) == (3, 9, 6)  # pilco seed 1 has no health.csv
    assert source.events[JITTER] == 4 and source.events[GP_FIT_FAILED] == 1
    assert target.events == {**dict.fromkeys(EVENTS, 0), NONFINITE: 2, SEARCH_STOPPED: 1, JITTER: 1}
    assert (target.resumed, target.resumed_runs) == (2, 2)
    assert target.unfinished == ["pilco/m2.0/seed_1 (3 of 5)"] and both.unfinished == target.unfinished
    assert both.events[JITTER] == 5 and both.runs == 4


def test_the_report_has_the_table_and_the_json(tmp_path):
    root = make(tmp_path)
    rows = table_rows(reliability_markdown(discover(root)))
    assert ("Cholesky factorisations retried with jitter", "4", "1", "5") in rows
    assert ("episodes (with a health record)", "4 (4)", "9 (6)", "13 (10)") in rows
    report = write_report(root)
    text = report.read_text()
    assert "## Reliability" in text and "Unfinished: pilco/m2.0/seed_1 (3 of 5)." in text
    stored = json.loads((report.parent / "tables.json").read_text())["reliability"]
    assert stored["all"]["search_runs_stopped"] == 1 and stored["target"]["resumed_sessions"] == 2
