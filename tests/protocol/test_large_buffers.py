"""What a process that moves batches of camera frames sets up: a shared-memory pool that holds
its replies, replies written into shared memory of its own, and a C allocator that reuses large
buffers instead of faulting in fresh pages; and that a batch decoded from such a reply keeps its
frames while Zenoh reuses its buffers."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys

import numpy as np
import zenoh

from l2r.protocol import SampleBatch, decode, encode, session_config, with_reply_pool
from l2r.protocol.session import REPLY_POOL_BYTES, SHARED_MEMORY_POOL, SharedMemoryReplies
from tests.conftest import wait_for
from tests.protocol.factories import make_frames_batch


def test_the_reply_pool_holds_batches_of_frames_unless_a_config_file_chose_its_own(tmp_path):
    conf = with_reply_pool(session_config(listen=["tcp/127.0.0.1:7003"]))
    assert json.loads(conf.get_json(SHARED_MEMORY_POOL)) == REPLY_POOL_BYTES >= 8 * 30 * 2**20
    path = tmp_path / "z.json5"
    path.write_text("{ transport: { shared_memory: { transport_optimization: { pool_size: 33554432 } } } }")
    conf = with_reply_pool(session_config(mode=None, config_file=path))
    assert json.loads(conf.get_json(SHARED_MEMORY_POOL)) == 32 * 2**20


# On a thread of its own, as Zenoh's threads answer queries, 10 times what a shard does per
# reply: gather 1,000 frames (21 MB), join them into a message, copy that (as Zenoh does); then
# prints the pages it faulted in.
FAULTS = """
import resource, sys, threading
import numpy as np
from l2r.protocol import reuse_large_buffers
if sys.argv[1] == "reuse":
    assert reuse_large_buffers()
frames = np.zeros((2000, 3 * 84 * 84), np.uint8)
def reply():
    gathered = frames.take(np.arange(0, 2000, 2), axis=0)
    return bytearray(b"".join([b"header", gathered.data]))
def replies():
    reply()  # the first buffers' pages are new either way
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(10):
        reply()
    print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
thread = threading.Thread(target=replies)
thread.start()
thread.join()
"""


def faults(mode: str) -> int:
    done = subprocess.run([sys.executable, "-c", FAULTS, mode], capture_output=True, text=True, timeout=60, check=True)
    return int(done.stdout)


def test_large_buffers_are_reused_instead_of_faulted_in_again():
    fresh, reused = faults("plain"), faults("reuse")
    assert fresh > 10 * 5000  # 5,200 pages of 4 KiB a buffer of 21 MB, two or three buffers a reply
    assert reused < fresh / 10


def test_a_decoded_batch_keeps_its_frames_while_the_next_batches_arrive(endpoint):
    batch = make_frames_batch(b=64, k=3)  # 1.4 MB: through the shared-memory pool
    replies = iter(range(1, 100))  # batch i has every frame i times the first's

    def answer(query: zenoh.Query) -> None:
        i = next(replies)
        query.reply(query.key_expr, encode(dataclasses.replace(batch, frames={"pixels": batch.frames["pixels"] * i})))

    def fetch() -> SampleBatch | None:
        got = [r.ok.payload for r in learner.get("test/batch", timeout=5.0) if r.ok is not None]
        return decode(got[0], SampleBatch) if got else None

    with zenoh.open(with_reply_pool(session_config(listen=[endpoint]))) as shard, \
            zenoh.open(session_config(connect=[endpoint])) as learner:
        shard.declare_queryable("test/batch", answer)
        first = wait_for(fetch)
        i = int(first.frames["pixels"][1, 0, 0, 0])
        later = [fetch() for _ in range(4)]
        np.testing.assert_array_equal(first.frames["pixels"], batch.frames["pixels"] * i)
        for n, b in enumerate(later):
            np.testing.assert_array_equal(b.frames["pixels"], batch.frames["pixels"] * (i + n + 1))


def test_replies_in_shared_memory_reach_peers_with_and_without_it_and_go_as_bytes_when_it_is_full(endpoint):
    rng = np.random.default_rng(4)
    messages = [bytearray(rng.integers(0, 256, 3_000_000, np.uint8).tobytes()) for _ in range(3)]
    replies = SharedMemoryReplies(pool_bytes=8 * 2**20)  # room for two
    answered = []

    def answer(query: zenoh.Query) -> None:
        answered.append(len(answered) % 3)
        query.reply(query.key_expr, replies.payload(messages[answered[-1]]))

    small = replies.payload(b"ack")
    assert small == b"ack"
    for shared in (True, False):
        learner_config = session_config(connect=[endpoint])
        learner_config.insert_json5("transport/shared_memory/enabled", json.dumps(shared))
        with zenoh.open(with_reply_pool(session_config(listen=[endpoint]))) as shard, \
                zenoh.open(learner_config) as learner:
            shard.declare_queryable("test/reply", answer)
            got = wait_for(lambda: [r.ok.payload for r in learner.get("test/reply", timeout=5.0) if r.ok is not None])
            held = [got[0], *(next(r.ok.payload for r in learner.get("test/reply", timeout=5.0)) for _ in range(3))]
            assert [p.to_bytes() for p in held] == [bytes(messages[i]) for i in answered[-4:]]
            assert [p.as_shm() is not None for p in held[:2]] == [shared] * 2
            if shared:  # the first two, held by the learner, fill the memory
                assert replies.sent_as_bytes == 2
        answered.clear()
        del got, held  # read: their memory is free again
