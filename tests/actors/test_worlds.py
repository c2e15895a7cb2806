"""The worlds an actor steps: a list of single envs and a gymnasium VectorEnv give the actor the
same episodes and the same experience chunks."""

from __future__ import annotations

import dataclasses
import signal
import subprocess
import sys
import threading
import uuid

import gymnasium
import numpy as np
import pytest
import torch
import zenoh
from gymnasium.vector import AutoresetMode, SyncVectorEnv

from l2r.actors.__main__ import parse_settings
from l2r.actors.actor import Actor, ActorConfig, main, make_worlds, registers_vector_env
from l2r.actors.curriculum import DifficultySchedule
from l2r.actors.worlds import EnvList, VectorWorlds
from l2r.config import StartupFailure, UsageError
from l2r.protocol import Keys, decode, encode, session_config
from l2r.sim.randomize import Randomization
from tests.conftest import ROOT, free_port, wait_for

FALLER = "tests.actors.standin:Faller-v0"


class Counter(gymnasium.Env):
    """Counts its steps, one reward each; falls (terminated, `info["fell"]`) at step ``length``. Draws nothing."""

    observation_space = gymnasium.spaces.Box(0.0, np.inf, (1,), np.float32)
    action_space = gymnasium.spaces.Box(0.0, 1.0, (1,), np.float32)

    def __init__(self, length: int):
        self.length, self.t = length, 0

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        return np.zeros(1, np.float32), {"distance": 0.0}

    def step(self, action):
        self.t += 1
        fell = self.t >= self.length
        info = {"distance": float(self.t), **({"fell": True} if fell else {})}
        return np.full(1, self.t, np.float32), 1.0, fell, False, info


def counters(mode: AutoresetMode) -> SyncVectorEnv:
    return SyncVectorEnv([lambda: Counter(3), lambda: Counter(5)], autoreset_mode=mode)


def test_a_repeated_action_ends_an_episode_where_it_ends_and_the_next_begins_after_the_repeats():
    """Two worlds falling at steps 3 and 5, each action taken twice: the reward is summed up to
    the fall, the fall's observation and info are the episode's last, and the next episode
    starts where the world's left-over repeat took it (the env reset it in that repeat)."""
    worlds = VectorWorlds(counters(AutoresetMode.SAME_STEP), repeat=2)
    assert [obs[0] for obs, _ in worlds.reset([7, 8], None)] == [0.0, 0.0]
    actions = np.zeros((2, 1), np.float32)
    assert [(s[0][0], s[1], s[2], s[4]["inner_steps"]) for s in worlds.step(actions)] == [(2, 2, False, 2)] * 2
    fell, running = worlds.step(actions)
    assert (fell[0][0], fell[1], fell[2], fell[3]) == (3, 1, True, False)
    assert (fell[4]["distance"], fell[4]["inner_steps"], fell[4]["fell"]) == (3, 1, True)
    assert (running[0][0], running[1], running[2]) == (4, 2, False)
    [(obs, info)] = worlds.reset_worlds([0], [9], None)
    assert obs[0] == 1.0 and info["distance"] == 1.0


@pytest.mark.parametrize("mode", [AutoresetMode.SAME_STEP, AutoresetMode.DISABLED])
def test_a_vector_env_steps_its_worlds_as_the_single_envs_step(mode):
    single, vector = EnvList([Counter(3), Counter(5)]), VectorWorlds(counters(mode))
    assert [o[0] for o, _ in single.reset([1, 2], None)] == [o[0] for o, _ in vector.reset([1, 2], None)]
    for _ in range(12):
        steps, vector_steps = single.step(np.zeros((2, 1), np.float32)), vector.step(np.zeros((2, 1), np.float32))
        assert [(s[0][0], *s[1:]) for s in steps] == [(s[0][0], *s[1:]) for s in vector_steps]  # infos too
        ended = [i for i, (_, _, terminated, truncated, _) in enumerate(steps) if terminated or truncated]
        assert ([o[0] for o, _ in single.reset_worlds(ended, ended, None)]
                == [o[0] for o, _ in vector.reset_worlds(ended, ended, None)])


def test_a_vector_env_registered_by_a_module_is_found_as_gymnasium_make_finds_it():
    assert registers_vector_env("tests.actors.standin:InstantWorlds-v0")
    assert not registers_vector_env("tests.actors.standin:StandIn-v0")  # a single env
    assert not registers_vector_env("tests.actors.nowhere:InstantWorlds-v0")


def test_an_unfit_autoreset_mode_is_refused():
    with pytest.raises(ValueError, match="autoreset mode"):
        VectorWorlds(counters(AutoresetMode.NEXT_STEP))


def sent(config: ActorConfig, steps: int) -> tuple[list[bytes], list]:
    """The chunks (their epoch, the process's start, set to 0) and episode summaries (time 0)
    that an actor of ``config`` sends in ``steps`` steps."""
    with zenoh.open(session_config(listen=[f"tcp/127.0.0.1:{free_port()}"])) as session:
        keys, chunks, episodes = Keys(config.run), [], []
        session.declare_subscriber(keys.experience_of_shard(0), lambda s: chunks.append(decode(s.payload)))
        session.declare_subscriber(keys.all_episodes, lambda s: episodes.append(decode(s.payload)))
        actor = Actor(config, session)
        for _ in range(steps):
            actor.step()
        actor.close()
        assert wait_for(lambda: len(chunks) == actor.chunks_sent and len(episodes) == actor.episodes)
    return ([encode(dataclasses.replace(c, epoch=0)) for c in chunks],
            [dataclasses.replace(e, time=0.0) for e in episodes])


def test_an_actor_on_a_vector_env_sends_the_chunks_and_episodes_of_one_on_single_envs():
    """Falls and time limits within repeated actions, each episode on its own seed, final
    observations: the same bytes whether the actor steps a list of envs or a SyncVectorEnv of them
    (resetting its worlds itself, with their seeds)."""
    config = ActorConfig(run=f"test-worlds-{uuid.uuid4().hex[:8]}", env_id=FALLER, num_envs=3, action_repeat=3,
                         chunk_size=8, chunk_delay=60.0, resend_buffer_mb=0, max_speed=0.0)
    chunks, episodes = sent(dataclasses.replace(config, vector_env=False), 40)
    assert len(episodes) >= 10 and {e.env_id for e in episodes} == {0, 1, 2}
    assert len({e.seed for e in episodes}) == len(episodes)
    assert {e.length for e in episodes} >= {40} and min(e.length for e in episodes) < 40  # truncated, and falls
    assert sent(dataclasses.replace(config, vector_env=True), 40) == (chunks, episodes)


def test_an_actor_seeds_each_runwarp_world_s_episodes_as_it_seeds_single_envs():
    """l2r/RunWarp-v0's worlds under an actor (autoreset DISABLED: the actor resets each finished
    world) take the actor's episode seeds and its difficulty schedule: the same chunks and
    episodes, byte for byte, as one-world envs stepped one by one, obstacles from 50 steps on."""
    config = ActorConfig(run=f"test-warp-seeds-{uuid.uuid4().hex[:8]}", env_id="l2r/RunWarp-v0", num_envs=2,
                         action_repeat=3, chunk_size=16, chunk_delay=60.0, resend_buffer_mb=0, device="cpu",
                         difficulty_schedule=DifficultySchedule.parse("0:0,50:2"))
    chunks, episodes = sent(dataclasses.replace(config, vector_env=None), 100)
    assert {e.difficulty for e in episodes} == {0, 2} and len({e.seed for e in episodes}) == len(episodes)
    assert sent(dataclasses.replace(config, vector_env=False), 100) == (chunks, episodes)


def test_randomised_runwarp_worlds_under_an_actor_are_its_randomised_single_envs():
    """With every randomisation on, each world's episodes draw the bodies a one-world env draws
    from the same seeds: the same chunks and episodes, byte for byte."""
    randomize = Randomization(strength=0.1, tendon_slack=0.02, fiber_length=0.02, mass=0.1, contact_stiffness=0.2,
                              contact_damping=0.2, friction=0.2, delay=0.5)
    config = ActorConfig(run=f"test-warp-random-{uuid.uuid4().hex[:8]}", env_id="l2r/RunWarp-v0", num_envs=2,
                         action_repeat=3, chunk_size=16, chunk_delay=60.0, resend_buffer_mb=0, device="cpu",
                         randomize=randomize)
    chunks, episodes = sent(dataclasses.replace(config, vector_env=None), 60)
    assert len(episodes) >= 2
    assert sent(dataclasses.replace(config, vector_env=False), 60) == (chunks, episodes)
    assert sent(dataclasses.replace(config, vector_env=None, randomize=Randomization()), 60)[0] != chunks


def test_runwarp_worlds_tell_the_episode_logger_their_obstacles_as_single_envs_do():
    config = ActorConfig(env_id="l2r/RunWarp-v0", num_envs=2, difficulty=2, device="cpu")
    courses = []
    for vector_env in (None, False):
        worlds = make_worlds(dataclasses.replace(config, vector_env=vector_env), [7, 8])
        worlds.reset([7, 8], None)
        courses.append([worlds.obstacles(i) for i in range(2)])
        worlds.close()
    assert courses[0] == courses[1] and all(len(course) == 3 for course in courses[0])


@pytest.mark.slow
def test_an_actor_steps_runwarp_worlds_in_one_call_and_its_replay_shard_stores_their_chunks(tmp_path):
    """A real actor on l2r/RunWarp-v0 (Warp's CPU device, its kernels cached on disk by make
    setup) feeding a real replay shard: the worlds' chunks are stored without gaps, and any
    episode that ended did so with the runner's lengths and distances."""
    keys = Keys(f"test-warp-actor-{uuid.uuid4().hex[:8]}")
    replay = f"tcp/127.0.0.1:{free_port()}"
    logs = {name: tmp_path / f"{name}.log" for name in ("replay", "actor")}
    with open(logs["replay"], "wb") as out:
        procs = [subprocess.Popen([sys.executable, "-m", "l2r.replay", "--run", keys.run, "--listen", replay,
                                   "--capacity", "100000", "--min-size", "1", "--stats-interval", "0.3"],
                                  cwd=ROOT, stdout=out, stderr=subprocess.STDOUT)]
    stats, episodes = {}, []

    def text() -> str:
        return "\n".join(f"--- {name}\n{path.read_text()[-3000:]}" for name, path in logs.items() if path.exists())

    try:
        with zenoh.open(session_config(connect=[replay])) as session:
            session.declare_subscriber(keys.all_stats,
                                       lambda s: stats.update({str(s.key_expr): decode(s.payload).values}))
            session.declare_subscriber(keys.all_episodes, lambda s: episodes.append(decode(s.payload)))
            assert wait_for(lambda: keys.stats("replay", 0) in stats, 30), text()
            with open(logs["actor"], "wb") as out:
                procs.append(subprocess.Popen(
                    [sys.executable, "-m", "l2r.actors", "--run", keys.run, "--connect", replay,
                     "--env-id", "l2r/RunWarp-v0", "--num-envs", "3", "--chunk-size", "4", "--stats-interval", "0.3",
                     "--random-steps", "100000", "--device", "cpu"], cwd=ROOT, stdout=out, stderr=subprocess.STDOUT))
            # Chunks, not episodes: a random episode on Warp's CPU device takes tens of seconds.
            assert wait_for(lambda: stats[keys.stats("replay", 0)]["inserted"] >= 4 * 3, 120), f"{stats}\n{text()}"
            actor = stats[keys.stats("actor", 0)]
            shard = stats[keys.stats("replay", 0)]
    finally:
        for proc in reversed(procs):
            proc.send_signal(signal.SIGTERM)
        for proc in reversed(procs):
            assert proc.wait(timeout=30) == 0, text()
    assert "3 x l2r/RunWarp-v0 as one vector env on cpu" in logs["actor"].read_text()
    assert actor["num_envs"] == 3 and actor["blowups"] == 0
    assert shard["gaps"] == 0 and shard["rejected"] == 0
    for e in episodes:  # random excitations: the runner falls within a second or two, near where it stood
        assert 0 < e.length < 1000 and abs(e.distance) < 2.0, e


@pytest.mark.parametrize("flags", [["--observation-noise", "0.1"], ["--action-noise", "0.1"]])
def test_what_l2r_runwarp_s_own_vector_env_cannot_take_is_refused_with_the_way_out(flags):
    with pytest.raises(UsageError, match="add --vector-env off"):
        parse_settings(["--env-id", "l2r/RunWarp-v0", *flags])
    assert parse_settings(["--env-id", "l2r/RunWarp-v0", "--vector-env", "off", *flags]).actor().vector_env is False


@pytest.mark.skipif(torch.cuda.is_available(), reason="a machine with CUDA serves --device cuda")
def test_device_cuda_without_cuda_is_a_start_up_failure_not_a_silent_cpu_run():
    stopped = threading.Event()
    stopped.set()
    with pytest.raises(StartupFailure, match="--device cuda, but torch"):
        main(ActorConfig(env_id=FALLER, num_envs=1, device="cuda"), session_config(), stopped)
