"""A sum-tree over slot priorities, updated and searched with vectorised numpy."""

from __future__ import annotations

import numpy as np


def _leaves(capacity: int) -> int:
    return 1 << max(1, (capacity - 1).bit_length())


class SumTree:
    """Binary tree in one array: node i has children 2i and 2i+1, leaves start at ``leaves``.

    ``set_range`` (every insert) only writes leaves and remembers the range; the sums above
    are brought up to date when the tree is next searched, once for many inserts.
    """

    def __init__(self, capacity: int):
        self.capacity = capacity
        self.leaves = _leaves(capacity)
        self.tree = np.zeros(2 * self.leaves, dtype=np.float64)
        self._stale: list[tuple[int, int]] = []  # leaf ranges whose ancestors are out of date

    @staticmethod
    def nbytes_for(capacity: int) -> int:
        """The size of the tree of ``capacity`` slots, without making one."""
        return 2 * _leaves(capacity) * np.dtype(np.float64).itemsize

    @property
    def total(self) -> float:
        self._update()
        return float(self.tree[1])

    def get(self, slots: np.ndarray) -> np.ndarray:
        return self.tree[self.leaves + slots]

    def set_range(self, start: int, count: int, values: float | np.ndarray) -> None:
        """Set ``count`` consecutive slots from ``start`` (no wrap-around)."""
        self.tree[self.leaves + start:self.leaves + start + count] = values
        self._stale.append((start, start + count))
        if len(self._stale) > 64:  # inserts run along the ring: this keeps one or two ranges
            self._stale = _merged(self._stale)

    def set(self, slots: np.ndarray, values: np.ndarray) -> None:
        """Set arbitrary slots (duplicates: the last value wins)."""
        self._update()
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
        self._update()
        nodes = np.ones(len(targets), dtype=np.int64)
        targets = np.array(targets, dtype=np.float64)
        while nodes[0] < self.leaves:
            left = self.tree[2 * nodes]
            right = targets >= left
            targets -= left * right
            nodes = 2 * nodes + right
        return nodes - self.leaves

    def _update(self) -> None:
        """Recompute the ancestors of the leaves set since the last update."""
        for start, end in _merged(self._stale):
            lo, hi = (self.leaves + start) // 2, (self.leaves + end - 1) // 2 + 1
            while True:
                self.tree[lo:hi] = self.tree[2 * lo:2 * hi:2] + self.tree[2 * lo + 1:2 * hi:2]
                if lo == 1:
                    break
                lo, hi = lo // 2, (hi - 1) // 2 + 1
        self._stale.clear()


def _merged(ranges: list[tuple[int, int]]) -> list[tuple[int, int]]:
    out: list[list[int]] = []
    for start, end in sorted(ranges):
        if out and start <= out[-1][1]:
            out[-1][1] = max(out[-1][1], end)
        else:
            out.append([start, end])
    return [(a, b) for a, b in out]
