"""The difficulty schedule of a training actor: its stages, its text form, and the episodes it starts."""

import pytest

from l2r.actors.actor import ActorConfig, course_of, episode_difficulty, make_env
from l2r.actors.curriculum import DISTANCE_WINDOW, Course, DifficultySchedule, Reach


def test_each_stage_holds_from_its_first_step_until_the_next():
    schedule = DifficultySchedule.parse("0:0, 1000:1, 5000:2")
    assert schedule.stages == ((0, 0), (1000, 1), (5000, 2))
    course = Course(schedule)
    assert [course.difficulty(s) for s in (0, 999, 1000, 4999, 5000, 10**9)] == [0, 0, 1, 1, 2, 2]
    assert str(schedule) == "0:0,1000:1,5000:2"
    assert Course(DifficultySchedule.parse("0:2")).difficulty(123) == 2


def test_a_distance_stage_begins_once_the_last_episodes_of_the_stage_before_averaged_that_far():
    schedule = DifficultySchedule.parse("0:0,6m:2,2000:1")
    assert schedule.stages == ((0, 0), (Reach(6.0), 2), (2000, 1)) and str(schedule) == "0:0,6m:2,2000:1"
    course = Course(schedule)
    for _ in range(DISTANCE_WINDOW - 1):
        course.record(0, 7.0)
    assert course.difficulty(10**6) == 0  # not yet a whole window of episodes, and no step count stands in
    course.record(0, 5.0 - 6 * DISTANCE_WINDOW)  # one fall drags the mean below 6 m
    assert course.difficulty(10**6) == 0
    for _ in range(DISTANCE_WINDOW):
        course.record(0, 6.0)
    assert course.difficulty(1500) == 2
    course.record(2, -1.0)  # a stage once entered is kept, whatever its own episodes run
    course.record(0, -1.0)  # an episode begun before the move counts for no stage
    assert course.difficulty(1999) == 2 and list(course.recent) == [-1.0]
    assert course.difficulty(2000) == 1  # the stage after it comes at its step count, as ever


@pytest.mark.parametrize("text, message", [
    ("", "starts at step 0"), ("10:1", "starts at step 0"), ("0:0,500:1,500:2", "must rise"),
    ("0:0,500:3", "0, 1 or 2"), ("0-1", "STEP:DIFFICULTY"), ("0:x", "STEP:DIFFICULTY"),
    ("0:0,6:x", "STEP:DIFFICULTY"), ("0:0,far:2", "an env step \\(200000\\) or a distance \\(6m\\)"),
    ("0:0,6.5:2", "distance ends with m"), ("0:0,nanm:2", "a number of metres"),
])
def test_a_bad_schedule_is_a_clear_error(text, message):
    with pytest.raises(ValueError, match=message):
        DifficultySchedule.parse(text)


def test_a_training_episode_starts_at_the_schedule_s_difficulty():
    config = ActorConfig(difficulty=1, action_repeat=2, difficulty_schedule=DifficultySchedule.parse("0:0,100:2"),
                         observation_noise=0.01, action_noise=0.01)
    env = make_env(config, seed=0)  # the options pass through the noise wrappers and the repeat
    course = course_of(config)
    for steps, expected in ((0, 0), (99, 0), (100, 2)):
        difficulty, options = episode_difficulty(config, course, steps)
        env.reset(seed=1, options=options)
        assert difficulty == env.unwrapped.difficulty == expected
        assert (len(env.unwrapped.obstacles) > 0) == (expected > 0)
    # Without a schedule the env keeps the configured difficulty.
    assert course_of(ActorConfig(difficulty=1)) is None
    assert episode_difficulty(ActorConfig(difficulty=1), None, 10**6) == (1, None)


def test_a_resumed_actor_goes_on_with_the_schedule_where_its_place_in_the_run_left_it():
    config = ActorConfig(difficulty_schedule=DifficultySchedule.parse("0:0,100:2"), env_steps_before=60)
    assert [course_of(config).difficulty(steps) for steps in (0, 39, 40)] == [0, 0, 2]
