"""Render a finished run's final policy on its own env: an animated GIF and a frame strip (README, docs).

Loads the run's newest checkpoint (the policy that ran its last episode), runs one episode from the env's
seeded reset with ``render_mode="rgb_array"`` and writes ``<out>.gif`` (every ``--every``-th frame) and
``<out>_strip.png`` (``--strip`` frames side by side, evenly spaced over the episode).

    python scripts/render_swing_up.py RUN_DIR --out docs/img/swing_up
"""

from __future__ import annotations

import argparse
from pathlib import Path

import gymnasium
import numpy as np
from PIL import Image

from qtl.runs import load_run


def frames_of(run_dir: Path, seed: int) -> tuple[list[np.ndarray], float]:
    """The rendered frames of one episode of the run's final policy, and its return."""
    run = load_run(run_dir)
    act, task = run.parts.actor(run.policy()), run.parts.task
    env = gymnasium.make(task.env_id, render_mode="rgb_array", **task.env_kwargs)
    obs, _ = env.reset(seed=seed, options=task.reset_options)
    frames, total = [env.render()], 0.0
    for _ in range(task.horizon):
        action = np.clip(act(obs), -task.action_bound, task.action_bound).astype(env.action_space.dtype)
        obs, _, terminated, truncated, _ = env.step(action)
        total += float(task.reward(obs))
        frames.append(env.render())
        if terminated or truncated:
            break
    env.close()
    return frames, total


def main() -> None:
    """Parse the arguments, render, write the GIF and the strip, print their paths."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", type=Path, help="a finished run directory (with checkpoints/)")
    parser.add_argument("--out", type=Path, required=True, help="output stem: <out>.gif and <out>_strip.png")
    parser.add_argument("--seed", type=int, default=0, help="the env's reset seed (default 0)")
    parser.add_argument("--every", type=int, default=1, help="keep every k-th frame in the GIF (default 1)")
    parser.add_argument("--strip", type=int, default=8, help="frames in the strip (default 8)")
    parser.add_argument("--scale", type=float, default=0.5, help="image scale (default 0.5)")
    parser.add_argument("--crop", type=float, default=1.0,
                        help="keep this central share of each frame's width (default 1: the whole frame)")
    parser.add_argument("--strip-until", type=int, default=None,
                        help="spread the strip's frames over the first N steps (default: the whole episode)")
    args = parser.parse_args()
    frames, total = frames_of(args.run_dir, args.seed)
    images = [Image.fromarray(f) for f in frames]
    width = int(images[0].width * args.crop)
    left = (images[0].width - width) // 2
    images = [im.crop((left, 0, left + width, im.height)) for im in images]
    size = (int(images[0].width * args.scale), int(images[0].height * args.scale))
    images = [im.resize(size, Image.LANCZOS) for im in images]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    gif = args.out.with_suffix(".gif")
    step_s = 0.1 * args.every
    gif_frames = [im.convert("P", palette=Image.ADAPTIVE, colors=32) for im in images[:: args.every]]
    gif_frames[0].save(gif, save_all=True, append_images=gif_frames[1:], duration=int(1000 * step_s), loop=0,
                       optimize=True)
    last = len(images) - 1 if args.strip_until is None else min(args.strip_until, len(images) - 1)
    picks = np.linspace(0, last, args.strip).round().astype(int)
    strip = Image.new("RGB", (size[0] * len(picks), size[1]), "white")
    for k, index in enumerate(picks):
        strip.paste(images[index], (k * size[0], 0))
    strip_path = args.out.parent / f"{args.out.name}_strip.png"
    strip.save(strip_path, optimize=True)
    print(f"{gif} {strip_path} (return {total:.1f} over {len(frames) - 1} steps)")


if __name__ == "__main__":
    main()
