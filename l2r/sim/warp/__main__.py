"""`python -m l2r.sim.warp`: compile the Warp kernels of `l2r/RunWarp-v0` for Warp's CPU device
into Warp's kernel cache (~/.cache/warp). `make setup` runs it once, so that the first Warp step
of a test or a run does not compile for minutes (about 4 on 2 cores with an empty cache; a second
with a warm one)."""

import time

import gymnasium
import numpy as np

import l2r.sim  # noqa: F401  (registers the environments)


def main() -> None:
    started = time.monotonic()
    worlds = gymnasium.make_vec("l2r/RunWarp-v0", num_envs=1, device="cpu")
    worlds.reset(seed=0)
    worlds.step(np.zeros((1, worlds.single_action_space.shape[0]), np.float32))
    worlds.close()
    print(f"l2r/RunWarp-v0: Warp's CPU kernels compiled or found in its cache in {time.monotonic() - started:.0f} s")


if __name__ == "__main__":
    main()
