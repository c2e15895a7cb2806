"""MCAP episode logs, written by actors without slowing their environments down.

Usage (one logger per actor process, one recorder per running episode)::

    logger = EpisodeLogger(run_dir / "episodes", run="exp1", actor_id=3,
                           policy=LogPolicy(every=10, evaluation=True, best=False),
                           disk_budget_bytes=2 << 30, step_seconds=0.01 * action_repeat)
    episode = logger.begin_episode({"seed": 7, "difficulty": 2, "policy_version": 41,
                                    "evaluation": False, "obstacles": env.unwrapped.obstacles})
    ...
    obs, reward, terminated, truncated, info = env.step(action)
    episode.log_step(obs, action, reward, info)      # obs: the vector, or the observation's fields
    ...
    episode.end({"return": ret, "distance": info["distance"], "length": n,
                 "terminated": terminated, "truncated": truncated})
    logger.close()                                   # on shutdown: flushes what is queued

Tasks without the runner's body (``with_body=False``: camera and photo tasks) log the Step
numbers they have (observation vector, action, reward, time; ``with_psnr``: the photo tasks'
``info["psnr_db"]``) and each uint8[3, H, W] field of the observation as PNG frames, one channel
per field, or where the observation holds no image, those of ``info["frames"]`` (a photo task
observed through statistics shows its images there).

``begin_episode`` always returns a recorder (a no-op one for episodes not logged), so the
actor never branches. Recorders of different environments are independent.

Which episodes: every ``every``-th training episode (0: none), every evaluation episode
(``evaluation``), and with ``best`` each training episode whose return beats the best so far
(kept in memory until it ends, then written; this costs a copy of every step).

Files: one per episode, ``<run>-a<actor>-<UTC start>-e<n>-<train|eval|best>.mcap`` in
``directory``, written as ``….mcap.part`` and renamed when complete, so a ``.mcap`` is
always whole; a crash leaves a ``.part`` that ``python -m l2r.episodes.recover`` repairs.
After each file the actor's own files beyond ``disk_budget_bytes`` are removed, oldest
first (never the newest, nor the current best). Below ``min_free_bytes`` free on the disk, no
episode is begun (``stats["episodes_shed"]``), so that a filling disk keeps its room for the
run's checkpoints and replay log; logging starts again once there is room. The format is in ``l2r.episodes.schema``
and docs/episodes.md.

Cost: ``log_step`` copies the step into a preallocated block (a few microseconds); a
background thread encodes blocks (frames as PNG) and writes zstd chunks. The queue between
them is bounded: when the disk falls behind, the episode being logged is dropped and counted
(``stats["episodes_skipped"]``) instead of blocking the environment. ``stats`` also counts
files written and removed, failures, and the writer thread's CPU seconds (``writer_cpu_s``).
"""

from __future__ import annotations

import hashlib
import logging
import queue
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

import l2r
from l2r.durable import DISK_ERRORS, MB, FailureLog, free_bytes
from l2r.episodes import schema
from l2r.episodes.body import BodyModel
from l2r.episodes.encode import StepLayout, TransformEncoder
from l2r.episodes.write import CHUNK_BYTES, EpisodeFile, text
from l2r.protocol.observations import VECTOR_FIELD
from l2r.sim.env import FOOT_SPHERES
from l2r.sim.ligaments import LIGAMENTS
from l2r.sim.model import MODEL_PATH, load_model

log = logging.getLogger(__name__)

BLOCK_STEPS = 100  # steps per hand-over to the writer thread (what a crash can lose at most)
INFO_VECTORS = ("muscle_activation", "muscle_force", "muscle_length", "ligament_force", "contact_force")


@dataclass(frozen=True)
class LogPolicy:
    """Which episodes an actor logs."""

    every: int = 10  # every N-th training episode, counting from the first; 0: none
    evaluation: bool = True  # every evaluation episode
    best: bool = False  # each training episode that beats the best return so far


class EpisodeLogger:
    """Writes selected episodes of one actor to MCAP files, off the stepping thread."""

    def __init__(
        self,
        directory: str | Path,
        run: str,
        actor_id: int,
        policy: LogPolicy = LogPolicy(),
        disk_budget_bytes: int = 1 << 30,
        min_free_bytes: int = 0,
        step_seconds: float = 0.01,
        queue_blocks: int = 64,
        block_steps: int = BLOCK_STEPS,
        chunk_bytes: int = CHUNK_BYTES,
        body: BodyModel | None = None,
        with_body: bool = True,
        with_psnr: bool = False,
    ):
        self.directory = Path(directory)
        self.write_failures = FailureLog(log, "episode logs")
        self._failed_before: set[tuple[type, str]] = set()  # other failures' causes, logged once each
        self.directory.mkdir(parents=True, exist_ok=True)
        self.run, self.actor_id, self.policy = run, int(actor_id), policy
        self.disk_budget_bytes, self.min_free_bytes = int(disk_budget_bytes), int(min_free_bytes)
        self._shedding = False
        self.step_seconds = float(step_seconds)
        self.block_steps, self.chunk_bytes = int(block_steps), int(chunk_bytes)
        self.stats = {"episodes_written": 0, "episodes_skipped": 0, "episodes_shed": 0, "episodes_failed": 0, "files_removed": 0, "write_errors": 0,
                      "writer_cpu_s": 0.0}
        self._layouts: dict[tuple, StepLayout] = {}
        self.body = (body or BodyModel.from_model(load_model())) if with_body else None
        self.with_psnr = with_psnr
        if self.body is not None:
            self.model_version = _model_version(MODEL_PATH)
            self._transforms = TransformEncoder(self.body.bodies)
            self.pelvis = self.body.bodies.index("pelvis") + 1  # row of the pelvis in info["body_pos"]
            self.body_json = self.body.to_json()
        self._training_episodes = 0
        self._episodes = 0
        self._best_return = -np.inf
        self._best_file: Path | None = None
        self._queue: queue.Queue = queue.Queue(maxsize=queue_blocks)
        self._thread = threading.Thread(target=self._write_loop, name=f"episode-log-{actor_id}", daemon=True)
        self._thread.start()

    # ----------------------------------------------------------------- stepping thread side

    def begin_episode(self, meta: dict[str, Any]) -> Recorder | NullRecorder:
        """Start an episode. ``meta``: seed, difficulty, policy_version, evaluation (bool),
        obstacles [(x, y, r)], and any other str/number values to keep."""
        evaluation = bool(meta.get("evaluation", False))
        n, self._episodes = self._episodes, self._episodes + 1
        if evaluation:
            kind = "eval" if self.policy.evaluation else None
        else:
            every = self.policy.every
            kind = "train" if every and self._training_episodes % every == 0 else None
            self._training_episodes += 1
            if kind is None and self.policy.best:
                kind = "best"
        if kind is None or self._below_floor():
            return NULL_RECORDER
        stamp = time.strftime("%Y%m%dT%H%M%S", time.gmtime())
        path = self.directory / f"{self.run}-a{self.actor_id}-{stamp}-e{n:06d}-{kind}.mcap"
        return Recorder(self, path, kind, dict(meta))

    def _below_floor(self) -> bool:
        """Whether the disk has less than `min_free_bytes` free, so that the episode is not
        logged: the run's checkpoints and replay log need the room more. Said once a spell."""
        if not self.min_free_bytes:
            return False
        free = free_bytes(self.directory)
        shedding = free < self.min_free_bytes
        if shedding != self._shedding:
            self._shedding = shedding
            if shedding:
                log.warning("episode logs: %.1f MB free at %s, below the floor of %.1f MB: episodes are not logged "
                            "until there is room", free / MB, self.directory, self.min_free_bytes / MB)
            else:
                log.info("episode logs: %.1f MB free at %s again: logging episodes", free / MB, self.directory)
        self.stats["episodes_shed"] += shedding
        return shedding

    def close(self, timeout: float = 30.0) -> None:
        """Write what is queued, abandon episodes still running (their .part files are
        removed), and stop the writer thread."""
        if self._thread.is_alive():
            try:
                self._queue.put(("stop",), timeout=timeout)
            except queue.Full:
                log.warning("episode logs: the writer did not drain its queue in %.0f s; giving up", timeout)
                return
            self._thread.join(timeout)

    def layout(self, sizes: dict[str, int]) -> StepLayout:
        key = tuple(sorted(sizes.items()))
        if key not in self._layouts:
            kept = [name for name, _ in schema.STEP_SCALARS
                    if (self.body is not None or name not in schema.BODY_SCALARS)
                    and (self.with_psnr or name not in schema.PHOTO_SCALARS)]
            self._layouts[key] = StepLayout(sizes, kept)
        return self._layouts[key]

    def _submit(self, item: tuple) -> bool:
        try:
            self._queue.put_nowait(item)
            return True
        except queue.Full:
            return False

    def _finished(self, recorder: Recorder, summary: dict[str, Any]) -> bool:
        """Whether a finished episode's file is kept; tracks the best training return."""
        ret = float(summary.get("return", -np.inf))
        if recorder.kind == "eval":
            return True
        is_best = ret > self._best_return
        if is_best:
            self._best_return = ret
        return recorder.kind == "train" or is_best

    # ---------------------------------------------------------------------- writer thread

    def _write_loop(self) -> None:
        open_files: dict[Recorder, EpisodeFile] = {}
        while True:
            item = self._queue.get()
            what, recorder = item[0], item[1] if len(item) > 1 else None
            try:
                if what == "stop":
                    self.stats["writer_cpu_s"] = time.thread_time()
                    break
                if recorder.dropped:
                    _discard(open_files.pop(recorder, None))
                elif what == "begin":
                    open_files[recorder] = _open_file(self, recorder)
                elif what == "block":
                    open_files[recorder].write_block(recorder.layout, *item[2:])
                elif what == "end":
                    open_files[recorder].finish(item[2])
                    del open_files[recorder]  # only now: a file that failed to finish is discarded below
                    self.stats["episodes_written"] += 1
                    self.write_failures.succeeded()
                    if recorder.kind == "best":
                        self._best_file = recorder.path
                    self._enforce_budget(keep=recorder.path)
            except Exception as e:
                if isinstance(e, OSError) and e.errno in DISK_ERRORS:  # one line per cause, not per episode
                    self.write_failures.failed(e, recorder.path, "episodes are dropped until one is written")
                elif (type(e), str(e)) not in self._failed_before:  # a traceback per cause, then a count
                    self._failed_before.add((type(e), str(e)))
                    log.exception("episode log %s: write failed; the episode is dropped (later episodes failing "
                                  "alike are counted in write_errors, not logged)", recorder.path.name)
                self.stats["write_errors"] += 1
                recorder.dropped = True  # its later items are discarded quietly
                _discard(open_files.pop(recorder, None))
            for rec in [r for r in open_files if r.dropped]:
                _discard(open_files.pop(rec))
            self.stats["writer_cpu_s"] = time.thread_time()
        for episode_file in open_files.values():
            _discard(episode_file)

    def _enforce_budget(self, keep: Path) -> None:
        files = []
        for p in self.directory.glob(f"{self.run}-a{self.actor_id}-*.mcap"):
            try:
                files.append((p.stat().st_mtime, p.stat().st_size, p))
            except FileNotFoundError:
                continue
        total = sum(size for _, size, _ in files)
        for _, size, p in sorted(files):
            if total <= self.disk_budget_bytes:
                break
            if p in (keep, self._best_file):
                continue
            p.unlink(missing_ok=True)
            total -= size
            self.stats["files_removed"] += 1


class NullRecorder:
    """The recorder of an episode that is not logged."""

    def log_step(self, obs: Any, action: Any, reward: float, info: dict[str, Any]) -> None:
        pass

    def end(self, summary: dict[str, Any]) -> None:
        pass


NULL_RECORDER = NullRecorder()


class Recorder:
    """Collects one episode's steps into blocks and hands them to the writer thread.

    A ``train``/``eval`` episode streams its blocks as they fill; a ``best`` candidate keeps
    them until ``end`` shows whether it beat the best return.
    """

    def __init__(self, logger: EpisodeLogger, path: Path, kind: str, meta: dict[str, Any]):
        self.logger, self.path, self.kind, self.meta = logger, path, kind, meta
        self.start_ns = time.time_ns()
        self.dropped = False
        self.ended = False
        self._streaming = kind != "best"
        self._held: list[tuple] = []
        self._step = 0
        self._row = 0
        self._block: np.ndarray | None = None
        if self._streaming:
            self._send(("begin", self))

    def log_step(self, obs: Any, action: Any, reward: float, info: dict[str, Any]) -> None:
        if self.dropped or self.ended:
            return
        try:
            self._copy_step(obs, action, reward, info)
        except (KeyError, ValueError, TypeError, IndexError, AttributeError) as e:
            # A step the format cannot hold (a missing info key, a changed shape) must not stop
            # the actor: the episode goes unlogged and the reason is logged.
            self.dropped = True
            self.logger.stats["episodes_failed"] += 1
            if self.logger.stats["episodes_failed"] <= 3:
                log.error("episode log %s: step %d cannot be logged (%r); episode not logged", self.path.name, self._step, e)

    def _copy_step(self, obs: Any, action: Any, reward: float, info: dict[str, Any]) -> None:
        vector, images = _split(obs, info)
        if self._block is None:
            self._new_block(vector, action, info, images)
        i, c = self._row, self._columns
        if "observation" in c:
            c["observation"][i] = vector
        c["action"][i] = action
        c["reward"][i] = reward
        c["time"][i] = (self._step + 1) * self.logger.step_seconds
        for name in self._info_vectors:
            c[name][i] = info[name].reshape(-1)
        if "psnr_db" in c:
            c["psnr_db"][i] = info["psnr_db"]
        if self._pos is not None:
            c["distance"][i] = info["distance"]
            pos = info["body_pos"]
            self._pos[i] = pos[1:]
            self._quat[i] = info["body_quat"][1:]
            c["pelvis_height"][i] = pos[self.logger.pelvis, 1]
        if images.keys() != self._images.keys():
            raise KeyError(f"image fields {sorted(images)}, the episode began with {sorted(self._images)}")
        for name, frames in self._images.items():
            frames[i] = images[name]
        self._step += 1
        self._row += 1
        if self._row == self.logger.block_steps:
            self._flush_block()

    def end(self, summary: dict[str, Any]) -> None:
        if self.ended:
            return
        self.ended = True
        if self.dropped:
            return
        if self._block is not None and self._row:
            self._flush_block()
        summary = {"length": self._step, **summary}
        if not self.logger._finished(self, summary):
            self._held.clear()
            return
        if not self._streaming:
            self._send(("begin", self))
            for block in self._held:
                self._send(block)
            self._held.clear()
        self._send(("end", self, summary))

    # ------------------------------------------------------------------------------ blocks

    def _new_block(self, vector: Any, action: Any, info: dict[str, Any], images: dict[str, np.ndarray]) -> None:
        logger = self.logger
        sizes = {"observation": np.size(vector), "action": np.size(action)}
        self._info_vectors = [name for name in INFO_VECTORS if name in info]
        sizes.update({name: np.size(info[name]) for name in self._info_vectors})
        self.layout = logger.layout(sizes)
        rows = logger.block_steps
        self._block = self.layout.new_block(rows)
        self._columns = {name: self._block[name] for name in self._block.dtype.names if not name.startswith("_")}
        self._images = {name: np.empty((rows, *frame.shape), np.uint8) for name, frame in images.items()}
        self._pos = self._quat = None
        if logger.body is not None:
            n = len(logger.body.bodies)
            self._pos = np.empty((rows, n, 3))
            self._quat = np.empty((rows, n, 4))

    def _flush_block(self) -> None:
        item = ("block", self, self._block, self._pos, self._quat, self._step - self._row, self._row, self._images)
        if self._streaming:
            self._send(item)
        else:
            self._held.append(item)
        self._row = 0
        if not self.dropped:
            self._block = self.layout.new_block(self.logger.block_steps)
            self._columns = {name: self._block[name] for name in self._columns}
            self._images = {name: np.empty_like(frames) for name, frames in self._images.items()}
            if self._pos is not None:
                self._pos = np.empty_like(self._pos)
                self._quat = np.empty_like(self._quat)

    def _send(self, item: tuple) -> None:
        if not self.dropped and not self.logger._submit(item):
            self.dropped = True
            stats = self.logger.stats
            stats["episodes_skipped"] += 1
            if stats["episodes_skipped"] in (1, 10, 100) or stats["episodes_skipped"] % 1000 == 0:
                log.warning("episode logs: the writer is behind (slow disk?); %d episode(s) skipped so far",
                            stats["episodes_skipped"])


def _open_file(logger: EpisodeLogger, recorder: Recorder) -> EpisodeFile:
    meta = recorder.meta
    obstacles = [tuple(float(v) for v in o) for o in meta.get("obstacles", ())]
    metadata = {k: text(v) for k, v in meta.items() if k != "obstacles"}
    metadata.update(run=logger.run, actor=str(logger.actor_id), kind=recorder.kind, format=schema.FORMAT_VERSION,
                    env_version=l2r.__version__)
    body = logger.body
    if body is None:
        metadata.update(step_seconds=text(logger.step_seconds))
        return EpisodeFile(recorder.path, None, metadata, {}, recorder.start_ns, chunk_bytes=logger.chunk_bytes)
    metadata.update(model=logger.model_version, step_seconds=text(logger.step_seconds),
                    obstacles=";".join(",".join(text(v) for v in o) for o in obstacles))
    names = {"muscles": body.muscles, "ligaments": LIGAMENTS, "contacts": FOOT_SPHERES, "bodies": body.bodies}
    return EpisodeFile(recorder.path, body, metadata, names, recorder.start_ns, obstacles,
                       logger.chunk_bytes, logger._transforms, logger.body_json)  # fmt: skip


def _split(obs: Any, info: Mapping[str, Any]) -> tuple[Any, dict[str, np.ndarray]]:
    """The vector an observation logs in Step, and its camera frames (uint8[3, H, W] fields) by
    name: the observation's, or where it holds none, those the step's info gives as ``frames``."""
    images = schema.image_fields(obs) if isinstance(obs, Mapping) else {}
    if not images and isinstance(info.get("frames"), Mapping):
        images = schema.image_fields(info["frames"])
    return (obs.get(VECTOR_FIELD, ()) if isinstance(obs, Mapping) else obs), images


def _model_version(path: Path) -> str:
    """The model file's content hash: two logs share a model exactly when these agree."""
    return "runner.xml sha256:" + hashlib.sha256(path.read_bytes()).hexdigest()[:16]


def _discard(episode_file: EpisodeFile | None) -> None:
    if episode_file is not None:
        episode_file.discard()
