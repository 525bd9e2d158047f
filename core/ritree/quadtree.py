"""A forest of quadtrees in flat arrays, built level by level and searched for whole arrays of
query points at once (one loop iteration per tree level, never per query).

Every tree t covers the rectangle ``domain[t] = (x0, x1, y0, y1)``. Node k is the cell
(ix, iy) of its tree's 2^level x 2^level grid; its children are the four consecutive nodes
``child[k] + q`` with quadrant q = qx + 2 qy (qx = 1: upper x half). ``corner[k]`` holds the ids
of the samples at the cell's corners in the order (x0,y0), (x1,y0), (x0,y1), (x1,y1).

The same structure holds the viewpoint trees (six per RI-Tree; corners are viewpoint ids) and
the direction trees (five per viewpoint; corners are ray-sample ids).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# Corner offsets (dx, dy) of the corner slots.
CORNERS = np.array([[0, 0], [1, 0], [0, 1], [1, 1]])


@dataclass
class Forest:
    domain: np.ndarray      # (T, 4) float64 per-tree rectangle
    root: np.ndarray        # (T,) int64 root node, -1 where the tree was not built
    child: np.ndarray       # (K,) int64 first child, -1 for leaves
    level: np.ndarray       # (K,) int8
    ix: np.ndarray          # (K,) int32
    iy: np.ndarray          # (K,) int32
    corner: np.ndarray      # (K, 4) int64 corner sample ids (-1: not sampled)

    @classmethod
    def empty(cls, domain: np.ndarray) -> "Forest":
        return cls(domain=np.asarray(domain, np.float64), root=-np.ones(len(domain), np.int64),
                   child=np.zeros(0, np.int64), level=np.zeros(0, np.int8),
                   ix=np.zeros(0, np.int32), iy=np.zeros(0, np.int32),
                   corner=np.zeros((0, 4), np.int64))

    @property
    def max_level(self) -> int:
        return int(self.level.max()) if len(self.level) else 0

    def add_roots(self, trees: np.ndarray) -> np.ndarray:
        """Create root nodes for ``trees``; returns their node ids."""
        ids = self._append(len(trees), 0, np.zeros(len(trees), np.int32),
                           np.zeros(len(trees), np.int32))
        self.root[trees] = ids
        return ids

    def split(self, nodes: np.ndarray) -> np.ndarray:
        """Give leaf ``nodes`` four children each; returns the (len(nodes), 4) child ids."""
        n = len(nodes)
        lv = self.level[nodes].astype(np.int64) + 1
        ix = np.repeat(2 * self.ix[nodes], 4) + np.tile(CORNERS[:, 0], n)
        iy = np.repeat(2 * self.iy[nodes], 4) + np.tile(CORNERS[:, 1], n)
        ids = self._append(4 * n, np.repeat(lv, 4), ix, iy)
        self.child[nodes] = ids[::4]
        return ids.reshape(n, 4)

    def _append(self, n, level, ix, iy) -> np.ndarray:
        start = len(self.child)
        self.child = np.concatenate([self.child, -np.ones(n, np.int64)])
        self.level = np.concatenate([self.level, np.broadcast_to(level, (n,)).astype(np.int8)])
        self.ix = np.concatenate([self.ix, np.asarray(ix, np.int32)])
        self.iy = np.concatenate([self.iy, np.asarray(iy, np.int32)])
        self.corner = np.concatenate([self.corner, -np.ones((n, 4), np.int64)])
        return np.arange(start, start + n)

    def tree_of_nodes(self) -> np.ndarray:
        """(K,) tree index of every node (by walking down from the roots, level by level)."""
        tree = -np.ones(len(self.child), np.int64)
        built = np.flatnonzero(self.root >= 0)
        tree[self.root[built]] = built
        frontier = self.root[built]
        while len(frontier):
            frontier = frontier[self.child[frontier] >= 0]
            kids = (self.child[frontier][:, None] + np.arange(4)).ravel()
            tree[kids] = np.repeat(tree[frontier], 4)
            frontier = kids
        return tree

    def normalized(self, trees, x, y):
        """Query coordinates mapped to [0, 1]^2 of their trees' domains (clamped)."""
        d = self.domain.take(trees, axis=0)
        fx = np.clip((x - d[:, 0]) / (d[:, 1] - d[:, 0]), 0.0, 1.0)
        fy = np.clip((y - d[:, 2]) / (d[:, 3] - d[:, 2]), 0.0, 1.0)
        return fx, fy

    def locate(self, trees, x, y):
        """Leaf containing each query point (x, y) of tree ``trees``: returns (node, lx, ly)
        with (lx, ly) in [0, 1]^2 the point's coordinates inside the leaf cell; node = -1 where
        the tree was not built. Points on a shared cell edge go to the upper cell, except at
        the domain's upper end (clamped into the last cell)."""
        fx, fy = self.normalized(trees, x, y)
        return self.descend(self.root[trees], fx, fy)

    def descend(self, node, fx, fy):
        """Forest.locate from ``node`` (-1: tree not built), a node containing the points at
        normalized domain coordinates (fx, fy)."""
        ok = node >= 0
        nd = np.where(ok, node, 0)
        while True:
            ch = np.where(ok, self.child[nd], -1) if len(nd) else nd
            go = ch >= 0
            if not np.any(go):
                break
            g = np.flatnonzero(go)
            scale = np.exp2(self.level[nd[g]].astype(np.float64) + 1.0)
            qx = np.minimum(np.floor(fx[g] * scale), 2 * self.ix[nd[g]] + 1) - 2 * self.ix[nd[g]]
            qy = np.minimum(np.floor(fy[g] * scale), 2 * self.iy[nd[g]] + 1) - 2 * self.iy[nd[g]]
            nd[g] = ch[g] + np.clip(qx, 0, 1).astype(np.int64) + 2 * np.clip(qy, 0, 1).astype(np.int64)
        scale = np.exp2(self.level[nd].astype(np.float64))
        lx = np.clip(fx * scale - self.ix[nd], 0.0, 1.0)
        ly = np.clip(fy * scale - self.iy[nd], 0.0, 1.0)
        return np.where(ok, nd, -1), lx, ly

    def cube_scale(self, nodes, trees, lx, ly):
        """|(1, u, v)| at cell-local points (lx, ly) of ``nodes`` of ``trees`` (direction trees:
        the length of the direction-cube point, the weight that makes interpolated directions
        perspective-correct). nodes/trees (...), lx/ly (..., k) -> (..., k)."""
        d = self.domain[trees]
        sc = np.exp2(-self.level[nodes].astype(np.float64))[..., None]
        u = d[..., 0, None] + (d[..., 1] - d[..., 0])[..., None] * (self.ix[nodes][..., None] + lx) * sc
        v = d[..., 2, None] + (d[..., 3] - d[..., 2])[..., None] * (self.iy[nodes][..., None] + ly) * sc
        return np.sqrt(1.0 + u * u + v * v)

    def corner_coords(self, nodes, max_level):
        """(len(nodes), 4, 2) integer corner coordinates on the tree's 2^max_level grid."""
        sh = (max_level - self.level[nodes].astype(np.int64))[:, None]
        cx = (self.ix[nodes].astype(np.int64)[:, None] + CORNERS[:, 0]) << sh
        cy = (self.iy[nodes].astype(np.int64)[:, None] + CORNERS[:, 1]) << sh
        return np.stack([cx, cy], axis=2)

    def arrays(self, prefix: str) -> dict[str, np.ndarray]:
        """The forest as named arrays (for the cache file): per-tree domains and roots, the
        nodes' child links and the leaves' corners, in node order. Levels, cell indices and
        the inner nodes' corners follow from them (``from_arrays``)."""
        return {f"{prefix}.domain": self.domain, f"{prefix}.root": self.root,
                f"{prefix}.child": self.child, f"{prefix}.leaf_corner": self.corner[self.child < 0]}

    @classmethod
    def from_arrays(cls, arrays, prefix: str, max_level: int | None = None) -> "Forest":
        """``arrays``' forest (Forest.arrays): levels and cell indices walked down from the
        roots; an inner node's corner j is its child j's corner j, gathered up from the
        leaves (the same grid point: the bake keys direction samples on it; inner viewpoint
        cells, which the bake leaves without viewpoints, get them too, and nothing reads
        them). ValueError where the links are not a forest of quadtrees (or, with
        ``max_level``, one deeper than that)."""
        domain, root, child, leaf_corner = (np.asarray(arrays[f"{prefix}.{k}"]) for k in
                                            ("domain", "root", "child", "leaf_corner"))
        k = len(child)
        leaf = child < 0
        if leaf_corner.shape != (int(leaf.sum()), 4) or np.any(child < -1) \
                or np.any((child >= 0) & (child > k - 4)) or np.any(root >= k) \
                or np.any(root < -1):
            raise ValueError(f"{prefix} forest: child links, roots and leaf corners disagree")
        level = np.zeros(k, np.int8)
        ix, iy = np.zeros(k, np.int32), np.zeros(k, np.int32)
        corner = np.full((k, 4), -1, leaf_corner.dtype)
        corner[leaf] = leaf_corner
        seen = np.zeros(k, bool)
        levels, nodes = [], root[root >= 0]
        while len(nodes):
            if seen[nodes].any() or len(np.unique(nodes)) < len(nodes):
                raise ValueError(f"{prefix} forest: a node is reached twice")
            if max_level is not None and len(levels) > max_level:
                raise ValueError(f"{prefix} forest: deeper than {max_level} levels")
            seen[nodes] = True
            levels.append(nodes)
            inner = nodes[child[nodes] >= 0]
            kids = child[inner][:, None] + np.arange(4)
            level[kids] = level[inner][:, None] + 1
            ix[kids] = 2 * ix[inner][:, None] + CORNERS[:, 0]
            iy[kids] = 2 * iy[inner][:, None] + CORNERS[:, 1]
            nodes = kids.ravel()
        for nodes in reversed(levels):
            inner = nodes[child[nodes] >= 0]
            corner[inner] = corner[child[inner][:, None] + np.arange(4), np.arange(4)]
        return cls(domain=domain, root=root, child=child, level=level, ix=ix, iy=iy,
                   corner=corner)


# Memory a DenseLocator's table may take (int32 entries): a grid of 2^L x 2^L cells per built
# tree at the finest level L that fits.
LOCATOR_BUDGET_BYTES = 64 << 20


class DenseLocator:
    """Leaf search by table: for every built tree, a 2^L x 2^L grid holding the node at level
    <= L that covers each cell (L the forest's deepest level, or shallower to fit the memory
    budget). One table read replaces the descent to level L; deeper nodes are descended from
    there. Same answers as Forest.locate: cell indices floor(f * 2^L) are exact (powers of
    two), and the clamp to the last cell is the descent's."""

    def __init__(self, forest: Forest, budget_bytes: int = LOCATOR_BUDGET_BYTES):
        self.forest = forest
        built = np.flatnonzero(forest.root >= 0)
        level = forest.max_level
        while level > 0 and len(built) * 4 ** level * 4 > budget_bytes:
            level -= 1
        self.level, side = level, 1 << level
        self.offset = -np.ones(len(forest.root), np.int64)
        self.offset[built] = np.arange(len(built)) * side * side
        # at least one entry: a lookup in an unbuilt tree reads one (and ignores it)
        self.table = np.full(max(len(built) * side * side, 1), -1, np.int32)
        tree = forest.tree_of_nodes()
        for lv in range(level + 1):
            nodes = np.flatnonzero((forest.level == lv) & ((forest.child < 0) | (lv == level))
                                   & (tree >= 0))
            if len(nodes) == 0:
                continue
            sh = level - lv
            span = np.arange(1 << sh)
            cx = (forest.ix[nodes].astype(np.int64) << sh)[:, None, None] + span[None, None, :]
            cy = (forest.iy[nodes].astype(np.int64) << sh)[:, None, None] + span[None, :, None]
            self.table[self.offset[tree[nodes]][:, None, None] + cy * side + cx] = nodes[:, None, None]
        # per node, as Forest.descend computes them: 2^level and the cell index, float64
        self.scale = np.exp2(forest.level.astype(np.float64))
        self.ix = forest.ix.astype(np.float64)
        self.iy = forest.iy.astype(np.float64)

    def locate(self, trees, x, y):
        """As Forest.locate."""
        return self.locate_normalized(trees, *self.forest.normalized(trees, x, y))

    def locate_normalized(self, trees, fx, fy):
        """Forest.locate for points given in normalized domain coordinates (Forest.normalized).
        ``fx``, ``fy`` broadcast against ``trees`` (e.g. (n, 1) against (n, 4): one point in
        four trees, its cell computed once); results have the broadcast shape."""
        # np.take: numpy's fancy indexing costs up to twice as much for these gathers
        side = 1 << self.level
        off = self.offset.take(trees)
        cell = np.minimum((fy * side).astype(np.int64), side - 1) * side \
            + np.minimum((fx * side).astype(np.int64), side - 1)
        start = np.where(off >= 0, self.table.take(np.maximum(off, 0) + cell), -1)
        if self.level < self.forest.max_level:
            shape = start.shape
            nd, lx, ly = self.forest.descend(start.ravel(), np.broadcast_to(fx, shape).ravel(),
                                             np.broadcast_to(fy, shape).ravel())
            return nd.reshape(shape), lx.reshape(shape), ly.reshape(shape)
        # the table's nodes are leaves: Forest.descend's cell-local coordinates, no descent
        nd = np.maximum(start, 0)
        scale = self.scale.take(nd)
        lx = np.clip(fx * scale - self.ix.take(nd), 0.0, 1.0)
        ly = np.clip(fy * scale - self.iy.take(nd), 0.0, 1.0)
        return start, lx, ly
