"""How each propagator values one policy on one model: prediction against search, for a run's checkpoints.

A diagnostic for a propagator whose searches fail: if its rollouts value a known good policy (e.g. the one
moment matching found from the same data) as highly as moment matching does, the model and the estimate are
right and the search is what fails. The model is refitted on the data of ``--data`` (a checkpoint of
``RUN_DIR``) with the run's model settings, as ``probe_policy_search.py`` does; ψ is the policy of
``--policy`` (by default the same checkpoint). Printed as JSON: moment matching's predicted return, and for
each particle propagator (marginal or pathwise sampling, x + Δ or speed integration where the task declares
its kinematics) the predicted return under the task's reward over ``--draws`` draws of ``--particles``; where
the run's config (with the overrides, e.g. a recipe's settings) is a particle propagator, that one too, under the
task's reward (``configured``) and under its search reward (``configured_search_reward``). With ``--gradients K``
also the reparameterised gradient ∂V/∂ψ of each particle propagator over K draws: the median over ψ's entries of
|mean| / std of one draw (its signal-to-noise ratio), and the mean cosine between one draw's gradient and moment
matching's. ``--start-scale s`` values everything from N(μ_0, s² Σ_0) (the search's ``search_start_scale``).

    .venv/bin/python scripts/research/probe_policy_value.py RUN_DIR --data PATH [--policy PATH] [--draws 5]
        [--particles 400] [--features 256] [--gradients K] [--start-scale s] [--threads 1] [--seed 0] [OVERRIDE ...]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch
from torch import Tensor

from qtl.bench import display_path
from qtl.bench.refit import loaded, refitted
from qtl.checkpoint import load_checkpoint
from qtl.gaussian import Gaussian
from qtl.propagation import MomentMatching, Particles


def main() -> None:
    """Refit the run's model; value the policy by moment matching and by each particle propagator; print JSON."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", type=Path)
    parser.add_argument("--data", type=Path, required=True, help="checkpoint whose data the model is fitted on")
    parser.add_argument("--policy", type=Path, help="checkpoint whose ψ is valued (default: --data's)")
    parser.add_argument("--draws", type=int, default=5, help="particle draws (fresh random numbers each)")
    parser.add_argument("--particles", type=int, default=400)
    parser.add_argument("--features", type=int, default=256, help="random Fourier features of pathwise sampling")
    parser.add_argument("--gradients", type=int, default=0, help="draws of ∂V/∂ψ per propagator (0: none)")
    parser.add_argument("--start-scale", type=float, default=1.0, help="value from N(μ_0, s² Σ_0)")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--seed", type=int, default=0, help="of the particles' draws")
    args, overrides = parser.parse_known_args()
    if args.draws < 1 or args.particles < 2 or args.gradients == 1 or args.gradients < 0:
        raise SystemExit("--draws must be >= 1, --particles >= 2 and --gradients 0 or >= 2")
    if not 0 < args.start_scale <= 1:
        raise SystemExit("--start-scale must be in (0, 1]")
    torch.set_num_threads(args.threads)

    run = loaded(args.run_dir, args.data, overrides)
    data_checkpoint = run.checkpoint
    policy_checkpoint = load_checkpoint(args.policy) if args.policy else data_checkpoint
    data, model = refitted(run)
    parts = run.parts
    task = parts.task
    start = Gaussian(parts.start.mean, parts.start.cov * args.start_scale**2)
    policy = parts.initial_policy()
    policy.load_state_dict(policy_checkpoint["policy"])

    variants: dict[str, dict] = {"marginal": {}, "pathwise": {"sampling": "pathwise"}}
    if task.kinematics is not None:
        variants |= {f"{name}_speed": {**kw, "integration": "speed", "kinematics": task.kinematics}
                     for name, kw in list(variants.items())}
    report = {"run": display_path(args.run_dir), "data_episode": data_checkpoint["episode"], "n": len(data),
              "policy_episode": policy_checkpoint["episode"], "start_scale": args.start_scale, "overrides": overrides}
    params = [p for p in policy.parameters() if p.requires_grad]

    def gradient(value: Tensor) -> Tensor:
        """∂V/∂ψ flattened."""
        return torch.cat([g.reshape(-1) for g in torch.autograd.grad(value, params)])

    moments = MomentMatching(model, policy, parts.reward, angle_dims=task.angle_dims, engine=parts.engine)
    propagators = {name: Particles(model, policy, parts.reward, angle_dims=task.angle_dims,
                                   num_particles=args.particles, num_features=args.features, expected_reward=False,
                                   seed=args.seed, engine=parts.engine, **settings)
                   for name, settings in variants.items()}
    if args.gradients:
        reference = gradient(moments.rollout(start, task.horizon).value)
        for name, particles in propagators.items():
            draws = torch.stack([gradient(particles.rollout(start, task.horizon, draw=d).value)
                                 for d in range(args.gradients)])
            report[f"{name}_gradient"] = {
                "snr_median": float((draws.mean(0).abs() / draws.std(0)).median()),
                "cosine_to_moment_matching": float(torch.nn.functional.cosine_similarity(
                    draws, reference[None], dim=1).mean()),
            }
    with torch.no_grad():
        report["moment_matching"] = float(moments.rollout(start, task.horizon).value)
        for name, particles in propagators.items():
            report[name] = [float(particles.rollout(start, task.horizon, draw=d).value)
                            for d in range(args.draws)]
        configured = parts.make_propagator(model, policy, parts.reward, angle_dims=task.angle_dims)
        if isinstance(configured, Particles):  # the run's own particles (with the overrides), and its search reward
            for name, reward in (("configured", None), ("configured_search_reward", configured.search_reward)):
                report[name] = [float(configured.rollout(start, task.horizon, draw=d, reward=reward).value)
                                for d in range(args.draws)]
    print(json.dumps(report))


if __name__ == "__main__":
    main()
