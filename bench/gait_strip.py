"""Draw how a trained policy moves: a stick-figure chronophotograph of one deterministic episode.

    python bench/gait_strip.py runs/NAME [--env-id l2r/RunOpenSim-v0] [--seconds 2] [--every 0.1] [--out docs/gait.png]

The figure is drawn from the body frames the simulator reports (each body's origin joined to its
parent's in the MuJoCo body's tree; OpenSim reports its bodies in the same order), so it shows
what the simulation did, not what a renderer makes of it. Below it: pelvis height and
the height of each foot over time. Prints one JSON line with the episode's figures.
"""

from __future__ import annotations

import argparse
import json

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import gymnasium  # noqa: E402

from l2r.learner.checkpoint import load_checkpoint  # noqa: E402
from l2r.policy import act  # noqa: E402
from l2r.sim import PORT_ID  # noqa: E402
from l2r.sim.env import STEP_SECONDS, RunEnv  # noqa: E402


def record(policy, env_id: str, seed: int, action_repeat: int) -> tuple[np.ndarray, float]:
    """Body positions (steps, bodies, 3) of one deterministic episode, and its distance."""
    env = gymnasium.make(env_id)
    obs, info = env.reset(seed=seed)
    frames = [info["body_pos"]]
    done = False
    while not done:
        action = act(policy, obs[None], deterministic=True)[0]
        for _ in range(action_repeat):
            obs, _, terminated, truncated, info = env.step(action)
            frames.append(info["body_pos"])
            done = terminated or truncated
            if done:
                break
    env.close()
    return np.array(frames), info["distance"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("checkpoint", help="checkpoint file or run directory")
    parser.add_argument("--seconds", type=float, default=2.0, help="simulated time drawn in the strip")
    parser.add_argument("--every", type=float, default=0.1, help="seconds between drawn figures")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--env-id", default=PORT_ID, help="the simulator: l2r/Run-v0 or l2r/RunOpenSim-v0")
    parser.add_argument("--action-repeat", type=int, help="default: what the checkpoint says training used")
    parser.add_argument("--out", default="docs/gait.png")
    args = parser.parse_args()

    ckpt = load_checkpoint(args.checkpoint)
    pos, distance = record(ckpt.policy(), args.env_id, args.seed, args.action_repeat or ckpt.action_repeat or 3)
    m = RunEnv().model  # the skeleton: which body hangs from which
    names = [m.body(i).name for i in range(m.nbody)]
    bones = [(int(m.body_parentid[i]), i) for i in range(1, m.nbody) if m.body_parentid[i] != 0]
    feet = {side: names.index(f"toes_{side}") for side in "rl"}
    t = np.arange(len(pos)) * STEP_SECONDS

    fig, (strip, heights) = plt.subplots(2, 1, figsize=(12, 7), gridspec_kw={"height_ratios": [2, 1]})
    shown = np.arange(0, min(len(pos), int(args.seconds / STEP_SECONDS) + 1), round(args.every / STEP_SECONDS))
    for k, step in enumerate(shown):
        shade = plt.cm.viridis(k / max(1, len(shown) - 1))
        for parent, child in bones:
            right = names[child].endswith("_r")
            strip.plot(pos[step, [parent, child], 0], pos[step, [parent, child], 1], color=shade,
                       lw=2.0 if right else 1.0, alpha=0.9 if right else 0.5)
    strip.axhline(0.0, color="0.4", lw=1)
    strip.set_aspect("equal")
    strip.set_xlabel("x (m)")
    strip.set_ylabel("y (m)")
    strip.set_title(f"{ckpt.path.parent.parent.name}, version {ckpt.version}, in {args.env_id}: the first {args.seconds:g} s, "
                    f"a figure every {args.every:g} s (right leg thick); episode: {distance:.1f} m in "
                    f"{t[-1]:.2f} s", fontsize=10)
    heights.plot(t, pos[:, names.index("pelvis"), 1], label="pelvis")
    for side, body in feet.items():
        heights.plot(t, pos[:, body, 1], label=f"toes, {'right' if side == 'r' else 'left'}", lw=0.8)
    heights.set_xlabel("time (s)")
    heights.set_ylabel("height (m)")
    heights.legend(loc="upper right", fontsize=8)
    heights.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(args.out, dpi=100)

    pelvis_y = pos[:, names.index("pelvis"), 1]
    print(json.dumps({"checkpoint": str(ckpt.path), "version": ckpt.version, "env_id": args.env_id, "distance": distance,
                      "seconds": float(t[-1]), "mean_speed": distance / max(t[-1], 1e-9),
                      "pelvis_height_min": float(pelvis_y.min()), "pelvis_height_max": float(pelvis_y.max()),
                      "plot": args.out}))


if __name__ == "__main__":
    main()
