"""A sum-tree over slot priorities, updated and searched with vectorised numpy."""

from __future__ import annotations

import numpy as np


class SumTree:
    """Binary tree in one array: node i has children 2i and 2i+1, leaves start at ``leaves``."""

    def __init__(self, capacity: int):
        self.capacity = capacity
        self.leaves = 1 << max(1, (capacity - 1).bit_length())
        self.tree = np.zeros(2 * self.leaves, dtype=np.float64)

    @property
    def total(self) -> float:
        return float(self.tree[1])

    def get(self, slots: np.ndarray) -> np.ndarray:
        return self.tree[self.leaves + slots]

    def set_range(self, start: int, values: np.ndarray) -> None:
        """Set ``len(values)`` consecutive slots from ``start`` (no wrap-around)."""
        lo = self.leaves + start
        hi = lo + len(values)  # exclusive
        self.tree[lo:hi] = values
        lo, hi = lo // 2, (hi - 1) // 2 + 1
        while lo >= 1:
            self.tree[lo:hi] = self.tree[2 * lo:2 * hi:2] + self.tree[2 * lo + 1:2 * hi:2]
            if lo == 1:
                break
            lo, hi = lo // 2, (hi - 1) // 2 + 1

    def set(self, slots: np.ndarray, values: np.ndarray) -> None:
        """Set arbitrary slots (duplicates: the last value wins)."""
        nodes = self.leaves + np.asarray(slots, dtype=np.int64)
        self.tree[nodes] = values
        nodes = np.unique(nodes // 2)
        while nodes[0] >= 1:
            self.tree[nodes] = self.tree[2 * nodes] + self.tree[2 * nodes + 1]
            if nodes[0] == 1:
                break
            nodes = np.unique(nodes // 2)

    def find(self, targets: np.ndarray) -> np.ndarray:
        """Slots whose cumulative priority range contains each target in [0, total)."""
        nodes = np.ones(len(targets), dtype=np.int64)
        targets = np.array(targets, dtype=np.float64)
        while nodes[0] < self.leaves:
            left = self.tree[2 * nodes]
            right = targets >= left
            targets -= left * right
            nodes = 2 * nodes + right
        return nodes - self.leaves
