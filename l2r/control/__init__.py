"""DeepMind Control suite tasks with camera observations, as gymnasium environments.

Importing this package registers one id per task that DrQ-v2 reports on, named
`l2r/dmc-<domain>-<task>-v0` with the suite's own domain and task names (which may hold
underscores, never hyphens). dm_control, MuJoCo and OpenGL load only when an env is made:

    import gymnasium, l2r.control
    env = gymnasium.make("l2r/dmc-cartpole-swingup-v0")            # action_repeat=2, 84×84
    env = gymnasium.make("l2r/dmc-walker-walk-v0", with_state=True)  # pixels and the suite's state
"""

import gymnasium

# DrQ-v2's suite tasks (its cfgs/task/), as the suite names them.
TASKS = (
    ("acrobot", "swingup"),
    ("ball_in_cup", "catch"),
    ("cartpole", "balance"),
    ("cartpole", "balance_sparse"),
    ("cartpole", "swingup"),
    ("cartpole", "swingup_sparse"),
    ("cheetah", "run"),
    ("finger", "spin"),
    ("finger", "turn_easy"),
    ("finger", "turn_hard"),
    ("hopper", "hop"),
    ("hopper", "stand"),
    ("humanoid", "run"),
    ("humanoid", "stand"),
    ("humanoid", "walk"),
    ("pendulum", "swingup"),
    ("quadruped", "run"),
    ("quadruped", "walk"),
    ("reacher", "easy"),
    ("reacher", "hard"),
    ("walker", "run"),
    ("walker", "stand"),
    ("walker", "walk"),
)


def env_id(domain: str, task: str) -> str:
    """The gymnasium id of a suite task, e.g. `l2r/dmc-cartpole-swingup-v0`."""
    return f"l2r/dmc-{domain}-{task}-v0"


# The env ends its episodes itself (the suite's 1000 steps), so no max_episode_steps.
for _domain, _task in TASKS:
    gymnasium.register(id=env_id(_domain, _task), entry_point="l2r.control.env:ControlEnv", kwargs={"domain": _domain, "task": _task})
