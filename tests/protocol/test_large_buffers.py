"""What a process that moves batches of camera frames sets up: a shared-memory pool that holds
its replies, and a C allocator that reuses large buffers instead of faulting in fresh pages."""

from __future__ import annotations

import json
import subprocess
import sys

from l2r.protocol import session_config, with_reply_pool
from l2r.protocol.session import REPLY_POOL_BYTES, SHARED_MEMORY_POOL


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
