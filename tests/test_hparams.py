"""TensorBoard dashboards: outcome metrics, HParams hyper-parameters, chart layouts and text, read back from events."""

from __future__ import annotations

import csv
import math
import re
import time
from pathlib import Path

import pytest
from omegaconf import OmegaConf
from tensorboard import context
from tensorboard.backend.event_processing.data_provider import MultiplexerDataProvider
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
from tensorboard.backend.event_processing.plugin_event_multiplexer import EventMultiplexer
from tensorboard.plugins.base_plugin import TBContext
from tensorboard.plugins.custom_scalar import layout_pb2
from tensorboard.plugins.hparams import api_pb2, backend_context, list_session_groups, metadata

from qtl.hparams import (
    CONFIG_TAG,
    DEFAULT_APPROACH,
    OUTCOMES,
    PLAN_TAG,
    approach_of,
    compliance_layout,
    outcomes,
    run_hparams,
    scalar_layout,
)
from qtl.loop import run
from qtl.recorder import METRICS_FILE, TIMINGS_FILE
from qtl.report.approaches import DEFAULT_APPROACH as REPORT_DEFAULT_APPROACH
from tests.helpers import tiny_config


def read_csv(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def session_groups(logdir: Path) -> list[api_pb2.SessionGroup]:
    """The HParams plugin's table of ``logdir``, as its backend serves it to the dashboard."""
    multiplexer = EventMultiplexer()
    multiplexer.AddRunsFromDirectory(str(logdir))
    multiplexer.Reload()
    provider = MultiplexerDataProvider(multiplexer, str(logdir))
    plugin = backend_context.Context(TBContext(logdir=str(logdir), multiplexer=multiplexer, data_provider=provider))
    request = api_pb2.ListSessionGroupsRequest(start_index=0, slice_size=100, include_metrics=True,
                                               allowed_statuses=[api_pb2.STATUS_UNKNOWN])
    return list(list_session_groups.Handler(context.RequestContext(), plugin, "", request).run().session_groups)


def test_outcomes_summarise_the_learning_curve():
    rows = [{"return": r, "success": s, "compliance": c}
            for r, s, c in zip([1.0, 2.0, 4.0, 4.0, 5.0], [0, 0, 1, 0, 1], ["", 0.5, "", 0.75, ""], strict=True)]
    got = outcomes(rows, [{"episode_s": t} for t in (0.5, 1.0, "", 2.0, 0.25)])
    assert got["outcome/final_performance"] == pytest.approx(13.0 / 3.0)
    assert got["outcome/auc"] == pytest.approx(0.5 * 1 + 2 + 4 + 4 + 0.5 * 5)  # trapezoidal, as report.py's tables
    assert got["outcome/first_success"] == 2.0
    assert got["outcome/time_to_convergence"] == 4.0  # 4 < 0.95 × 13/3 ≈ 4.12 <= 5
    assert got["outcome/last_compliance"] == 0.75
    assert got["outcome/wall_time_s"] == pytest.approx(3.75)  # an empty cell (an older run's) counts 0
    assert set(got) == set(OUTCOMES)
    # As read back from metrics.csv (strings); no success, no compliance, a curve no episode converges on.
    never = outcomes([{"return": "-10.0", "success": "0", "compliance": ""}] * 3)
    assert math.isnan(never["outcome/first_success"]) and math.isnan(never["outcome/last_compliance"])
    assert math.isnan(never["outcome/time_to_convergence"]) and never["outcome/wall_time_s"] == 0.0


def test_run_hparams_name_the_choices_of_a_transfer_run():
    cfg = OmegaConf.create({
        "seed": 3,
        "task": {"name": "cartpole", "env": {"id": "qtl/CartPoleSwingUp-v0", "pole_mass": 2.0, "wind": [1, 2]}},
        "propagation": {"_target_": "qtl.propagation.MomentMatching"},
        "transfer": {"source": "runs/source/seed_3", "hyperparameters": True, "policy": True},
    })
    values = run_hparams(cfg, "qtl_gamma_05", "forgetting", 0.5)
    assert values == {"task": "cartpole", "env/pole_mass": 2.0, "env/wind": "[1, 2]", "approach": "qtl_gamma_05",
                      "source": "runs/source/seed_3", "theta_s": True, "psi_s": True, "rule": "forgetting",
                      "gamma": 0.5, "propagation": "moment_matching", "seed": 3}
    cfg.transfer.source = None
    cfg.propagation["_target_"] = "qtl.propagation.Particles"
    pilco = run_hparams(cfg, "pilco", "none", None)
    assert pilco["source"] == "" and not pilco["theta_s"] and not pilco["psi_s"] and math.isnan(pilco["gamma"])
    assert pilco["propagation"] == "particles" and list(pilco) == list(values)  # the same columns for every run
    assert approach_of(False, "none") == DEFAULT_APPROACH == REPORT_DEFAULT_APPROACH
    assert approach_of(True, "forgetting") == "custom"


def test_scalar_layout_pairs_theta_and_theta_p_of_each_hyperparameter():
    layout = scalar_layout(2, 3)
    assert layout["returns"] == {"real vs predicted return": ["Multiline", ["^eval/return$",
                                                                            "^policy/predicted_return$"]]}
    charts = layout["θ_i vs θ_p_i: out1"]
    assert list(charts) == ["out1/lengthscale/in0", "out1/lengthscale/in1", "out1/lengthscale/in2",
                            "out1/signal_variance", "out1/noise_variance"]
    kind, patterns = charts["out1/lengthscale/in2"]
    tags = ["theta/out1/lengthscale/in2", "theta_p/out1/lengthscale/in2", "theta/out0/lengthscale/in2",
            "theta/out1/lengthscale/in20", "theta_p/out1/lengthscale/in1"]
    assert kind == "Multiline" and [t for t in tags if any(re.search(p, t) for p in patterns)] == tags[:2]


def test_a_run_and_its_resume_leave_one_hparams_session_with_the_final_outcomes(tmp_path):
    run(tiny_config("episodes=1", "seed=4", "task.env.pole_mass=0.8"), tmp_path)
    # Event files are read in name order: <seconds>.<host>.<pid>.<writer count>. In one process and one second the
    # count decides, as text ("10" < "9"); a resume is another process, or at least another second.
    time.sleep(1.1)
    run(tiny_config("episodes=2", "seed=4", "task.env.pole_mass=0.8"), tmp_path, resume=True)
    events = EventAccumulator(str(tmp_path), size_guidance={"tensors": 0, "scalars": 0})
    events.Reload()
    # Written once, at the first run's start: one experiment, one session, one layout, one text each.
    for tag in (metadata.EXPERIMENT_TAG, metadata.SESSION_START_INFO_TAG, "custom_scalars__config__",
                f"{CONFIG_TAG}/text_summary", f"{PLAN_TAG}/text_summary"):
        assert len(events.Tensors(tag)) == 1, tag
    content = events.PluginTagToContent(metadata.PLUGIN_NAME)
    start = metadata.parse_session_start_info_plugin_data(content[metadata.SESSION_START_INFO_TAG])
    hparams = {name: getattr(value, value.WhichOneof("kind")) for name, value in start.hparams.items()}
    assert hparams == {"task": "cartpole", "env/pole_mass": 0.8, "approach": "pilco", "source": "", "theta_s": False,
                       "psi_s": False, "rule": "none", "gamma": 0.0,
                       "propagation": "moment_matching", "seed": 4.0}
    experiment = metadata.parse_experiment_plugin_data(content[metadata.EXPERIMENT_TAG])
    assert {info.name for info in experiment.hparam_infos} == set(hparams)
    assert [m.name.tag for m in experiment.metric_infos] == list(OUTCOMES)
    # The metrics: one value per episode, the last step's being the whole run's (metrics.csv and timings.csv).
    expected = outcomes(read_csv(tmp_path / METRICS_FILE), read_csv(tmp_path / TIMINGS_FILE))
    for tag, value in expected.items():
        logged = events.Scalars(tag)
        assert [e.step for e in logged] == [0, 1, 2], tag
        assert logged[-1].value == pytest.approx(value, rel=1e-6, nan_ok=True), tag
    assert expected["outcome/wall_time_s"] > 0
    # The chart layout and the text, as written.
    layout = layout_pb2.Layout.FromString(events.Tensors("custom_scalars__config__")[0].tensor_proto.string_val[0])
    assert [c.title for c in layout.category] == ["returns", *(f"θ_i vs θ_p_i: out{j}" for j in range(4))]
    plan = events.Tensors(f"{PLAN_TAG}/text_summary")[0].tensor_proto.string_val[0].decode()
    config = events.Tensors(f"{CONFIG_TAG}/text_summary")[0].tensor_proto.string_val[0].decode()
    assert plan == "no transfer (PILCO)" and "    episodes: 1\n" in config and "pole_mass: 0.8" in config
    # The dashboard's table: one session, these hyper-parameters, the final outcomes.
    (group,) = session_groups(tmp_path)
    assert len(group.sessions) == 1
    assert {name: getattr(value, value.WhichOneof("kind")) for name, value in group.hparams.items()} == hparams
    shown = {m.name.tag: m.value for m in group.metric_values}
    assert shown == pytest.approx(expected, rel=1e-6, nan_ok=True)


def test_compliance_layout_charts_every_sources_compliance():
    layout = compliance_layout(3)
    kind, patterns = layout["transfer"]["task compliance Λ_k per source"]
    assert kind == "Multiline" and patterns == [f"^transfer/compliance/{k}$" for k in range(3)]
