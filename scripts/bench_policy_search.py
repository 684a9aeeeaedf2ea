"""Benchmark one full policy search and one rollout + gradient, moment matching and particles, on cart-pole data.

Data: real transitions of the configured cart-pole (``qtl/CartPoleSwingUp-v0``, 0.5 kg, the defaults
of ``configs/task/cartpole.yaml``), episodes of uniform random actions alternating with episodes of a
random RBF policy, cut at n tuples, seeded. GP inputs are built as the loop builds them
(``qtl.data.gp_training_pairs``); one exact ``DynamicsGP`` per n is fitted once in float64 with
``fit(restarts=1)`` (a benchmark model; the loop uses ``model.restarts``) and cached under
``--cache-dir``. Each (propagator, n, dtype) then runs in a fresh subprocess, so that its peak
resident memory is its own: the default ``train`` config composed with the propagator's overrides,
propagator, optimiser, initial policy, start distribution, horizon and reward made by ``qtl.build.build``,
as the loop makes them, and the model loaded in the run's dtype. Measured: the median of
``--repeats`` rollouts + gradients (``expected_return(...).backward()``) after one warm-up, and one
policy search timed as the loop times it (propagator construction + search). ``--device cuda``: model,
policy and propagation on the GPU (the targets are judged on the CPU only). Writes JSON (default
``docs/bench/policy_search[-cuda].json``) and, unless ``--no-docs``, its section of ``docs/benchmarks.md``.

In the same run (issue 18), the moment-matching search at each ``--compare-sizes`` n (default 250, float64)
under the ``COMPARE_VARIANTS`` of ``kernels.backend`` {torch, native}, ``optimizer.batched`` {false, true}
(restarts one after the other, or in lockstep in one batched rollout) and ``kernels.moments`` {reference,
fused, native}: the same data, model and ψ_0, each in its own subprocess; absolute times, ratios against
torch + sequential + reference (today's defaults), and the predicted returns found.
``--no-compare`` skips it.

``--compare integration`` (issue 63) runs instead full-state against kinematic moment matching
(``propagation.integration=delta|speed``, :mod:`qtl.bench.kinematic`): the loop's search at each ``--compare-sizes``
n on the cart-pole, each row in its own subprocess, and one batched round of the aircraft stage with
``--aircraft-inducing`` m (0: none), both steps on one fitted model; its own JSON and section (*_integration).

    .venv/bin/python scripts/bench_policy_search.py [--sizes 250 500 1000] [--dtypes float64 float32]
        [--propagators moment_matching particles] [--threads 2] [--device cpu] [--repeats 3]
        [--skip-search | --search-at-targets] [--compare-sizes 250 | --no-compare | --compare-only]
        [--compare integration [--aircraft-inducing 300] [--aircraft-overrides OVERRIDE ...]]
        [--variants native/batched/native ...]
        [--overrides OVERRIDE ...] [--mm-overrides OVERRIDE ...] [--particles-overrides OVERRIDE ...]
        [--output PATH] [--no-docs] [--cache-dir DIR]
"""

from __future__ import annotations

import argparse
import functools
import json
import logging
import statistics
import subprocess
import sys
import time
import traceback
import warnings
from pathlib import Path
from typing import Any

import torch
from omegaconf import OmegaConf

from qtl.bench import (
    ROOT,
    command_line,
    commit,
    display_path,
    kinematic,
    machine,
    markdown_table,
    peak_rss_mib,
    today,
    write_results,
    write_section,
)
from qtl.bench.search import (
    CACHE_DIR,
    MODEL_FIT_RESTARTS,
    PROPAGATORS,
    SEARCH_EPISODE,
    batched_rollout_grad,
    compose_config,
    ensure_model,
    rollout_and_gradient,
)
from qtl.build import DTYPES, build, resolve_device
from qtl.models import DynamicsGP
from qtl.seeding import SEARCH_STREAM, seed_everything, torch_generator

SIZES = [250, 500, 1000]
COMPARE_SIZES = [250]
# The comparison of issue 18, moment matching, float64: (exp-sum backend, restarts batched, moment formulation).
COMPARE_VARIANTS = [
    ("torch", False, "reference"),  # the reference path (the defaults before issue 18): the ratios' baseline
    ("torch", True, "reference"),
    ("native", False, "reference"),
    ("native", True, "reference"),
    ("torch", False, "fused"),
    ("native", False, "fused"),
    ("native", True, "fused"),
    ("native", False, "native"),
    ("native", True, "native"),  # every speed switch on
]
RESTART_MODES = {False: "sequential", True: "batched"}
BASELINE_VARIANT = COMPARE_VARIANTS[0]


def variant_name(variant: tuple[str, bool, str]) -> str:
    """'backend/restarts/moments' of a comparison variant, e.g. 'native/batched/fused'."""
    backend, batched, moments = variant
    return f"{backend}/{RESTART_MODES[batched]}/{moments}"


# Issue 8's targets: wall time of one policy search, by (propagator, n), in seconds.
TARGETS: dict[tuple[str, int], float] = {
    ("moment_matching", 250): 15.0,
    ("moment_matching", 500): 30.0,
    ("particles_pathwise", 250): 60.0,
}
TARGET_NOTES = {
    "moment_matching": "one policy search",
    "particles": "500 Adam steps, P = 400",
    "particles_pathwise": "500 Adam steps, P = 400, pathwise sampling",
}
# Established implementations as issue 8 quotes them: context, not measured here.
QUOTED_REFERENCES = [
    "TF/GPflow PILCO (moment matching): 46–79 s per policy search, pendulum, 160–240 data points.",
    "PyTorch particle PILCO: 265–430 s per policy search (500 Adam steps, 400 particles), cart-pole, "
    "60–240 data points.",
]
MAX_RECORDED_WARNINGS = 5
PRODUCT_REPEATS = 20  # timed variance products (the particles' arithmetic floor) after one warm-up
DEFAULT_OUTPUT = ROOT / "docs" / "bench" / "policy_search.json"
SECTION = "bench_policy_search"
DESCRIPTION = (
    "Wall time of one full policy search with the loop's real settings (moment matching: the default "
    "`propagation=moment_matching optimizer=lbfgs`; particles: `propagation=particles optimizer=adam "
    "optimizer.steps=500`, P = 400) and of one rollout + gradient (`expected_return(...).backward()`, median of "
    "the repeats after one warm-up) over the task's horizon, on real cart-pole transitions (0.5 kg; random-action "
    "episodes alternating with random-RBF-policy episodes, cut at n tuples). One exact `DynamicsGP` per n, "
    f"fitted once in float64 with `fit(restarts={MODEL_FIT_RESTARTS})` (a benchmark model; the loop uses "
    "`model.restarts = 3`); the float32 rows load the same θ and data in float32 (model, posterior cache, "
    "policy and start distribution in float32, as the loop with `dtype=float32`). Propagator, optimiser, "
    "initial policy ψ_0, start distribution, horizon and reward are made from the composed default config "
    "by `qtl.build.build`, as the loop makes them; the search is timed as the loop times it (propagator construction + "
    "search; torch.optim's one-off lazy import, ~1 s, is paid before, as the loop's GP fit pays it before its "
    "first search). Each configuration runs in a fresh subprocess; peak RSS is its `getrusage` max RSS (torch, "
    "GPyTorch and the model included). Evaluations: objective calls of the search (rollout + gradient each)."
)

COMPARE_DESCRIPTION = (
    "Moment-matching policy search (the loop's `optimizer=lbfgs` settings), float64, the same data, model and ψ_0 "
    "in every row, each row in its own subprocess: the exp sums on the torch path or the native kernel "
    "(`kernels.backend`), the restarts one after the other or all at once (`optimizer.batched=true`: each restart "
    "runs its own L-BFGS, one batched rollout per round answers all that still run), and the per-step moment maths "
    "as written first, in the fused formulation with fewer dispatched operations, or in that formulation with its "
    "hot pieces (SE-kernel moments, angle features, squashing) one compiled call forward and one backward "
    "each (`kernels.moments=reference|fused|native`). Rollouts: "
    "calls of the objective (one per batched round); evaluations: per restart. 'rollout + gradient': one restart; "
    "'batched, R restarts': one rollout + gradient of the R starting points of the search at once. Ratios are times "
    "over torch + sequential + reference (below 1: faster). Predicted return: the best V found; per restart in "
    "brackets (every variant runs the same algorithm per restart, so they differ by round-off and where it leads)."
)

FLOOR_DESCRIPTION = (
    "Particles' arithmetic floor: each step needs, per output and particle, the latent variance "
    "α² − k (K + σ_ε²I)⁻¹ kᵀ and its gradient, i.e. the rows k (K + σ_ε²I)⁻¹: one `E x P x n` by `E x n x n` "
    "product, E P n² multiply-adds (two triangular solves with the Cholesky factor cost as many), whatever else an "
    "implementation of the exact GP does. That product alone, measured on this machine (random matrices of the "
    f"row's shapes and dtype, median of {PRODUCT_REPEATS} after a warm-up), H times per evaluation:"
)


class _WarningLog(logging.Handler):
    """Collects the warnings the library logs during a measurement."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        """Keep the message."""
        self.messages.append(record.getMessage())


def warm_up_optimisers() -> None:
    """Pay torch.optim's one-off lazy import (torch._dynamo, ~1 s) here: in the loop the GP fit pays it first."""
    dummy = torch.nn.Parameter(torch.zeros(1))
    torch.optim.Adam([dummy])
    torch.optim.LBFGS([dummy])


def variance_product_s(num_outputs: int, num_particles: int, n: int, dtype: torch.dtype,
                       device: torch.device) -> float:
    """Median time of one step's `E x P x n` by `E x n x n` product k (K + σ_ε²I)⁻¹ (the particles' GEMM)."""
    kern = torch.randn(num_outputs, num_particles, n, dtype=dtype, device=device)
    k_inv = torch.randn(num_outputs, n, n, dtype=dtype, device=device)
    times = []
    for _ in range(PRODUCT_REPEATS + 1):  # each product waits for its result, so the next starts idle
        tic = time.perf_counter()
        kern @ k_inv
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        times.append(time.perf_counter() - tic)
    return statistics.median(times[1:])  # the first, a warm-up, also waits for the random matrices


def measure(job: dict[str, Any]) -> dict[str, Any]:
    """Measure one (propagator, n, dtype) in this process; a failure is recorded, not raised."""
    torch.set_num_threads(job["threads"])
    result: dict[str, Any] = {key: job[key] for key in ("propagator", "n", "dtype", *_VARIANT_KEYS) if key in job}
    log_warnings = _WarningLog()
    logging.getLogger("qtl").addHandler(log_warnings)
    stage = "setup"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            # -- Everything as the loop makes it (qtl.build), from the composed config. ----------------
            cfg = compose_config(job["propagator"], job["dtype"],
                                 [*job["overrides"], *variant_overrides(job), f"device={job['device']}"])
            if "integration" in job:  # the step, and the task's kinematics where known but undeclared
                cfg = kinematic.with_integration(cfg, job["integration"])
            seed_everything(cfg.seed)
            parts = build(cfg)
            task, reward, start, make_propagator = parts.task, parts.reward, parts.start, parts.make_propagator
            model = DynamicsGP.load(job["model"], dtype=parts.dtype, device=parts.device)
            policy = parts.initial_policy()
            warm_up_optimisers()
            result.update(horizon=task.horizon, propagation=OmegaConf.to_container(cfg.propagation, resolve=True),
                          optimizer=OmegaConf.to_container(cfg.optimizer, resolve=True),
                          kernels=OmegaConf.to_container(cfg.kernels, resolve=True),
                          kernel_backend=parts.kernel_backend, setup_rss_mib=peak_rss_mib())

            # -- One rollout + gradient: a warm-up, then the median of the repeats. ------------------
            stage = "rollout + gradient"
            propagator = make_propagator(model, policy, reward, angle_dims=task.angle_dims)
            result["value_initial"] = rollout_and_gradient(propagator, start, task.horizon)
            times = []
            for _ in range(job["repeats"]):
                tic = time.perf_counter()
                rollout_and_gradient(propagator, start, task.horizon)
                times.append(time.perf_counter() - tic)
            result.update(rollout_grad_s_median=statistics.median(times), rollout_grad_s_min=min(times),
                          repeats=job["repeats"])
            if job["propagator"] == "particles":
                # The arithmetic no implementation of the exact per-particle variance avoids: H products.
                stage = "variance product"
                product = variance_product_s(task.state_dim, cfg.propagation.num_particles, job["n"], parts.dtype,
                                             parts.device)
                result["variance_products_s_per_evaluation"] = task.horizon * product
            if job.get("batched"):
                stage = "batched rollout + gradient"
                result.update(batched_rollout_grad(parts, model, policy, cfg.seed, job["repeats"]))

            # -- One policy search, timed as the loop times it (lines 6-9). --------------------------
            if not job["skip_search"]:
                stage = "policy search"
                tic = time.perf_counter()
                propagator = make_propagator(model, policy, reward, angle_dims=task.angle_dims)
                found = parts.search(policy, functools.partial(propagator.expected_return, start, task.horizon),
                                     generator=torch_generator(cfg.seed, SEARCH_EPISODE, SEARCH_STREAM))
                result.update(search_s=time.perf_counter() - tic, evaluations=found.evaluations,
                              rollouts=found.rollouts, value_found=found.value, run_values=found.run_values)
        except Exception as err:  # a benchmark records what failed and goes on
            where = traceback.extract_tb(err.__traceback__)[-1]
            origin = f"{Path(where.filename).name}:{where.lineno}"
            result["error"] = f"{stage}: {type(err).__name__} at {origin}: {err}"
        finally:
            logging.getLogger("qtl").removeHandler(log_warnings)
    seen = list(dict.fromkeys([*log_warnings.messages, *(f"{w.category.__name__}: {w.message}" for w in caught)]))
    result["warnings"] = seen[:MAX_RECORDED_WARNINGS]
    result["peak_rss_mib"] = peak_rss_mib()
    return result


# What a comparison job adds to a job: the exp-sum backend, whether the restarts are batched, the formulation.
_VARIANT_KEYS = ("backend", "batched", "moments", "integration")


def variant_overrides(job: dict[str, Any]) -> list[str]:
    """The Hydra overrides of a comparison job's backend and restart mode (none for the other jobs)."""
    overrides = []
    if "backend" in job:
        overrides.append(f"kernels.backend={job['backend']}")
    if "batched" in job:
        overrides.append(f"optimizer.batched={str(job['batched']).lower()}")
    if "moments" in job:
        overrides.append(f"kernels.moments={job['moments']}")
    return overrides


def run_job(job: dict[str, Any]) -> dict[str, Any]:
    """Measure one configuration in a fresh subprocess; a crash is recorded as an error."""
    done = subprocess.run([sys.executable, __file__, "--worker", json.dumps(job)], capture_output=True, text=True)
    lines = done.stdout.strip().splitlines()
    if done.returncode == 0 and lines:
        return json.loads(lines[-1])
    tail = done.stderr.strip().splitlines()[-5:]
    return {key: job[key] for key in ("propagator", "n", "dtype", *_VARIANT_KEYS) if key in job} | {
        "error": f"worker exited with {done.returncode}: {' | '.join(tail)}"}


def _variant(row: dict[str, Any]) -> tuple[str, bool, str]:
    """A comparison row's (backend, batched, moments); rows from before the formulation switch are 'reference'."""
    return row["backend"], row["batched"], row.get("moments", "reference")


def add_ratios(rows: list[dict[str, Any]]) -> None:
    """Each comparison row's times over those of torch + sequential at the same n (where both were measured)."""
    for row in rows:
        base = next((r for r in rows if r["n"] == row["n"] and _variant(r) == BASELINE_VARIANT), None)
        for key in ("search_s", "rollout_grad_s_median"):
            if base is not None and key in row and key in base:
                row[f"{key}_ratio"] = row[key] / base[key]


def comparison_markdown(rows: list[dict[str, Any]]) -> list[str]:
    """The backend x restarts x formulation table."""
    lines = [
        "### Exp sums torch vs native, restarts sequential vs batched, moments reference, fused or native",
        "",
        COMPARE_DESCRIPTION,
        "",
    ]
    errors, cells = [], []
    for r in rows:
        if "error" in r:
            errors.append(f"{len(errors) + 1}. n = {r['n']}, {r['backend']}, {RESTART_MODES[r['batched']]}, "
                          f"{_variant(r)[2]}: "
                          f"`{r['error']}`")
        ratio = {key: f"{r[key]:.2f}" if key in r else "—" for key in ("search_s_ratio", "rollout_grad_s_median_ratio")}
        per_rollout = f"{r['search_s'] / r['rollouts']:.3f}" if r.get("rollouts") else "—"
        batched = (f"{r['batched_rollout_grad_s_median']:.3f} (R = {r['batched_restarts']})"
                   if "batched_rollout_grad_s_median" in r else "—")
        found = (f"{r['value_found']:.4g} ({', '.join(f'{v:.4g}' for v in r['run_values'])})"
                 if "value_found" in r else (f"error ({len(errors)})" if "error" in r else "—"))
        cells.append([r["n"], r["backend"], RESTART_MODES[r["batched"]], _variant(r)[2], _seconds(r, "search_s"),
                      ratio["search_s_ratio"], r.get("rollouts", "—"), r.get("evaluations", "—"), per_rollout,
                      _seconds(r, "rollout_grad_s_median"), ratio["rollout_grad_s_median_ratio"], batched, found])
    lines.append(markdown_table(cells, [
        "n", "backend", "restarts", "moments", "policy search (s)", "ratio", "rollouts", "evaluations", "s / rollout",
        "rollout + gradient (s)", "ratio", "batched, R restarts (s)", "predicted return (per restart)"],
        "rlllrrrrrrrrl"))
    if errors:
        lines += ["", "Errors:", "", *errors]
    return lines


def judge(result: dict[str, Any], judged: bool, why_not: str = "settings overridden") -> tuple[str, str]:
    """The target of a result's configuration and whether it was met."""
    target = TARGETS.get((result["propagator"], result["n"]))
    if target is None:
        return "—", "—"
    label = f"≤ {target:.0f} s ({TARGET_NOTES[result['propagator']]})"
    if not judged:
        return label, f"not judged ({why_not})"
    if "search_s" not in result:
        return label, "not measured"
    return label, "met" if result["search_s"] <= target else "not met"


def _seconds(result: dict[str, Any], key: str) -> str:
    """A time in seconds for the table, or a dash where it was not measured."""
    return f"{result[key]:.2f}" if key in result else "—"


def settings_lines(results: list[dict[str, Any]]) -> list[str]:
    """What each propagator ran with: horizon, propagation and optimiser settings of its first measured row."""
    lines = []
    for name in dict.fromkeys(r["propagator"] for r in results):
        row = next((r for r in results if r["propagator"] == name and "optimizer" in r), None)
        if row is not None:
            settings = [f"{k}={v}" for k, v in {**row["propagation"], **row["optimizer"]}.items()
                        if k not in ("_target_", "_partial_")]
            lines.append(f"- {name}: H = {row['horizon']}, {', '.join(settings)}")
    return lines


def floor_lines(results: list[dict[str, Any]]) -> list[str]:
    """Per particle row: the time of its variance products alone, per evaluation and for the target's steps."""
    lines = []
    for r in results:
        if "variance_products_s_per_evaluation" not in r:
            continue
        per_evaluation = r["variance_products_s_per_evaluation"]
        optimizer = r["optimizer"]
        # The search's evaluations where it ran, else the configured Adam steps (L-BFGS has no fixed count).
        steps = r.get("evaluations") or optimizer.get("steps", 0) * optimizer.get("restarts", 1)
        share = f", {per_evaluation / r['rollout_grad_s_median']:.0%} of its rollout + gradient" \
            if "rollout_grad_s_median" in r else ""
        target = TARGETS.get(("particles", r["n"]))
        against = f" (target {target:.0f} s)" if target is not None else ""
        search = f"; {steps * per_evaluation:.1f} s for {steps} steps{against}" if steps else ""
        lines.append(f"- n = {r['n']}, {r['dtype']}: {per_evaluation:.3f} s per evaluation{share}{search}")
    return lines


def sampling_ratio_lines(results: list[dict[str, Any]]) -> list[str]:
    """Per n and dtype with both particle rows: pathwise over marginal, for the search and the rollout + gradient."""
    lines = []
    rows = {(r["propagator"], r["n"], r["dtype"]): r for r in results if "error" not in r}
    for (name, n, dtype), pathwise in rows.items():
        marginal = rows.get(("particles", n, dtype))
        if name != "particles_pathwise" or marginal is None:
            continue
        parts = []
        for key, what in (("search_s", "policy search"), ("rollout_grad_s_median", "rollout + gradient")):
            if key in pathwise and key in marginal:
                ratio = pathwise[key] / marginal[key]
                parts.append(f"{what} {pathwise[key]:.2f} s vs {marginal[key]:.2f} s ({ratio:.2f}×, "
                             f"{1 / ratio:.1f}× faster)")
        if parts:
            lines.append(f"- n = {n}, {dtype}: " + "; ".join(parts))
    return lines


def markdown(results: list[dict[str, Any]], info: dict[str, Any], comparison: list[dict[str, Any]]) -> str:
    """The section of docs/benchmarks.md."""
    m = info["machine"]
    settings = "the loop's settings" if info["judged"] else f"overridden settings ({', '.join(info['overrides_all'])})"
    on_gpu = info["device"] != "cpu"
    where = f"device {info['device']} ({info['gpu']}), " if on_gpu else ""
    lines = [
        "## Policy search: moment matching and particles" + (f" ({info['device']})" if on_gpu else ""),
        "",
        DESCRIPTION,
        "",
        f"`{info['command']}` at commit {info.get('commit', '?')} — "
        f"{info['date']}, {where}{m['cpu']} ({m['cores']} cores), "
        f"{info['threads']} torch threads, torch {m['torch']}, {settings}. Results: `{info['output']}`.",
        "",
        *settings_lines(results),
        "",
    ]
    errors, cells = [], []
    for r in results:
        target, met = judge(r, info["judged"], info["why_not_judged"])
        evals = str(r["evaluations"]) if "evaluations" in r else "—"
        per_eval = f"{r['search_s'] / r['evaluations']:.3f}" if r.get("evaluations") else "—"
        rss = f"{r['peak_rss_mib']:.0f}" if "peak_rss_mib" in r else "—"
        if "error" in r:
            errors.append(f"{len(errors) + 1}. {r['propagator']}, n = {r['n']}, {r['dtype']}: `{r['error']}`")
            met = f"error ({len(errors)})"
        cells.append([r["propagator"], r["n"], r["dtype"], _seconds(r, "rollout_grad_s_median"),
                      _seconds(r, "search_s"), evals, per_eval, rss, target, met])
    lines.append(markdown_table(cells, [
        "propagator", "n", "dtype", "rollout + gradient (s, median)", "policy search (s)", "evaluations",
        "s / evaluation", "peak RSS (MiB)", "target", "met?"], "lrlrrrrrll"))
    if errors:
        lines += ["", "Errors:", "", *errors]
    ratios = sampling_ratio_lines(results)
    if ratios:
        lines += ["", "Pathwise against marginal particle sampling, measured in this run:", "", *ratios]
    floors = floor_lines(results)
    if floors:
        lines += ["", FLOOR_DESCRIPTION, "", *floors]
    lines += ["", "Quoted in issue 8 for context — not measured here, other machines:", ""]
    lines += [f"- {ref}" for ref in QUOTED_REFERENCES]
    if comparison:
        lines += ["", *comparison_markdown(comparison)]
    return "\n".join(lines)


def compare_only_markdown(info: dict[str, Any], comparison: list[dict[str, Any]]) -> str:
    """The section of a ``--compare-only`` run: how it was run, then the comparison table."""
    m = info["machine"]
    return "\n".join([
        f"`{info['command']}` at commit {info.get('commit', '?')} — "
        f"{info['date']}, {m['cpu']} ({m['cores']} cores), {info['threads']} torch threads, "
        f"torch {m['torch']}. Results: `{info['output']}`.",
        "",
        *comparison_markdown(comparison),
    ])


def measure_aircraft(job: dict[str, Any]) -> dict[str, Any]:
    """The aircraft round under both steps in this process; a failure is recorded, not raised."""
    torch.set_num_threads(job["threads"])
    overrides = [*job["overrides"], f"model.sparse_above={job['inducing']}", f"model.inducing={job['inducing']}",
                 f"device={job['device']}"]
    try:
        return kinematic.aircraft_rounds(overrides, job["seed"], job["repeats"]) | {"peak_rss_mib": peak_rss_mib()}
    except Exception as err:  # a benchmark records what failed and goes on
        return {"error": f"{type(err).__name__}: {err}"}


def integration_suffix(device: str, tag: str = "") -> str:
    """The name suffix of ``--compare integration``'s JSON and section: the device where not the CPU, and the tag."""
    return "_integration" + ("" if resolve_device(device).type == "cpu" else f"-{device}") + (f"-{tag}" if tag else "")


def compare_integration(args: argparse.Namespace) -> None:
    """Full-state vs kinematic moment matching: cart-pole searches per n, one aircraft round; JSON and section."""
    suffix = integration_suffix(args.device, args.tag)
    output = (args.output or DEFAULT_OUTPUT.with_stem(DEFAULT_OUTPUT.stem + suffix)).resolve()
    data_cfg = compose_config("moment_matching", "float64", args.overrides)
    rows, models = [], {}
    for n in args.compare_sizes:
        path, models[n] = ensure_model(data_cfg, n, args.seed, args.cache_dir)
        for integration in kinematic.INTEGRATIONS:
            job = {"propagator": "moment_matching", "n": n, "dtype": "float64", "model": str(path),
                   "overrides": [*args.overrides, *args.mm_overrides], "threads": args.threads,
                   "device": args.device, "repeats": args.repeats, "skip_search": args.skip_search,
                   "integration": integration}
            rows.append(run_job(job))
            print(json.dumps({k: v for k, v in rows[-1].items() if k not in ("propagation", "optimizer")}),
                  file=sys.stderr, flush=True)
    aircraft = None
    if args.aircraft_inducing > 0:
        job = {"aircraft": True, "inducing": args.aircraft_inducing, "overrides": args.aircraft_overrides,
               "threads": args.threads, "device": args.device, "repeats": args.repeats, "seed": args.seed}
        aircraft = run_job(job)
        print(json.dumps(aircraft), file=sys.stderr, flush=True)
    info = {"date": today(), "commit": commit(), "command": command_line(), "machine": machine(),
            "threads": args.threads, "device": args.device, "output": display_path(output),
            "models": {str(n): m for n, m in models.items()}, "aircraft": aircraft}
    write_results(output, info, rows)
    m = info["machine"]
    section = "\n".join([f"`{info['command']}` at commit {info.get('commit', '?')} — {info['date']}, {m['cpu']} "
                         f"({m['cores']} cores), {args.threads} torch threads, torch {m['torch']}. "
                         f"Results: `{info['output']}`.", "", *kinematic.markdown(rows, aircraft)])
    if not args.no_docs:
        write_section(SECTION + suffix, section)
    print(section)


def main() -> None:
    """Fit (or load) one model per n, run every configuration in its own subprocess; write JSON and markdown."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=SIZES)
    parser.add_argument("--dtypes", nargs="+", default=list(DTYPES), choices=list(DTYPES))
    parser.add_argument("--propagators", nargs="+", default=list(PROPAGATORS), choices=list(PROPAGATORS))
    parser.add_argument("--threads", type=int, default=2, help="torch threads of every measurement")
    parser.add_argument("--device", default="cpu", help="torch device of model, policy and propagation (cpu, cuda)")
    parser.add_argument("--repeats", type=int, default=3, help="timed rollouts + gradients after one warm-up")
    parser.add_argument("--seed", type=int, default=0, help="of the data collection and the model fit")
    parser.add_argument("--skip-search", action="store_true", help="only the rollout + gradient")
    parser.add_argument("--search-at-targets", action="store_true",
                        help="time the policy search only where issue 8 sets a target (rollout + gradient everywhere)")
    parser.add_argument("--compare-sizes", type=int, nargs="+", default=COMPARE_SIZES,
                        help="n of the backend x restarts comparison (moment matching, float64)")
    parser.add_argument("--no-compare", action="store_true", help="skip the backend x restarts comparison")
    parser.add_argument("--variants", nargs="+", metavar="BACKEND/RESTARTS/MOMENTS",
                        help="compare only these (e.g. native/batched/native; the baseline "
                             f"{variant_name(BASELINE_VARIANT)} always runs too); default: all")
    parser.add_argument("--compare-only", action="store_true",
                        help="only the backend x restarts comparison (its own JSON and docs section: *_compare)")
    parser.add_argument("--tag", default="",
                        help="--compare integration: names its JSON and section (e.g. threads1 for a --threads 1 run)")
    parser.add_argument("--compare", choices=["integration"],
                        help="integration: only full-state vs kinematic moment matching (issue 63), at --compare-sizes")
    parser.add_argument("--aircraft-inducing", type=int, default=300,
                        help="--compare integration: the aircraft round's inducing inputs m (0: no aircraft round)")
    parser.add_argument("--aircraft-overrides", nargs="*", default=[],
                        help="--compare integration: Hydra overrides of the aircraft stage (e.g. a smaller fit)")
    parser.add_argument("--overrides", nargs="*", default=[], help="Hydra overrides for every configuration")
    parser.add_argument("--mm-overrides", nargs="*", default=[], help="Hydra overrides for moment matching only")
    parser.add_argument("--particles-overrides", nargs="*", default=[], help="Hydra overrides for particles only")
    parser.add_argument("--output", type=Path, help="JSON path (default: docs/bench/policy_search[-cuda].json)")
    parser.add_argument("--no-docs", action="store_true", help="do not write the section of docs/benchmarks.md")
    parser.add_argument("--cache-dir", type=Path, default=CACHE_DIR, help="fitted models, one per n")
    parser.add_argument("--worker", help=argparse.SUPPRESS)  # child process: one configuration, as JSON
    args = parser.parse_args()
    if args.worker:
        job = json.loads(args.worker)
        print(json.dumps(measure_aircraft(job) if job.get("aircraft") else measure(job)))
        return
    if args.compare == "integration":
        compare_integration(args)
        return

    torch.set_num_threads(args.threads)
    device = resolve_device(args.device)  # a bad or absent device fails here, before any measurement
    # --compare-only writes beside the full run's results and section, never over them.
    suffix = ("_compare" if args.compare_only else "") + ("" if device.type == "cpu" else f"-{device.type}")
    output = (args.output or DEFAULT_OUTPUT.with_stem(DEFAULT_OUTPUT.stem + suffix)).resolve()
    per_propagator = {"moment_matching": args.mm_overrides, "particles": args.particles_overrides,
                      "particles_pathwise": args.particles_overrides}
    data_cfg = compose_config("moment_matching", "float64", args.overrides)
    results, models, comparison = [], {}, []
    compare_sizes = [] if args.no_compare else args.compare_sizes
    if args.compare_only and args.no_compare:
        parser.error("--compare-only and --no-compare leave nothing to measure")
    names = {variant_name(v): v for v in COMPARE_VARIANTS}
    unknown = sorted(set(args.variants or ()) - set(names))
    if unknown:
        parser.error(f"unknown --variants {', '.join(unknown)}: choose from {', '.join(names)}")
    chosen = set(args.variants or names)
    variants = [v for v in COMPARE_VARIANTS if v == BASELINE_VARIANT or variant_name(v) in chosen]
    for n in dict.fromkeys([*([] if args.compare_only else args.sizes), *compare_sizes]):
        path, models[n] = ensure_model(data_cfg, n, args.seed, args.cache_dir)
        how = "cached" if models[n]["cached"] else f"fitted in {models[n]['fit_s']:.1f} s"
        print(f"n={n}: model {how} ({path.name})", file=sys.stderr, flush=True)
        for backend, batched, moments in variants if n in compare_sizes else ():
            job = {"propagator": "moment_matching", "n": n, "dtype": "float64", "model": str(path),
                   "overrides": [*args.overrides, *args.mm_overrides], "threads": args.threads,
                   "device": args.device, "repeats": args.repeats, "skip_search": False,
                   "backend": backend, "batched": batched, "moments": moments}
            comparison.append(run_job(job))
            print(json.dumps({k: v for k, v in comparison[-1].items() if k not in ("propagation", "optimizer")}),
                  file=sys.stderr, flush=True)
        if args.compare_only or n not in args.sizes:
            continue
        for propagator in args.propagators:
            for dtype_name in args.dtypes:
                job = {"propagator": propagator, "n": n, "dtype": dtype_name, "model": str(path),
                       "overrides": [*args.overrides, *per_propagator[propagator]], "threads": args.threads,
                       "device": args.device, "repeats": args.repeats,
                       "skip_search": args.skip_search or (args.search_at_targets and (propagator, n) not in TARGETS)}
                results.append(run_job(job))
                print(json.dumps({k: v for k, v in results[-1].items() if k not in ("propagation", "optimizer")}),
                      file=sys.stderr, flush=True)

    overrides_all = [*args.overrides, *args.mm_overrides, *args.particles_overrides]
    info = {
        "date": today(),
        "commit": commit(),
        "command": command_line(),
        "machine": machine(),
        "threads": args.threads,
        "device": args.device,
        "gpu": torch.cuda.get_device_name(device) if device.type == "cuda" else None,
        "output": display_path(output),
        "overrides_all": overrides_all,
        "judged": not overrides_all and not args.skip_search and device.type == "cpu",
        "why_not_judged": "the targets are for 2 CPU threads" if device.type != "cpu" else "settings overridden",
        "targets": [{"propagator": p, "n": n, "search_s_max": s, "what": TARGET_NOTES[p]} for (p, n), s in
                    TARGETS.items()],
        "quoted_references": QUOTED_REFERENCES,
        "models": {str(n): m for n, m in models.items()},
    }
    for r in results:
        r["target"], r["met"] = judge(r, info["judged"], info["why_not_judged"])
    add_ratios(comparison)
    info["comparison"] = comparison
    write_results(output, info, results)
    section = compare_only_markdown(info, comparison) if args.compare_only else markdown(results, info, comparison)
    if not args.no_docs:
        write_section(SECTION + suffix, section)
    print(section)


if __name__ == "__main__":
    main()
