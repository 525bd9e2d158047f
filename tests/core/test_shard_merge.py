"""shardmerge: the merge's interleave against a plain per-item reference, and the merge
buffers (estimates, growth, touching, use) - the cluster tests check whole merged trees."""

import numpy as np
import pytest

from riray.ritree.shardmerge import MergeBuffers, block_shifts, interleave


def _shards(rng, n_shards, n_keys):
    counts = rng.integers(0, 5, (n_shards, n_keys))
    parts = [rng.integers(-1, 50, (int(c.sum()), 2)) for c in counts]
    return counts, parts


def test_interleave_and_shifts_against_a_reference():
    """Items go key-major, then shard, each shard's own order kept; block_shifts gives each
    item that position; maps renumber ids (-1 through the map's last entry)."""
    rng = np.random.default_rng(3)
    for trial in range(20):
        counts, parts = _shards(rng, int(rng.integers(1, 6)), int(rng.integers(1, 5)))
        head = rng.integers(0, 9, (int(rng.integers(0, 4)), 2))
        want, pos = [list(r) for r in head], {}
        for j in range(counts.shape[1]):
            for s in range(len(parts)):
                first = int(counts[s, :j].sum())
                for i in range(first, first + int(counts[s, j])):
                    pos[s, i] = len(want)
                    want.append(list(parts[s][i]))
        got = interleave(parts, counts, head)
        assert np.array_equal(got, np.array(want).reshape(-1, 2))
        shift = block_shifts(counts, len(head))
        for (s, i), p in pos.items():
            j = int(np.searchsorted(np.cumsum(counts[s]), i, side="right"))
            assert i + shift[s, j] == p
        maps = [np.append(rng.integers(100, 200, 50), -7) for _ in parts]
        got = interleave(parts, counts, head, maps=maps)
        ref = [list(r) for r in head] + [[maps[s][x] for x in parts[s][i]]
                                         for (s, i), _ in sorted(pos.items(), key=lambda kv: kv[1])]
        assert np.array_equal(got, np.array(ref).reshape(-1, 2))


def test_interleave_keeps_every_shards_values_and_checks_ids():
    """Shards may return different dtypes (int16 patch ids in one, int32 in another): the
    merged array holds them all. Ids outside a shard's map are an error, not wrapped."""
    counts = np.array([[2], [1]])
    got = interleave([np.array([1, 2], np.int16), np.array([40000], np.int32)], counts,
                     np.zeros(0, np.int16), buf=np.zeros(5, np.int16))
    assert got.dtype == np.int32 and np.array_equal(got, [1, 2, 40000])
    maps = [np.array([5, 6, -1]), np.array([7, -1])]
    ok = interleave([np.array([0, -1]), np.array([0])], counts, np.zeros(0, np.int64), maps=maps)
    assert np.array_equal(ok, [5, -1, 7])
    for bad in (np.array([0, 2]), np.array([0, -2])):
        with pytest.raises(ValueError, match="outside"):
            interleave([bad, np.array([0])], counts, np.zeros(0, np.int64), maps=maps)


def test_interleave_writes_into_a_buffer_with_room_only():
    counts = np.array([[2, 1], [1, 3]])
    parts = [np.arange(3), np.arange(10, 14)]
    head = np.array([-5])
    room = np.zeros(9, np.int64)
    got = interleave(parts, counts, head, buf=room)
    assert np.shares_memory(got, room) and len(got) == 8
    assert np.array_equal(got, [-5, 0, 1, 10, 2, 11, 12, 13])
    small = np.zeros(7, np.int64)
    got2 = interleave(parts, counts, head, buf=small)
    assert not np.shares_memory(got2, small) and np.array_equal(got2, got)
    wrong = np.zeros(9, np.int32)                  # another dtype: not used
    assert not np.shares_memory(interleave(parts, counts, head, buf=wrong), wrong)


def test_merge_buffers_estimate_grow_and_touch():
    """Sizes per tree of the shards received, scaled to all trees; an estimate beyond the
    capacity replaces the buffer; touching stops at the estimate and within the budget."""
    groups = {"a": "nodes", "b": "samples"}
    mb = MergeBuffers(groups, {"nodes": 10, "samples": 0}, trees=100,
                      dtypes={"a": np.dtype(np.int64)})
    r1 = {"a": np.zeros(40, np.int32), "b": np.zeros((30, 3), np.uint16)}
    mb.add(r1, 10)                                  # 4 nodes, 3 samples per tree
    assert len(mb.get("a")) >= 10 + 400 and mb.get("a").dtype == np.int64
    assert mb.get("b").shape[1:] == (3,) and len(mb.get("b")) >= 300
    first = mb.get("a")
    mb.touch(budget=2048)                           # of a's 410 rows x 8 bytes
    assert mb.touched_bytes == 2048 and mb.touched["a"] == 2048 and mb.touched["b"] == 0
    mb.add({"a": np.zeros(10, np.int32), "b": np.zeros((5, 3), np.uint16)}, 10)   # smaller
    assert mb.get("a") is first                     # the estimate shrank: the buffer stays
    mb.add({"a": np.zeros(400, np.int32), "b": np.zeros((5, 3), np.uint16)}, 10)  # much larger
    assert mb.get("a") is not first and len(mb.get("a")) >= 10 + 450 * 100 // 30
    while True:
        before = mb.touched_bytes
        mb.touch()
        if mb.touched_bytes == before:
            break
    est_a = 10 + int(np.ceil(450 * 100 / 30))
    assert mb.touched["a"] == est_a * 8 and mb.touched["b"] == int(np.ceil(40 * 100 / 30)) * 6
