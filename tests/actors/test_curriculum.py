"""The difficulty schedule of a training actor: its stages, its text form, and the episodes it starts."""

import pytest

from l2r.actors.actor import ActorConfig, episode_difficulty, make_env
from l2r.actors.curriculum import DifficultySchedule


def test_each_stage_holds_from_its_first_step_until_the_next():
    schedule = DifficultySchedule.parse("0:0, 1000:1, 5000:2")
    assert schedule.stages == ((0, 0), (1000, 1), (5000, 2))
    assert [schedule.at(s) for s in (0, 999, 1000, 4999, 5000, 10**9)] == [0, 0, 1, 1, 2, 2]
    assert str(schedule) == "0:0,1000:1,5000:2"
    assert DifficultySchedule.parse("0:2").at(123) == 2


@pytest.mark.parametrize("text, message", [
    ("", "starts at step 0"), ("10:1", "starts at step 0"), ("0:0,500:1,500:2", "must rise"),
    ("0:0,500:3", "0, 1 or 2"), ("0-1", "STEP:DIFFICULTY"), ("0:x", "STEP:DIFFICULTY"),
])
def test_a_bad_schedule_is_a_clear_error(text, message):
    with pytest.raises(ValueError, match=message):
        DifficultySchedule.parse(text)


def test_a_training_episode_starts_at_the_schedule_s_difficulty():
    config = ActorConfig(difficulty=1, action_repeat=2, difficulty_schedule=DifficultySchedule.parse("0:0,100:2"),
                         observation_noise=0.01, action_noise=0.01)
    env = make_env(config, seed=0)  # the options pass through the noise wrappers and the repeat
    for steps, expected in ((0, 0), (99, 0), (100, 2)):
        difficulty, options = episode_difficulty(config, steps)
        env.reset(seed=1, options=options)
        assert difficulty == env.unwrapped.difficulty == expected
        assert (len(env.unwrapped.obstacles) > 0) == (expected > 0)
    # Without a schedule the env keeps the configured difficulty.
    assert episode_difficulty(ActorConfig(difficulty=1), 10**6) == (1, None)


def test_a_resumed_actor_goes_on_with_the_schedule_where_its_place_in_the_run_left_it():
    config = ActorConfig(difficulty_schedule=DifficultySchedule.parse("0:0,100:2"), env_steps_before=60)
    assert [episode_difficulty(config, steps)[0] for steps in (0, 39, 40)] == [0, 0, 2]
