"""The native kernels on first use: compiled once into the per-user cache, else the torch path in one log line."""

from __future__ import annotations

import logging
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from qtl.errors import UserError
from qtl.kernels import engine as engine_module
from qtl.kernels.engine import Engine
from qtl.kernels.native import artefact, first_use
from qtl.kernels.native import build as native_build
from qtl.kernels.native.exp_sum import ExpSumLibrary
from qtl.kernels.native.loader import load_binding

# One process of the race: import qtl, say it is ready, wait for the other, then load the kernels (compiling them).
RACER = """
import logging, sys, time
from pathlib import Path
logging.basicConfig(level=logging.INFO, format="%(name)s: %(message)s")
from qtl.kernels.native.exp_sum import load_exp_sum
from qtl.kernels.native.first_use import library_path
here = Path(sys.argv[1])
(here / f"ready-{sys.argv[2]}").touch()
deadline = time.monotonic() + 60
while len(list(here.glob("ready-*"))) < 2 and time.monotonic() < deadline:
    time.sleep(0.01)
load_exp_sum()
print(library_path())
"""
COMPILED = "compiled the native kernels into"


@pytest.fixture(scope="module")
def raced(tmp_path_factory) -> tuple[Path, list[subprocess.CompletedProcess]]:
    """A fresh cache, and two processes that started loading the kernels from it at the same moment."""
    if shutil.which(artefact.compiler()[0]) is None:
        pytest.skip(f"no C compiler ({artefact.compiler()[0]})")
    cache, meeting = tmp_path_factory.mktemp("cache"), tmp_path_factory.mktemp("meeting")
    env = {**os.environ, "QTL_CACHE_DIR": str(cache)}
    racers = [
        subprocess.Popen(
            [sys.executable, "-c", RACER, str(meeting), str(i)],
            env=env,
            text=True,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
        )
        for i in range(2)
    ]
    done = []
    for racer in racers:
        out, err = racer.communicate(timeout=300)
        done.append(subprocess.CompletedProcess(racer.args, racer.returncode, out, err))
    return cache, done


def test_two_processes_at_once_compile_once_and_both_load(raced):
    cache, done = raced
    assert [d.returncode for d in done] == [0, 0], [d.stderr for d in done]
    paths = {Path(d.stdout.strip()) for d in done}
    assert len(paths) == 1 and next(iter(paths)).parent == cache / "native" and next(iter(paths)).is_file()
    assert sum(d.stderr.count(COMPILED) for d in done) == 1
    assert not list((cache / "native").glob("*.tmp")) and not list((cache / "native").glob("*.unchecked.so"))


def test_a_built_cache_compiles_nothing_and_where_names_it(raced, monkeypatch, caplog, capsys):
    cache, done = raced
    monkeypatch.setenv("QTL_CACHE_DIR", str(cache))
    with caplog.at_level(logging.DEBUG, logger="qtl"):
        path = first_use.library_path()
        load_binding(ExpSumLibrary)
    assert path == Path(done[0].stdout.strip()) and not caplog.records
    assert native_build.main(["--where"]) == 0
    assert capsys.readouterr().out.strip() == str(path)


def test_a_missing_compiler_takes_the_torch_path_in_one_line(monkeypatch, caplog, capsys, tmp_path):
    monkeypatch.setenv("QTL_CACHE_DIR", str(tmp_path))
    monkeypatch.setenv("CC", str(tmp_path / "no-such-cc"))
    engine_module._log_once.cache_clear()
    with caplog.at_level(logging.INFO, logger="qtl"):
        assert Engine.resolve("auto", "auto") == Engine(exp_sums="torch", moments="fused")
        assert Engine.resolve("auto", "auto") == Engine(exp_sums="torch", moments="fused")  # neither retried nor said
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 1 and "no-such-cc" in lines[0] and "install gcc, or set CC" in lines[0]
    assert "using kernels.moments=fused and kernels.backend=torch" in lines[0]
    with pytest.raises(UserError, match=r"^kernels\.backend=native, but .*install gcc") as refused:
        Engine.resolve("native", "auto")
    assert "\n" not in str(refused.value)
    assert native_build.main(["--where"]) == 1  # not built: the path it would use, and status 1
    assert Path(capsys.readouterr().out.strip()).parent == tmp_path / "native"


def test_an_unwritable_cache_takes_the_torch_path(monkeypatch, caplog, tmp_path):
    blocker = tmp_path / "a-file"
    blocker.write_text("not a directory")
    monkeypatch.setenv("QTL_CACHE_DIR", str(blocker))
    with pytest.raises(ImportError, match="set QTL_CACHE_DIR to a writable directory"):
        first_use.library_path()
    engine_module._log_once.cache_clear()
    with caplog.at_level(logging.INFO, logger="qtl"):
        assert Engine.resolve("auto", "reference") == Engine(exp_sums="torch")
    assert [r.getMessage().count("QTL_CACHE_DIR") for r in caplog.records] == [1]
    assert not artefact.artefact_path().exists()


def test_a_build_clears_what_a_crashed_build_left(monkeypatch, tmp_path):
    """A build killed between compile and check leaves ``*.unchecked.so``; the next lock holder removes it."""
    monkeypatch.setenv("QTL_CACHE_DIR", str(tmp_path))
    target = artefact.artefact_path()
    target.parent.mkdir(parents=True)
    crashed = target.with_name(f"{target.stem}.99999999.unchecked.so")
    crashed.write_bytes(b"half a library")
    assert native_build.build() == target and target.is_file()
    assert not crashed.exists() and not list(target.parent.glob("*.unchecked.so"))
