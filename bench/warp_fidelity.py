"""The Warp runner on a GPU against OpenSim, for machines where the two cannot be installed together.

    python bench/warp_fidelity.py record --device cuda --out warp_cuda.npz   # beside the GPU
    python bench/warp_fidelity.py judge warp_cuda.npz                        # where OpenSim is

`record` drives `l2r/RunWarp-v0` (one world) on the Warp device with the dynamic validator's
excitation sequences (`l2r.sim.dynamics`: zero excitation until the fall, all at 0.5, a uniform
draw every step from seed 0), saves its trajectories, and prints one JSON line comparing them
with the numba port's (`l2r/Run-v0`, float64) on the same machine, in the validator's figures.
`judge` drives live OpenSim with the saved excitations and prints the validator's figures and
targets for the saved trajectories against it (`l2r validate --dynamics --env-id l2r/RunWarp-v0`
in two halves), one JSON line after the table.
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from l2r.sim import dynamics

FIELDS = ("observation", "activation", "tendon_force", "foot_force")


def save(path: str, device: str, sequences: dict[str, np.ndarray], trajectories: dict[str, dynamics.Trajectory]) -> None:
    arrays = {"labels": np.array(list(sequences)), "device": np.array(device)}
    for i, (label, excitations) in enumerate(sequences.items()):
        arrays[f"{i}_excitations"] = excitations
        arrays[f"{i}_fall_step"] = np.array(trajectories[label].fall_step or -1)
        for field in FIELDS:
            arrays[f"{i}_{field}"] = getattr(trajectories[label], field)
    np.savez_compressed(path, **arrays)


def load(path: str) -> tuple[str, dict[str, np.ndarray], dict[str, dynamics.Trajectory]]:
    with np.load(path) as f:
        sequences, trajectories = {}, {}
        for i, label in enumerate(f["labels"].tolist()):
            sequences[label] = f[f"{i}_excitations"]
            fall = int(f[f"{i}_fall_step"])
            trajectories[label] = dynamics.Trajectory(*(f[f"{i}_{field}"] for field in FIELDS), fall if fall >= 0 else None)
        return str(f["device"]), sequences, trajectories


def record(args: argparse.Namespace) -> dict:
    import warp as wp

    import l2r.sim.warp  # noqa: F401  (Warp logs warnings alone: stdout is the JSON line)

    wp.set_device(args.device)  # the one-world env runs on Warp's default device
    sequences = dynamics.excitation_sequences(args.seed)
    ours = {label: dynamics.rollout("l2r/RunWarp-v0", u) for label, u in sequences.items()}
    save(args.out, str(wp.get_device()), sequences, ours)
    port = {label: dynamics.compare(ours[label], dynamics.rollout("l2r/Run-v0", u)) for label, u in sequences.items()}
    return {"bench": "warp_fidelity", "against": "l2r/Run-v0", "device": str(wp.get_device()),
            "device_name": wp.get_device().name, "rollouts": port}


def judge(args: argparse.Namespace) -> dict:
    device, sequences, ours = load(args.trajectories)
    rollouts = {}
    for label, excitations in sequences.items():
        print(f"rollout '{label}': {len(excitations)} steps in OpenSim", file=sys.stderr)
        rollouts[label] = dynamics.compare(ours[label], dynamics.rollout("l2r/RunOpenSim-v0", excitations))
    report = {"rollouts": rollouts, "targets_met": dynamics.targets_met(rollouts)}
    print(dynamics.format_table(report), file=sys.stderr)
    return {"bench": "warp_fidelity", "against": "l2r/RunOpenSim-v0", "device": device, **report}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest="command", required=True)
    rec = commands.add_parser("record", help="drive l2r/RunWarp-v0 on a Warp device and save its trajectories")
    rec.add_argument("--device", default="cuda", help="Warp device: cuda, cuda:N or cpu")
    rec.add_argument("--seed", type=int, default=0, help="seed of the random excitations")
    rec.add_argument("--out", required=True, help="the .npz file to write")
    jud = commands.add_parser("judge", help="compare saved trajectories with live OpenSim")
    jud.add_argument("trajectories", help="a file `record` wrote")
    args = parser.parse_args()
    print(json.dumps(record(args) if args.command == "record" else judge(args)))


if __name__ == "__main__":
    main()
