"""Learner tests run torch on one thread: on a busy two-core machine, two spinning torch
threads per test process slow small networks down by an order of magnitude."""

import pytest
import torch


@pytest.fixture(autouse=True)
def one_torch_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
