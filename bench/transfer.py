"""How far a trained policy carries from the MuJoCo body to OpenSim; prints one JSON line.

    python bench/transfer.py runs/NAME [--difficulty 0] [--action-repeat 3]

Runs the checkpoint's deterministic policy for one episode in `l2r/Run-v0` and one in
`l2r/RunOpenSim-v0` (difficulty 0 has nothing random in it, so one episode each says it), the way
`l2r eval` does, and reports both distances and their ratio. The issue's goal: the OpenSim
distance is at least half the MuJoCo one for a policy trained 30 minutes with `l2r up`.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch
from env_speed import cpu_flags, cpu_model  # this folder's: the same machine record as the speed figures

from l2r.evaluate import evaluate
from l2r.learner.checkpoint import load_checkpoint


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("checkpoint", type=Path, metavar="CHECKPOINT_OR_RUN_DIR")
    parser.add_argument("--difficulty", type=int, choices=(0, 1, 2), default=0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--action-repeat", type=int, default=3, help="0.01 s steps per action, as in training")
    args = parser.parse_args()
    checkpoint = load_checkpoint(args.checkpoint)
    torch.set_num_threads(1)
    policy = checkpoint.policy()
    out = {"checkpoint": str(checkpoint.path), "version": checkpoint.version, "updates": checkpoint.updates,
           "difficulty": args.difficulty, "seed": args.seed}
    for key, env_id in (("port", "l2r/Run-v0"), ("opensim", "l2r/RunOpenSim-v0")):
        start = time.perf_counter()
        (ret, distance, steps), = evaluate(policy, 1, args.seed, args.difficulty, args.action_repeat, env_id)
        out.update({f"{key}_distance_m": round(distance, 3), f"{key}_return": round(ret, 3), f"{key}_steps": steps,
                    f"{key}_seconds": round(time.perf_counter() - start, 1)})
    port = out["port_distance_m"]
    out["opensim_over_port"] = round(out["opensim_distance_m"] / port, 3) if port > 0 else None
    out["machine"], out["cpu_flags"] = cpu_model(), cpu_flags()
    print(json.dumps(out))


if __name__ == "__main__":
    main()
