"""The Learning to Run body in MuJoCo and its gymnasium environment.

Importing this package registers `l2r/Run-v0` (MuJoCo), `l2r/RunOpenSim-v0` (the same
environment on OpenSim 4.6, the 2017 simulator; `pip install 'l2r[opensim]'`) and
`l2r/RunWarp-v0` (MuJoCo Warp, N worlds at once through `gymnasium.make_vec`). The simulator
loads only when an env is made:

    import gymnasium, l2r.sim
    env = gymnasium.make("l2r/Run-v0", difficulty=2)
"""

import gymnasium

PORT_ID = "l2r/Run-v0"
OPENSIM_ID = "l2r/RunOpenSim-v0"
WARP_ID = "l2r/RunWarp-v0"
RANDOMIZED_IDS = (PORT_ID, WARP_ID)
"""The envs that take `randomize` (l2r.sim.randomize): OpenSim's body is the one judged, as it is."""


def randomize_refusal(env_id: str) -> str | None:
    """Why `env_id` takes no randomisation, or None where it does."""
    if env_id in RANDOMIZED_IDS:
        return None
    return f"randomisation is {' and '.join(RANDOMIZED_IDS)}'s, not {env_id}'s"

# The envs truncate at 1000 steps themselves, so no max_episode_steps (no second TimeLimit).
gymnasium.register(id=PORT_ID, entry_point="l2r.sim.env:RunEnv")
gymnasium.register(id=OPENSIM_ID, entry_point="l2r.sim.opensim_env:RunOpenSimEnv")
gymnasium.register(id=WARP_ID, entry_point="l2r.sim.warp.env:RunWarpEnv",
                   vector_entry_point="l2r.sim.warp.env:RunWarpVectorEnv")
