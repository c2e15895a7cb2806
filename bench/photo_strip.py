"""Draw how a trained photo tuner works: a held-out problem's input, the image after each of the
policy's queries, and the goal, each with its PSNR to the goal.

    python bench/photo_strip.py runs/NAME [--problem 0] [--out docs/photo_strip.png]

The problems are `l2r photo compare`'s (crops of the held-out photos, goals made with hidden
random parameters, seeds 0, 1, ...). Prints one JSON line with the PSNR of each image.
"""

from __future__ import annotations

import argparse
import json

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from l2r.learner.checkpoint import load_checkpoint  # noqa: E402
from l2r.photo import tune  # noqa: E402
from l2r.photo.env import psnr_db  # noqa: E402


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("checkpoint", help="a checkpoint file, best.pt, or an l2r up run directory")
    p.add_argument("--problem", type=int, default=0, help="which held-out problem (its seed)")
    p.add_argument("--out", default="docs/photo_strip.png")
    args = p.parse_args()

    problem = tune.held_out_problems(1, seed=args.problem)[0]
    trace = tune.policy_tune(load_checkpoint(args.checkpoint).policy(), problem)
    images = [problem.source, *(tune.finished(problem, a) for a in trace.actions), problem.goal]
    titles = (["input"] + [f"query {i + 1}" for i in range(len(trace.actions))] + ["goal"])
    psnrs = [float(psnr_db(image[None], problem.goal[None])[0]) for image in images[:-1]]

    fig, axes = plt.subplots(1, len(images), figsize=(1.6 * len(images), 2.0))
    for ax, image, title, psnr in zip(axes, images, titles, [*psnrs, None]):
        ax.imshow(np.clip(image.transpose(1, 2, 0), 0.0, 1.0))
        ax.set_title(title if psnr is None else f"{title}\n{psnr:.1f} dB", fontsize=8)
        ax.axis("off")
    fig.suptitle(f"{problem.name}: the tuner's queries, PSNR to the goal", fontsize=9)
    fig.tight_layout()
    fig.savefig(args.out, dpi=110)
    print(json.dumps({"bench": "photo_strip", "problem": problem.name, "psnr_db": [round(v, 2) for v in psnrs],
                      "out": args.out}))


if __name__ == "__main__":
    main()
