"""What logging a camera task's episodes costs its actor: bytes per frame, CPU per frame.

One episode of a camera task (84 x 84 frames, random actions) stepped twice: unlogged, for the
env's CPU time per step (the whole process's clock: the renderer's threads count), then logged
through ``EpisodeLogger`` as an actor of that task logs it (frames as PNG on the writer thread);
then the same frames PNG-encoded again alone. Logging's CPU time comes from per-thread clocks:
``log_step`` on the stepping thread and the writer thread's whole time (PNG, Step, MCAP, zstd).

Prints one JSON line: ``file_bytes_per_step`` (the whole file over its steps), ``png_bytes_per_frame``,
``raw_bytes_per_frame``, ``png_encode_ms`` (one frame, alone), ``writer_ms_per_step``,
``log_step_us``, ``env_step_ms``, ``cost_fraction_logged`` (logging CPU over env CPU, for a
logged episode) and ``cost_fraction_every_10`` (logging every 10th episode, as l2r up does).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from l2r.actors.actor import make_task
from l2r.actors.episode_log import EpisodeLogger, LogPolicy
from l2r.episodes.encode import png


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env-id", default="l2r/dmc-walker-walk-v0")
    parser.add_argument("--steps", type=int, default=300, help="env steps of the logged episode")
    args = parser.parse_args()

    env = make_task(args.env_id)
    rng = np.random.default_rng(0)
    actions = rng.random((args.steps, *env.action_space.shape)).astype(np.float32)
    clock = time.thread_time
    env.reset(seed=0)
    start = time.process_time()
    for action in actions:
        env.step(action)
    env_cpu = time.process_time() - start
    with tempfile.TemporaryDirectory() as directory:
        logger = EpisodeLogger(directory, "bench", actor_id=0, policy=LogPolicy(every=1), with_body=False)
        obs, _ = env.reset(seed=0)
        recorder = logger.begin_episode({"env_id": args.env_id, "seed": 0})
        log_cpu = 0.0
        frames = []
        for action in actions:
            obs, reward, terminated, truncated, info = env.step(action)
            start = clock()
            recorder.log_step(obs, action, reward, info)
            log_cpu += clock() - start
            frames.append(obs["pixels"])
        recorder.end({"return": 0.0})
        logger.close()
        file_bytes = sum(p.stat().st_size for p in Path(directory).glob("*.mcap"))
    env.close()

    start = clock()
    sizes = [len(png(frame)) for frame in frames]
    png_cpu = (clock() - start) / len(frames)
    steps = len(frames)
    logging = log_cpu / steps + logger.stats["writer_cpu_s"] / steps
    print(json.dumps({
        "env_id": args.env_id, "steps": steps, "frame_shape": list(frames[0].shape),
        "file_bytes_per_step": round(file_bytes / steps), "png_bytes_per_frame": round(float(np.mean(sizes))),
        "raw_bytes_per_frame": int(frames[0].nbytes), "png_encode_ms": round(1e3 * png_cpu, 3),
        "writer_ms_per_step": round(1e3 * logger.stats["writer_cpu_s"] / steps, 3),
        "log_step_us": round(1e6 * log_cpu / steps, 1), "env_step_ms": round(1e3 * env_cpu / steps, 2),
        "cost_fraction_logged": round(logging / (env_cpu / steps), 4),
        "cost_fraction_every_10": round(logging / (env_cpu / steps) / 10, 4),
        "episodes_written": logger.stats["episodes_written"], "episodes_skipped": logger.stats["episodes_skipped"],
    }))


if __name__ == "__main__":
    main()
