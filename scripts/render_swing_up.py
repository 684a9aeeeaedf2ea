"""The README's frame strip: frames of a played episode side by side (the animated GIF is ``qtl-play``'s).

Plays the run's policy as ``qtl-play`` does (:func:`qtl.play.play`: the checkpoint after ``--episode``, from that
episode's own start unless ``--seed``), keeps the central ``--crop`` share of each frame's width, scales it and
writes ``--frames`` frames evenly spaced over the first ``--until`` steps as one PNG. The README's pictures:

    qtl-play RUN_DIR --scale 0.6 --out docs/img/swing_up.gif
    python scripts/render_swing_up.py RUN_DIR --out docs/img/swing_up_strip.png

where RUN_DIR holds the checkpoint of the full-scale cart-pole source run (seed 0) after its last episode, 24
(``docs/guide/play.md`` says how to get it).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from qtl.play import open_run, play
from qtl.video import Clip, frame_strip, write_png


def main() -> None:
    """Parse the arguments, play the episode, write the strip, print its path."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", type=Path, help="a run directory (with checkpoints/)")
    parser.add_argument("--out", type=Path, required=True, help="the strip, a .png")
    parser.add_argument("--episode", type=int, default=None, help="the checkpoint after episode N (default: newest)")
    parser.add_argument("--seed", type=int, default=None, help="the env's reset seed (default: the episode's own)")
    parser.add_argument("--frames", type=int, default=8, help="frames in the strip (default 8)")
    parser.add_argument("--until", type=int, default=20, help="spread them over the first N steps (default 20)")
    parser.add_argument("--scale", type=float, default=0.6, help="image scale (default 0.6, as the README's GIF)")
    parser.add_argument("--crop", type=float, default=0.45,
                        help="keep this central share of each frame's width (default 0.45)")
    args = parser.parse_args()
    run = open_run(args.run_dir, args.episode)
    played = play(run, args.seed)
    width = played.clip.frames.shape[2]
    keep = round(width * args.crop)
    left = (width - keep) // 2
    clip = Clip(played.clip.frames[:, :, left : left + keep].copy(), played.clip.fps).scaled(args.scale)
    path = write_png(args.out, frame_strip(clip, args.frames, args.until))
    print(f"{path} (return {played.episode.rewards.sum():.2f} over {played.episode.length} steps)")


if __name__ == "__main__":
    main()
