"""The blow-up guard: a step faster than any runner ends the episode instead of paying out."""

from l2r.actors.actor import blew_up


def test_speeds_a_runner_can_reach_pass_and_blow_ups_do_not():
    three_steps = {"inner_steps": 3}
    assert not blew_up(0.3, three_steps, max_speed=20.0)  # 10 m/s over 0.03 s
    assert not blew_up(-0.3, three_steps, max_speed=20.0)
    assert blew_up(58.5, {"inner_steps": 1}, max_speed=20.0)  # seen in the runner: 58 m in 0.01 s
    assert blew_up(-2.9, three_steps, max_speed=20.0)
    assert blew_up(0.5, {}, max_speed=20.0)  # 50 m/s in one step
    assert not blew_up(1e9, three_steps, max_speed=0.0)  # off
