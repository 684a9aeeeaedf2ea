"""The Ray and SLURM launcher presets, end to end: a 2-seed tiny sweep through each gives the joblib sweep's curves.

``hydra/launcher=ray`` runs against a Ray head that the test starts on 127.0.0.1 (``ray start --head``, the
address in ``RAY_ADDRESS``, as on a cluster); ``hydra/launcher=slurm_local`` is the slurm preset's twin that
runs without SLURM (submitit's local executor, the same job settings); the slurm preset itself is checked up to
the sbatch file it submits. Same seed, one torch thread per run: the same ``metrics.csv``, byte for byte,
whatever launcher ran it. Skipped where the launcher's extra is not installed (``pip install 'qtl[ray]'``,
``pip install 'qtl[slurm]'``).
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
import yaml

from tests.helpers import CLI_TINY

ROOT = Path(__file__).resolve().parents[1]
LAUNCHERS = ROOT / "configs" / "hydra" / "launcher"
BIN = Path(sys.executable).parent
SEEDS = (0, 1)
SWEEP_TIMEOUT_S = 240  # a tiny 2-seed sweep takes ~15-25 s on 2 cores
HEAD_TIMEOUT_S = 120   # `ray start --head` takes ~5-20 s
NO_RAY = "the Ray launcher is not installed: pip install 'qtl[ray]' (hydra-ray-launcher)"
NO_SUBMITIT = "the SLURM launcher is not installed: pip install 'qtl[slurm]' (hydra-submitit-launcher)"


def qtl_train() -> str:
    exe = shutil.which("qtl-train", path=str(BIN))
    assert exe is not None, "the console script qtl-train is not installed"
    return exe


def sweep(launcher: str, sweep_dir: Path, *args: str, env: dict[str, str] | None = None,
          check: bool = True) -> subprocess.CompletedProcess:
    """``qtl-train -m hydra/launcher=<launcher> seed=0,1`` on the tiny budget, runs in ``sweep_dir/seed_<k>``."""
    environ = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"} | (env or {})
    done = subprocess.run(
        [qtl_train(), "-m", f"hydra/launcher={launcher}", f"seed={','.join(map(str, SEEDS))}", *CLI_TINY,
         f"hydra.sweep.dir={sweep_dir}", "hydra.sweep.subdir=seed_${seed}", *args],
        cwd=sweep_dir.parent, capture_output=True, text=True, timeout=SWEEP_TIMEOUT_S, env=environ)
    if check:
        assert done.returncode == 0, f"hydra/launcher={launcher}:\n{done.stdout[-3000:]}\n{done.stderr[-5000:]}"
    return done


def curves(sweep_dir: Path) -> dict[int, bytes]:
    return {seed: (sweep_dir / f"seed_{seed}" / "metrics.csv").read_bytes() for seed in SEEDS}


@pytest.fixture(scope="module")
def joblib_curves(tmp_path_factory) -> dict[int, bytes]:
    """The reference: the same sweep on the joblib preset (``hydra/launcher=local``, installed with qtl)."""
    sweep_dir = tmp_path_factory.mktemp("joblib") / "sweep"
    sweep("local", sweep_dir)
    found = curves(sweep_dir)
    assert all(len(rows.splitlines()) == 1 + 2 for rows in found.values())  # header + 2 episodes
    assert found[0] != found[1]  # the seeds differ: equality below means something
    return found


# --- Ray ---------------------------------------------------------------------------------------------------


def free_ports(count: int) -> list[int]:
    """``count`` distinct ports free on 127.0.0.1 now."""
    sockets = [socket.socket() for _ in range(count)]
    try:
        for s in sockets:
            s.bind(("127.0.0.1", 0))
        return [s.getsockname()[1] for s in sockets]
    finally:
        for s in sockets:
            s.close()


def processes() -> dict[int, tuple[int, int]]:
    """Every live process on this machine: pid -> (parent pid, process group), from /proc (zombies left out)."""
    found = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:  # ended meanwhile
            continue
        if fields[0] != "Z":
            found[int(stat.parent.name)] = (int(fields[1]), int(fields[2]))
    return found


def started_by(pgid: int) -> set[int]:
    """Live processes of process group ``pgid`` and all their descendants (Ray's workers have their own groups)."""
    table = processes()
    found = {pid for pid, (_, group) in table.items() if group == pgid}
    while more := {pid for pid, (parent, _) in table.items() if parent in found} - found:
        found |= more
    return found


def end_processes(pgid: int, timeout_s: float = 30.0) -> set[int]:
    """SIGKILL ``started_by(pgid)`` (the test's Ray head: it holds nothing to save); those still alive after."""
    left = started_by(pgid)
    deadline = time.monotonic() + timeout_s
    while left and time.monotonic() < deadline:
        for pid in left:
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        time.sleep(0.2)
        left = started_by(pgid) | (left & set(processes()))
    return left


@dataclass(frozen=True)
class RayHead:
    address: str  # host:port of its GCS, what RAY_ADDRESS names
    temp_dir: Path  # its sessions' files: logs/worker-*.out holds what its tasks printed


@pytest.fixture(scope="module")
def ray_head() -> Iterator[RayHead]:
    """A one-node Ray cluster on 127.0.0.1 (2 CPUs), as ``ray start --head`` makes one.

    ``ray start`` runs in a process group of its own; the teardown kills that group and every process it started
    (by their ids: no other Ray on this machine is touched). Its session files live in a temporary directory
    of its own, so that it meets no other Ray on this machine either.
    """
    pytest.importorskip("hydra_plugins.hydra_ray_launcher", reason=NO_RAY)
    ray = shutil.which("ray", path=str(BIN))
    assert ray is not None, "hydra-ray-launcher is installed but the `ray` command is not"
    temp = Path(tempfile.mkdtemp(prefix="qtl-ray-"))  # short: Ray's socket paths under it have at most 107 characters
    gcs, client, agent = free_ports(3)
    log = temp / "head.log"
    env = {k: v for k, v in os.environ.items() if k != "RAY_ADDRESS"} | {"RAY_USAGE_STATS_ENABLED": "0"}
    with open(log, "wb") as out:  # a file, not a pipe: the head's processes outlive `ray start` and keep it open
        head = subprocess.Popen(
            [ray, "start", "--head", "--node-ip-address=127.0.0.1", f"--port={gcs}",
             f"--ray-client-server-port={client}", f"--dashboard-agent-listen-port={agent}", "--num-cpus=2",
             "--include-dashboard=false", "--disable-usage-stats", "--object-store-memory=100000000",
             f"--temp-dir={temp}"],
            cwd=temp, stdin=subprocess.DEVNULL, stdout=out, stderr=subprocess.STDOUT, env=env,
            start_new_session=True)  # its own process group, which ends it below
    try:
        try:
            returncode = head.wait(timeout=HEAD_TIMEOUT_S)  # `ray start` returns once the cluster is up
        except subprocess.TimeoutExpired:
            pytest.fail(f"`ray start --head` did not return in {HEAD_TIMEOUT_S} s:\n{log.read_text()[-3000:]}")
        assert returncode == 0, f"`ray start --head` failed:\n{log.read_text()[-3000:]}"
        yield RayHead(f"127.0.0.1:{gcs}", temp)
    finally:
        left = end_processes(head.pid)
        if head.poll() is None:
            head.wait(timeout=30)
        shutil.rmtree(temp, ignore_errors=True)
        assert not left, f"the test's Ray head left processes behind: {left}"


@pytest.mark.e2e  # the real CLI in subprocesses: -m 'not e2e' skips it
def test_ray_preset_runs_the_sweep_on_a_ray_cluster_with_the_joblib_curves(ray_head, joblib_curves, tmp_path):
    sweep_dir = tmp_path / "sweep"
    sweep("ray", sweep_dir, env={"RAY_ADDRESS": ray_head.address})  # the preset's `address: auto` reads it
    printed = "".join(p.read_text() for p in ray_head.temp_dir.glob("session_*/logs/worker-*.out"))
    for seed in SEEDS:  # the runs were the head's tasks (`address: auto` never starts a cluster of its own)
        assert str(sweep_dir / f"seed_{seed}") in printed  # the summary line each run prints names its directory
    launcher = yaml.safe_load((sweep_dir / "multirun.yaml").read_text())["hydra"]["launcher"]
    assert launcher["_target_"].endswith("RayLauncher") and launcher["ray"]["remote"] == {"num_cpus": 1}
    assert curves(sweep_dir) == joblib_curves
    for seed in SEEDS:
        assert yaml.safe_load((sweep_dir / f"seed_{seed}" / ".hydra" / "overrides.yaml").read_text())[0] == \
            f"seed={seed}"


# --- SLURM -------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def submitit() -> None:
    """Skips where hydra-submitit-launcher is not installed (before any sweep runs)."""
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher", reason=NO_SUBMITIT)


@pytest.mark.e2e  # the real CLI in subprocesses: -m 'not e2e' skips it
def test_slurm_local_preset_runs_the_sweep_through_submitit_with_the_joblib_curves(submitit, joblib_curves, tmp_path):
    sweep_dir = tmp_path / "sweep"
    sweep("slurm_local", sweep_dir)
    launcher = yaml.safe_load((sweep_dir / "multirun.yaml").read_text())["hydra"]["launcher"]
    assert launcher["_target_"].endswith("submitit_launcher.LocalLauncher")
    assert curves(sweep_dir) == joblib_curves
    jobs = [p for p in (sweep_dir / ".submitit").iterdir() if p.is_dir() and any(p.glob("*_result.pkl"))]
    assert len(jobs) == len(SEEDS)  # one submitit job per run, each with its result


@pytest.mark.e2e  # the real CLI in subprocesses: -m 'not e2e' skips it
def test_slurm_preset_submits_one_array_job_with_its_settings(submitit, tmp_path):
    """Up to ``sbatch``: stand-ins for ``srun`` and ``sbatch`` keep the submission file and refuse the job."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    kept = tmp_path / "submitted.sh"
    stand_ins = {"srun": "exit 1", "sbatch": f'cp "$1" "{kept}"\necho "sbatch: no SLURM here" >&2\nexit 1'}
    for name, body in stand_ins.items():
        (bin_dir / name).write_text(f"#!/bin/sh\n{body}\n")
        (bin_dir / name).chmod(0o755)
    sweep_dir = tmp_path / "sweep"
    done = sweep("slurm", sweep_dir, "hydra.launcher.partition=debug", check=False,
                 env={"PATH": f"{bin_dir}{os.pathsep}{os.environ.get('PATH', '')}"})
    assert done.returncode != 0 and "sbatch: no SLURM here" in done.stderr, done.stderr[-3000:]
    directives = {line.split()[1] for line in kept.read_text().splitlines() if line.startswith("#SBATCH ")}
    assert {"--array=0-1%2", "--partition=debug", "--cpus-per-task=1", "--ntasks-per-node=1", "--nodes=1",
            "--mem=4GB", "--time=720", f"--output={sweep_dir}/.submitit/%A_%a/%A_%a_0_log.out"} <= directives
    assert f"-m submitit.core._submit {sweep_dir}/.submitit/%j" in kept.read_text()


def test_slurm_local_preset_mirrors_the_slurm_preset():
    """The twin that CI runs has the job settings of the preset that goes to a cluster (less what SLURM alone has)."""
    slurm = yaml.safe_load((LAUNCHERS / "slurm.yaml").read_text())
    twin = yaml.safe_load((LAUNCHERS / "slurm_local.yaml").read_text())
    assert (slurm.pop("defaults"), twin.pop("defaults")) == (["submitit_slurm"], ["submitit_local"])
    assert twin == {k: v for k, v in slurm.items() if k not in ("array_parallelism", "partition", "account")}
