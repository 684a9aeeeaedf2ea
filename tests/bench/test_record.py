"""``qtl.bench``: the commit a benchmark names, the shared table cells, its options and runs, its recorded paths."""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
from pathlib import Path

from qtl import bench
from qtl.bench import record


def _repo(tmp_path: Path) -> Path:
    def git(*args: str) -> None:
        subprocess.run(["git", *args], cwd=tmp_path, check=True, capture_output=True)

    git("init", "-q")
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "benchmarks.md").write_text("a\n")
    (tmp_path / "code.py").write_text("a\n")
    git("add", ".")
    git("-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "init")
    return tmp_path


def test_commit_ignores_changed_docs_but_not_changed_code(tmp_path, monkeypatch) -> None:
    root = _repo(tmp_path)
    monkeypatch.setattr(record, "ROOT", root)
    clean = bench.commit()
    assert len(clean) >= 7 and "+" not in clean
    (root / "docs" / "benchmarks.md").write_text("b\n")  # ` M docs/...`: a benchmark writing its table
    assert bench.commit() == clean
    (root / "code.py").write_text("b\n")
    assert bench.commit() == clean + "+changes"


def test_mean_std_and_first_successes() -> None:
    assert bench.mean_std([]) == "—" and bench.mean_std([2.0]) == "2.0"
    assert bench.mean_std([1.0, 3.0], 2) == "2.00 ± 1.41"
    assert bench.first_successes([{"first_success": 3}, {"first_success": None}]) == "3 —"


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser()
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument("--tag", default="")
    return parser


def test_parse_with_overrides_drops_the_separator(monkeypatch) -> None:
    monkeypatch.setattr(sys, "argv", ["bench", "--seeds", "0", "1", "--", "recipe=mc_pilco", "+task.env.dt=0.05"])
    args, overrides = bench.parse_with_overrides(_parser())
    assert args.seeds == [0, 1] and overrides == ["recipe=mc_pilco", "+task.env.dt=0.05"]
    monkeypatch.setattr(sys, "argv", ["bench", "--tag", "x", "recipe=mc_pilco"])
    assert bench.parse_with_overrides(_parser())[1] == ["recipe=mc_pilco"]


def test_parse_with_overrides_refuses_a_mistyped_option(monkeypatch, capsys) -> None:
    monkeypatch.setattr(sys, "argv", ["bench", "--sedes", "3", "recipe=mc_pilco"])
    try:
        bench.parse_with_overrides(_parser())
    except SystemExit as stop:
        assert stop.code == 2
    else:
        raise AssertionError("a mistyped option was taken for an override")
    assert "--sedes" in capsys.readouterr().err


def test_run_all_runs_every_item_when_one_fails() -> None:
    ran: list[int] = []

    def job(item: int) -> int:
        ran.append(item)
        if item == 1:
            raise RuntimeError("run 1 failed")
        return item * 10

    assert bench.run_all(job, [0, 2, 3], jobs=2) == [0, 20, 30]  # in order
    ran.clear()
    try:
        bench.run_all(job, [0, 1, 2, 3, 4], jobs=1)  # one worker: Executor.map would cancel 2, 3 and 4
    except RuntimeError as err:
        assert "1 of 5 runs failed" in str(err) and "run 1 failed" in str(err)
    else:
        raise AssertionError("a failed run was not reported")
    assert sorted(ran) == [0, 1, 2, 3, 4]


def test_each_generated_section_of_the_benchmarks_doc_holds_only_its_own_heading() -> None:
    """A script rewrites everything between its markers: prose hand-written inside them would be lost."""
    text = (Path(__file__).resolve().parents[2] / "docs" / "benchmarks.md").read_text()
    sections = re.findall(r"<!-- (\S+):begin -->\n(.*?)<!-- \1:end -->", text, flags=re.S)
    assert len(sections) == text.count(":begin -->") == text.count(":end -->")
    crowded = [name for name, body in sections if len(re.findall(r"^## ", body, flags=re.M)) > 1]
    assert not crowded, f"sections holding more than their own '## ' heading: {crowded}"


def test_recorded_paths_are_relative_to_the_repository(monkeypatch, tmp_path) -> None:
    """A path inside the repository is recorded relative to it; one outside it by its name only."""
    root = bench.ROOT
    assert bench.display_path(root / "docs" / "bench" / "gp.json") == "docs/bench/gp.json"
    assert bench.display_path(tmp_path / "runs" / "seed_0") == "…/seed_0"  # tmp_path: outside the checkout
    monkeypatch.chdir(root)
    assert bench.display_path(Path("runs") / "x") == "runs/x"
    monkeypatch.setattr(sys, "argv", [
        str(root / "scripts" / "bench_transfer.py"), "--sources", str(root / "runs" / "a"), f"cartpole={root}/runs/b",
        "--output", str(tmp_path / "out.json"), "task.horizon=10", "task.search_reward={angles: absolute}"])
    assert bench.command_line() == ("python scripts/bench_transfer.py --sources runs/a cartpole=runs/b "
                                       "--output …/out.json task.horizon=10 task.search_reward={angles: absolute}")


def test_the_recorded_results_name_no_path_of_the_measuring_machine() -> None:
    docs = Path(__file__).resolve().parents[2] / "docs"
    files = [docs / "benchmarks.md", *sorted((docs / "bench").iterdir())]
    found = [f"{path.relative_to(docs)}: {hit}" for path in files
             for hit in re.findall(r"(?:/work|/tmp|/home|/root|/Users)/[^\s\"`]+", path.read_text())]
    assert not found, found
    assert not (docs / "bench_kernels.json").exists() and (docs / "bench" / "kernels.json").is_file()
