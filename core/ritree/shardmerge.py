"""Merging the shards of a cluster bake (``bake.shards.ShardedPass.merge``): placing each
shard's blocks in the order one local pass makes, renumbering ids on the way, into output
arrays that the client first touched while it waited for the shards.

Writing fresh memory is most of a large merge's cost: on the VMs measured, the merge of a 5/6
full tree (1.3 GB) took 4.3-4.8 s, about nine tenths of it the host's first touch of the new
pages (the same copy into memory the process had used before took a tenth of the time). The
client is idle while the workers bake, so ``MergeBuffers`` allocates the merge's outputs from
the sizes of the shards received so far and touches them page by page between polls.
"""

from __future__ import annotations

import numpy as np

PAGE = 4096                 # bytes; one write per page makes the host map it
TOUCH_BYTES = 64 << 20      # bytes touched per idle call: ~0.1-0.2 s here, so cancel stays prompt
MARGIN = 1.1                # capacity over the estimated size, so late shards still fit


def block_shifts(counts, base):
    """(n, k) id shifts for n shards' blocks of k keys (``counts[s, j]`` items of key j in shard
    s, each shard's items key-major): the merged order is key-major, then shard, so item i of
    shard s with key j gets id ``base + i + shift[s, j]``."""
    key_start = np.concatenate([[0], np.cumsum(counts.sum(0))[:-1]])
    shard_off = np.cumsum(counts, axis=0) - counts
    local_start = np.cumsum(counts, axis=1) - counts
    return base + key_start[None] + shard_off - local_start


def interleave(parts, counts, head, buf=None, maps=None):
    """``head`` then the items of ``parts`` (one array per shard, key-major with ``counts[s,
    j]`` items of key j) in key-major, then shard order. Written into the first rows of
    ``buf`` where it has room (else a new array); with ``maps`` (one per shard), shard s's
    items are ids renumbered as ``maps[s][item]`` (an item of -1 maps to the map's last entry;
    ValueError for an id outside the map)."""
    start = np.cumsum(counts, axis=1) - counts
    if maps is not None:
        for part, m in zip(parts, maps):
            if part.size and (part.min() < -1 or part.max() >= len(m) - 1):
                raise ValueError("a shard's ids lie outside its id map")
    n = len(head) + int(counts.sum())
    dtype = np.result_type(head, *parts) if maps is None else maps[0].dtype
    if buf is not None and len(buf) >= n and buf.dtype == dtype \
            and buf.shape[1:] == head.shape[1:]:
        out = buf[:n]
    else:
        out = np.empty((n,) + head.shape[1:], dtype)
    out[:len(head)] = head
    pos = len(head)
    for j in range(counts.shape[1]):
        for s in range(len(parts)):
            c = counts[s, j]
            if c:
                src = parts[s][start[s, j]:start[s, j] + c]
                if maps is None:
                    out[pos:pos + c] = src
                else:           # "wrap": -1 is the last entry; "raise" would buffer the output
                    np.take(maps[s], src, out=out[pos:pos + c], mode="wrap")
                pos += c
    return out


class MergeBuffers:
    """The output arrays of one pass's merge, allocated and first touched while the client
    waits for the shards (``add`` each shard's result as it arrives, ``touch`` between polls,
    ``get`` at the merge). ``groups`` maps each merged field to its group ("nodes",
    "samples"): a group's fields have one row per item of it, ``head[group]`` rows before
    this pass. Dtypes are the shards' unless ``dtypes`` names one (renumbered ids). A
    group's size is estimated per direction tree of the shards received so far; a larger
    estimate later replaces its buffers (their touching starts over). The merged arrays are
    views of the buffers, which hold up to MARGIN more rows (untouched past the estimate)."""

    def __init__(self, groups: dict, head: dict, trees: int, dtypes: dict | None = None):
        self.groups, self.head, self.trees = groups, head, trees
        self.dtypes = dict(dtypes or {})
        self.trees_in, self.rows_in = 0, {g: 0 for g in head}
        self.buf, self.touched = {}, {}         # field -> array, bytes touched
        self.touched_bytes = 0                  # in all, for the record

    def add(self, result: dict, trees: int) -> None:
        """A shard's result (``bake_shard``), for ``trees`` direction trees, arrived."""
        self.trees_in += trees
        for group in self.head:
            first = next(k for k, g in self.groups.items() if g == group)
            self.rows_in[group] += len(result[first])
        for name, group in self.groups.items():
            need = self._estimate(group)
            buf = self.buf.get(name)
            if buf is None or len(buf) < need:
                a = np.asarray(result[name])
                self.buf[name] = None           # free the old buffer before the new one
                self.buf[name] = np.empty((int(need * MARGIN),) + a.shape[1:],
                                          self.dtypes.get(name, a.dtype))
                self.touched[name] = 0

    def _estimate(self, group: str) -> int:
        return self.head[group] + int(np.ceil(self.rows_in[group] * self.trees
                                              / max(self.trees_in, 1)))

    def touch(self, budget: int = TOUCH_BYTES) -> None:
        """First-touch up to ``budget`` more bytes of the estimated rows."""
        for name, buf in self.buf.items():
            row = buf.itemsize * int(np.prod(buf.shape[1:], dtype=np.int64))
            end = min(self._estimate(self.groups[name]) * row, buf.nbytes)
            a = self.touched[name]
            if a >= end or budget <= 0:
                continue
            b = min(end, a + budget)
            buf.reshape(-1).view(np.uint8)[a:b:PAGE] = 0
            self.touched[name] = b
            self.touched_bytes += b - a
            budget -= b - a

    def get(self, name: str):
        """The buffer for ``name`` (its first rows become the merged array), or None."""
        return self.buf.get(name)
