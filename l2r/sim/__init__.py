"""The Learning to Run body in MuJoCo and its gymnasium environment.

Importing this package registers `l2r/Run-v0`; MuJoCo loads only when an env is made:

    import gymnasium, l2r.sim
    env = gymnasium.make("l2r/Run-v0", difficulty=2)
"""

import gymnasium

# RunEnv truncates at 1000 steps itself, so no max_episode_steps (no second TimeLimit).
gymnasium.register(id="l2r/Run-v0", entry_point="l2r.sim.env:RunEnv")
