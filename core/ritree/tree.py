"""The RI-Tree container (paper 3.2): viewpoint trees on the faces of the object's padded
bounding box, direction trees (five per viewpoint) on the inward hemicube, the ray samples
they share, and the extra samples of two-class leaf cells (paper 4.3).

Viewpoint tree f covers box face f (numbering as ``dircube``), in the face's (u, v) world axes
``UV_AXES[f // 2]``. Direction tree ``5 * vp + slot`` covers hemicube slot ``slot`` of
viewpoint ``vp``; ``dir_rect`` is the part of its domain that was baked (a query outside is
traced). Samples store f's answer for the corner rays: output ray, first hit point and normal
(float32), first patch (-1: the ray misses the object), null flag, ray-tree hash.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields
from functools import cached_property

import numpy as np

from ..trace.objectfn import one_reflection_hash
from .answers import COL
from .cache import TreeCacheError, fingerprint, load_tree, save_tree
from .codec import (decode_params, decode_points, decode_unit_vectors, encode_params, encode_points,
                    encode_unit_vectors)
from .derive import fill, kept_rows, valid_codes
from .quadtree import CORNERS, DenseLocator, Forest

SAMPLE_FIELDS = ("out_o", "out_d", "point", "normal", "patch", "null", "tree", "uv")
# Version of the tree's array layout inside a .rit file (the file format has its own version):
# a reader refuses other layouts with a message to re-bake. 2: the bake's measured errors and
# flags per direction node and viewpoint node (dir_err, dir_flags, vp_err, vp_flags). 3: what
# follows from the rest is not stored (levels, cell indices and inner corners of the forests,
# the outputs of samples that miss the object), small ranges in small dtypes. 4: each hit
# sample's normalized first-hit patch parameters (s.uv_q), the seeds of the mirror query's
# Newton step. 5: hit points and normals that follow from a sample's patch and parameters are
# not stored (s.geom; derive.py).
TREE_LAYOUT = 5
# Extra samples' cell-local positions are stored as uint16 multiples of 1 / EX_POS_SCALE where
# that is exact (the bake's edge search lands on binary fractions: search_steps <= 15), else
# as float32.
EX_POS_SCALE = 1 << 15
# Bits of dir_flags / vp_flags: what the bake's tests saw in a leaf cell.
UNVERIFIED = 1    # the cell failed its test (error above the tolerance, a class or null state its
                  # corners do not share, no interpolation) and could not be split further
BOUNDARY = 2      # an object/miss boundary crosses it: corners or test rays both hit and miss
                  # (or, direction cells, all miss while their frustum meets the object's boxes)
PATH_CHANGE = 4   # its corners or test rays do not all share one ray-tree hash (event sequence)


@dataclass
class BakeParams:
    """Bake settings. Angles in degrees, distances relative to the object's box diagonal."""

    viewpoint_depth: int = 5          # uniform viewpoint-tree depth (paper: 5)
    viewpoint_refine: int = 2         # extra viewpoint levels where camera rays lack interpolants
                                      # or the viewpoint-level error is too large
    direction_depth: int = 6          # maximum direction-tree depth (paper: 6)
    min_direction_depth: int = 1      # direction trees are split at least this deep
    tolerance_deg: float = 0.5        # split while the midpoint's interpolated output ray ...
    tolerance_dist: float = 0.002     # ... (or first hit / normal) misses the traced one by more
    viewpoint_tolerance_deg: float = 0.25  # split viewpoint cells whose camera test rays answered
                                      # through the tree miss the exact ones by more (verify.py)
    finest_min_traced: int = 0        # > 0: the finest viewpoint level (depth + refine) splits
                                      # only cells through which at least this many camera rays
                                      # are traced under the 2-degree baked-error tolerance
                                      # (bake.finest_rule; 0: by the rule of the other levels)
    search_steps: int = 4             # binary-search steps for the extra samples (paper 4.3):
                                      # a boundary to 1/16 of a cell edge (see docs/ritree.md)
    pad: float = 1e-3                 # bounding-box padding, relative to the diagonal

    def validate(self) -> "BakeParams":
        checks = [
            (1 <= self.viewpoint_depth <= 9, "viewpoint_depth must be in 1..9"),
            (1 <= self.direction_depth <= 10, "direction_depth must be in 1..10"),
            (0 <= self.viewpoint_refine <= 4 and self.viewpoint_depth + self.viewpoint_refine <= 10,
             "viewpoint_refine must be in 0..4 with viewpoint_depth + viewpoint_refine <= 10"),
            (0 <= self.min_direction_depth <= self.direction_depth,
             "min_direction_depth must be in 0..direction_depth"),
            (np.isfinite(self.tolerance_deg) and self.tolerance_deg > 0, "tolerance_deg must be > 0"),
            (np.isfinite(self.tolerance_dist) and self.tolerance_dist > 0,
             "tolerance_dist must be > 0"),
            (np.isfinite(self.viewpoint_tolerance_deg) and self.viewpoint_tolerance_deg > 0,
             "viewpoint_tolerance_deg must be > 0"),
            (0 <= self.search_steps <= 30, "search_steps must be in 0..30"),
            (0 <= self.finest_min_traced <= 1 << 30, "finest_min_traced must be in 0..2^30"),
            (np.isfinite(self.pad) and 0 <= self.pad <= 0.5, "pad must be in [0, 0.5]"),
        ]
        for ok, msg in checks:
            if not ok:
                raise ValueError(f"bake parameters: {msg} (got {asdict(self)})")
        return self


@dataclass
class Samples:
    """Ray samples (S of them); float32 geometry, int32 patch ids; ``uv`` (S, 2) float32 the
    first hit's normalized patch parameters (ObjectRays.uv)."""

    out_o: np.ndarray
    out_d: np.ndarray
    point: np.ndarray
    normal: np.ndarray
    patch: np.ndarray
    null: np.ndarray
    tree: np.ndarray
    uv: np.ndarray | None = None      # None: zeros (hand-made samples without patch parameters)

    def __post_init__(self):
        if self.uv is None:
            self.uv = np.zeros((len(self.patch), 2), np.float32)

    @classmethod
    def empty(cls) -> "Samples":
        z3 = np.zeros((0, 3), np.float32)
        return cls(z3, z3.copy(), z3.copy(), z3.copy(), np.zeros(0, np.int32),
                   np.zeros(0, bool), np.zeros(0, np.uint32), np.zeros((0, 2), np.float32))

    @classmethod
    def from_rays(cls, res) -> "Samples":
        """From an ``ObjectRays`` result (trace.objectfn)."""
        return cls(res.out_o.astype(np.float32) if hasattr(res, "out_o") else
                   res.out_origin.astype(np.float32), res.out_dir.astype(np.float32),
                   res.point.astype(np.float32), res.normal.astype(np.float32),
                   res.patch.astype(np.int32), res.null.astype(bool), res.tree.astype(np.uint32),
                   res.uv.astype(np.float32))

    def __len__(self) -> int:
        return len(self.patch)

    def gather(self, ids) -> np.ndarray:
        """(..., 12) float64 values (out_o, out_d, point, normal) of sample ids."""
        return np.concatenate([self.out_o[ids], self.out_d[ids], self.point[ids],
                               self.normal[ids]], axis=-1).astype(np.float64)

    def packed(self, lo, hi) -> "PackedSamples":
        """The compact form stored in cache files: points as 16-bit codes in the box [lo, hi],
        unit vectors as 2 x int16 octahedral codes (codec's worst-case errors: box / 131070
        per axis, 6.5e-5 rad), patch parameters as 2 x uint16 (worst 7.6e-6 of the domain)."""
        return PackedSamples(out_o_q=encode_points(self.out_o, lo, hi)[0],
                             out_d_q=encode_unit_vectors(self.out_d),
                             point_q=encode_points(self.point, lo, hi)[0],
                             normal_q=encode_unit_vectors(self.normal),
                             uv_q=encode_params(self.uv),
                             patch=self.patch.astype(np.int16 if self.patch.max(initial=0) < 32767
                                                     else np.int32),
                             null=self.null, tree=self.tree, lo=np.asarray(lo), hi=np.asarray(hi))

    def extend(self, other: "Samples") -> np.ndarray:
        """Append ``other``; returns the new ids."""
        start = len(self)
        for k in SAMPLE_FIELDS:
            setattr(self, k, np.concatenate([getattr(self, k), getattr(other, k)]))
        return np.arange(start, len(self))


@dataclass
class PackedSamples:
    """Samples as packed codes (codec.py; what bake shards return, and a cache file holds in
    the form of ``stored``): decoded on gather, or whole through the out_o / out_d / point /
    normal properties. ``geom`` (derive.py) says which hits' point, normal and output origin
    follow from the rest; a loaded file's are ``pending`` until derive.fill computes them."""

    out_o_q: np.ndarray     # (S, 3) uint16 point codes in the box [lo, hi]
    out_d_q: np.ndarray     # (S, 2) int16 octahedral codes (zero vector reserved)
    point_q: np.ndarray
    normal_q: np.ndarray
    uv_q: np.ndarray        # (S, 2) uint16 normalized patch parameter codes
    patch: np.ndarray       # (S,) int16/int32
    null: np.ndarray        # (S,) bool
    tree: np.ndarray        # (S,) uint32 ray-tree hash
    lo: np.ndarray
    hi: np.ndarray
    geom: np.ndarray | None = None  # (S,) uint8 derive.GEOM_* (None: all stored)
    pending: bool = False   # the derived hits' point and normal codes are not computed yet

    FIELDS = ("out_o_q", "out_d_q", "point_q", "normal_q", "uv_q", "patch", "null", "tree")
    CODES = FIELDS[:5]          # the output codes (stored for hits only)
    CODE_FORMS = {"out_o_q": (np.uint16, 3), "out_d_q": (np.int16, 2), "point_q": (np.uint16, 3),
                  "normal_q": (np.int16, 2), "uv_q": (np.uint16, 2)}   # dtype, columns
    STORED = ("patch", "null_bits", "tree_table", "tree_code", "geom") + CODES

    def __post_init__(self):
        if self.geom is None:
            self.geom = np.zeros(len(self.patch), np.uint8)

    def __len__(self) -> int:
        return len(self.patch)

    def _derived(self) -> None:
        if self.pending:
            raise RuntimeError("this tree's hit points and normals follow from its object's "
                               "surfaces: call attach_geometry(tracer) first (TreeQuery does)")

    @property
    def out_o(self) -> np.ndarray:
        self._derived()
        return decode_points(self.out_o_q, self.lo, self.hi)

    @property
    def out_d(self) -> np.ndarray:
        return decode_unit_vectors(self.out_d_q)

    @property
    def point(self) -> np.ndarray:
        self._derived()
        return decode_points(self.point_q, self.lo, self.hi)

    @property
    def normal(self) -> np.ndarray:
        self._derived()
        return decode_unit_vectors(self.normal_q)

    @property
    def uv(self) -> np.ndarray:
        return decode_params(self.uv_q)

    def stored(self) -> dict[str, np.ndarray]:
        """The cache file's sample arrays: the codes of the samples that hit the object only
        (a miss's output is its input ray, which the tree never interpolates), and of those
        the point, normal and output origin codes only where they do not follow from the rest
        (``geom``, hits only), null flags as bits, ray-tree hashes as indices into their
        distinct values."""
        hit = np.flatnonzero(self.patch >= 0)             # row take: faster than a mask
        kept = {k: hit[m] for k, m in kept_rows(self.geom[hit]).items()}
        table = np.unique(self.tree).astype(np.uint32)
        code = np.searchsorted(table, self.tree)
        return {"patch": self.patch, "null_bits": np.packbits(self.null, bitorder="little"),
                "tree_table": table,
                "tree_code": code.astype(np.uint8 if len(table) <= 1 << 8 else
                                         np.uint16 if len(table) <= 1 << 16 else np.uint32),
                "geom": self.geom.take(hit),
                **{k: getattr(self, k).take(kept.get(k, hit), axis=0) for k in self.CODES}}

    @classmethod
    def from_stored(cls, a: dict, lo, hi) -> "PackedSamples":
        """PackedSamples.stored's arrays back (misses' codes are zeros, and the codes that
        follow from the rest until derive.fill: ``pending``). ValueError where their lengths
        or the geometry codes disagree."""
        patch = np.asarray(a["patch"])
        if patch.ndim != 1 or patch.dtype.kind != "i":
            raise ValueError("sample patches are not a list of integers")
        for k, (dtype, cols) in cls.CODE_FORMS.items():
            q = np.asarray(a[k])
            if q.dtype != dtype or q.ndim != 2 or q.shape[1] != cols:
                raise ValueError(f"s.{k} is not (n, {cols}) {np.dtype(dtype).name} codes")
        n, hit = len(patch), np.flatnonzero(patch >= 0)
        table, code = np.asarray(a["tree_table"]), np.asarray(a["tree_code"])
        geom_hit = np.asarray(a["geom"])
        if geom_hit.ndim != 1 or len(geom_hit) != len(hit) or geom_hit.dtype != np.uint8 \
                or not valid_codes(geom_hit):
            raise ValueError("sample geometry codes disagree with the hits")
        kept = {k: hit[m] for k, m in kept_rows(geom_hit).items()}
        if len(code) != n or (n and int(code.max()) >= len(table)) \
                or len(a["null_bits"]) != (n + 7) // 8 \
                or any(len(a[k]) != len(kept.get(k, hit)) for k in cls.CODES):
            raise ValueError("sample arrays disagree in length")
        codes = {}
        for k in cls.CODES:
            q = np.asarray(a[k])
            codes[k] = np.zeros((n,) + q.shape[1:], q.dtype)
            codes[k][kept.get(k, hit)] = q
        null = np.unpackbits(np.asarray(a["null_bits"]), count=n, bitorder="little").view(bool)
        geom = np.zeros(n, np.uint8)
        geom[hit] = geom_hit
        return cls(**codes, patch=patch, null=null,
                   tree=table[code] if n else np.zeros(0, np.uint32), lo=lo, hi=hi, geom=geom,
                   pending=bool(np.any(geom_hit)))

    def take(self, ids) -> "PackedSamples":
        """The samples ``ids`` (in that order)."""
        return PackedSamples(**{k: getattr(self, k)[ids] for k in self.FIELDS},
                             lo=self.lo, hi=self.hi, geom=self.geom[ids], pending=self.pending)

    def gather(self, ids) -> np.ndarray:
        """(..., 12) float64 values of sample ids; each distinct sample is decoded once."""
        self._derived()
        ids = np.asarray(ids)
        u, inv = np.unique(ids, return_inverse=True)
        vals = np.concatenate([decode_points(self.out_o_q[u], self.lo, self.hi),
                               decode_unit_vectors(self.out_d_q[u]),
                               decode_points(self.point_q[u], self.lo, self.hi),
                               decode_unit_vectors(self.normal_q[u])], axis=-1)
        return vals[inv.reshape(ids.shape)]


@dataclass
class SampleTable:
    """Every sample decoded once, for rendering. ``vals`` (S, 14) float32 holds out_o, out_d,
    point, normal (float32 keeps interpolation within 1e-7 rad of float64: far below the cache's
    6.5e-5 rad octahedral quantization) and the first hit's normalized patch parameters uv
    (columns named by answers.COL); ``cls`` the sample's class (-1: misses the object)."""

    vals: np.ndarray        # (S, 14) float32
    cls: np.ndarray         # (S,) int32
    null: np.ndarray        # (S,) bool
    patch: np.ndarray       # (S,) int32
    tree: np.ndarray        # (S,) uint32 ray-tree hash
    once: np.ndarray        # (S,) bool: a hit whose ray-tree hash is one reflection off its
                            # patch (a mirror ray that left at its first hit)

    @classmethod
    def of(cls, samples, class_of) -> "SampleTable":
        vals = np.empty((len(samples), COL.N), np.float32)
        for k, col in (("out_o", COL.OUT_O), ("out_d", COL.OUT_D), ("point", COL.POINT),
                       ("normal", COL.NORMAL), ("uv", COL.UV)):
            vals[:, col] = getattr(samples, k)
        patch = np.asarray(samples.patch, np.int32)
        klass = np.where(patch >= 0, np.asarray(class_of)[np.maximum(patch, 0)], -1)
        null = np.asarray(samples.null, bool)
        tree = np.asarray(samples.tree, np.uint32)
        once = (klass >= 0) & ~null & (tree == one_reflection_hash(patch))
        return cls(vals=vals, cls=klass.astype(np.int32), null=null, patch=patch, tree=tree,
                   once=once)


@dataclass
class RITree:
    params: BakeParams
    box_lo: np.ndarray                # (3,) padded bounding box
    box_hi: np.ndarray
    diag: float                       # the object's (unpadded) box diagonal
    class_of: np.ndarray              # (P,) class id of each patch
    vp_forest: Forest                 # 6 trees, corners = viewpoint ids
    vp_pos: np.ndarray                # (V, 3) viewpoint positions
    vp_face: np.ndarray               # (V,) box face of each viewpoint
    dir_forest: Forest                # 5 V trees, corners = sample ids
    dir_rect: np.ndarray              # (5 V, 4) baked part of each direction tree's domain
    samples: Samples | PackedSamples
    ex_node: np.ndarray               # (E,) sorted leaf nodes of dir_forest with extra samples
    ex_kind: np.ndarray               # (E,) 1 = one-interpolant, 2 = two-interpolant cell
    ex_ids: np.ndarray                # (E, 4) sample ids v1..v4
    ex_pos: np.ndarray                # (E, 4, 2) their cell-local (lx, ly)
    ex_corner: np.ndarray             # (E, 4) corner slots: see bake._extras
    # The bake's measurements (None: nothing measured, as for a hand-made tree: NaN errors and
    # no flags).
    dir_err: np.ndarray | None = None    # (K,) float32 largest output-direction error (degrees)
                                         # the bake measured in each direction node; NaN: none
    dir_flags: np.ndarray | None = None  # (K,) uint8 UNVERIFIED | BOUNDARY | PATH_CHANGE
    vp_err: np.ndarray | None = None     # (Kv,) float32 the same per viewpoint node (camera test
                                         # rays across the cell answered through the tree)
    vp_flags: np.ndarray | None = None   # (Kv,) uint8
    meta: dict = field(default_factory=dict)

    def __post_init__(self):
        for name, forest in (("dir", self.dir_forest), ("vp", self.vp_forest)):
            if getattr(self, f"{name}_err") is None:
                setattr(self, f"{name}_err", np.full(len(forest.child), np.nan, np.float32))
            if getattr(self, f"{name}_flags") is None:
                setattr(self, f"{name}_flags", np.zeros(len(forest.child), np.uint8))

    @cached_property
    def table(self) -> SampleTable:
        """The samples decoded once (the first use decodes a packed file's samples)."""
        return SampleTable.of(self.samples, self.class_of)

    def attach_geometry(self, tracer) -> None:
        """Compute a loaded tree's derived hit points and normals from ``tracer`` (the
        PatchTracer of the object it was baked for; derive.py). A no-op for a baked tree."""
        if getattr(self.samples, "pending", False):
            try:
                self.samples = fill(self.samples, tracer)
            except ValueError as e:
                raise TreeCacheError(f"RI-Tree does not fit this object ({e}); re-bake the "
                                     "tree") from None

    @cached_property
    def blend_vals(self) -> np.ndarray:
        """(S, 14) float32: ``table.vals`` with each output direction multiplied by its
        sample's perspective weight |(1, u, v)| (Forest.cube_scale at the sample's point of the
        direction cube), so that one weighted sum of these rows blends every column and the
        blended direction is perspective-correct. The weight depends only on the sample's
        input direction, so it is computed once per sample: from the corners of every
        direction node and from the extras' cell-local positions. A second table beside
        ``table.vals`` (whose unit directions the pairwise thresholds compare): 56 bytes a
        sample, 178 MB on a 3.2 M-sample full tree."""
        f, n = self.dir_forest, len(self.samples)
        scale = np.ones(n)
        tree = f.tree_of_nodes()
        nodes = np.flatnonzero(tree >= 0)
        lx = np.broadcast_to(CORNERS[:, 0].astype(np.float64), (len(nodes), 4))
        ly = np.broadcast_to(CORNERS[:, 1].astype(np.float64), (len(nodes), 4))
        sc = f.cube_scale(nodes, tree[nodes], lx, ly)
        ids = f.corner[nodes]
        scale[ids[ids >= 0]] = sc[ids >= 0]
        if len(self.ex_node):
            pos = self.ex_pos.astype(np.float64)
            sc = f.cube_scale(self.ex_node, tree[self.ex_node], pos[..., 0], pos[..., 1])
            scale[self.ex_ids] = sc
        vals = self.table.vals.copy()
        vals[:, COL.OUT_D] *= scale[:, None].astype(np.float32)
        return vals

    @cached_property
    def vp_locator(self) -> DenseLocator:
        return DenseLocator(self.vp_forest)

    @cached_property
    def dir_locator(self) -> DenseLocator:
        return DenseLocator(self.dir_forest)

    @cached_property
    def leaf_ok(self) -> np.ndarray:
        """(K,) direction-tree nodes whose four corners are sampled and whose cell lies inside
        its tree's baked rectangle: every query located in such a leaf can be answered."""
        f = self.dir_forest
        ok = np.all(f.corner >= 0, axis=1)
        tree = f.tree_of_nodes()
        ok &= tree >= 0
        t = np.maximum(tree, 0)
        dom, rect = f.domain[t], self.dir_rect[t]
        size = np.exp2(-f.level.astype(np.float64))
        for axis, idx in ((0, f.ix), (1, f.iy)):
            lo, span = dom[:, 2 * axis], dom[:, 2 * axis + 1] - dom[:, 2 * axis]
            c0 = lo + span * idx * size
            c1 = lo + span * (idx + 1) * size
            ok &= (c0 >= rect[:, 2 * axis]) & (c1 <= rect[:, 2 * axis + 1])
        return ok

    @cached_property
    def leaf_sampled(self) -> np.ndarray:
        """(K,) direction-tree nodes whose four corners are sampled."""
        return np.all(self.dir_forest.corner >= 0, axis=1)

    @cached_property
    def cell_rect(self) -> np.ndarray:
        """(Kv, 5, 4) per viewpoint-forest node and hemicube slot: the intersection of its four
        viewpoints' baked rectangles (``dir_rect``) of that slot (empty where a corner has no
        viewpoint), so a query direction inside it is inside all four."""
        vps = self.vp_forest.corner
        out = np.empty((len(vps), 5, 4))
        out[:] = (np.inf, -np.inf, np.inf, -np.inf)
        full = np.flatnonzero(np.all(vps >= 0, axis=1))       # none in a tree without viewpoints
        trees = vps[full][:, :, None] * 5 + np.arange(5)                      # (n, 4, 5)
        r = self.dir_rect[trees]                                               # (n, 4, 5, 4)
        out[full] = np.stack([r[..., 0].max(axis=1), r[..., 1].min(axis=1),
                              r[..., 2].max(axis=1), r[..., 3].min(axis=1)], axis=-1)
        return out

    def sample_class(self, ids: np.ndarray) -> np.ndarray:
        """Class of sample ids (-1: misses the object)."""
        p = self.samples.patch[ids]
        return np.where(p >= 0, self.class_of[np.maximum(p, 0)], -1)

    def arrays(self) -> dict[str, np.ndarray]:
        """The tree as the cache file's named arrays (layout 5, docs/tree-format.md), samples in
        first-use order (``first_use_order``)."""
        packed = self.samples if isinstance(self.samples, PackedSamples) else \
            self.samples.packed(self.box_lo, self.box_hi)
        forests = {**self.vp_forest.arrays("vp"), **self.dir_forest.arrays("dir")}
        perm = first_use_order(forests["dir.leaf_corner"], self.ex_ids, len(packed))
        new_id = np.empty(len(perm), np.int64)
        new_id[perm] = np.arange(len(perm))

        def renumber(ids):                   # -1 (a corner not sampled) stays -1
            return np.where(ids >= 0, new_id[np.maximum(ids, 0)], ids)

        forests["dir.leaf_corner"] = renumber(forests["dir.leaf_corner"])
        out = {"box_lo": self.box_lo, "box_hi": self.box_hi, "class_of": self.class_of,
               "vp_pos": self.vp_pos, "vp_face": self.vp_face, "dir_rect": self.dir_rect,
               "ex_node": _ids(self.ex_node), "ex_kind": self.ex_kind.astype(np.int8),
               "ex_ids": _ids(renumber(self.ex_ids)), "ex_pos": _ex_pos_codes(self.ex_pos),
               "ex_corner": self.ex_corner.astype(np.int8), "dir_err": self.dir_err,
               "dir_flags": self.dir_flags, "vp_err": self.vp_err, "vp_flags": self.vp_flags}
        out.update({k: _ids(v) if k.rsplit(".", 1)[1] in ("root", "child", "leaf_corner") else v
                    for k, v in forests.items()})
        out.update({f"s.{k}": v for k, v in packed.take(perm).stored().items()})
        return out

    # The cache file's filter chains (filters.py): ids and codes as column differences, which
    # are small once the samples are in first-use order; everything else as it is.
    _DELTA = ("vp.root", "vp.child", "vp.leaf_corner", "dir.root", "dir.child",
              "dir.leaf_corner", "ex_node", "ex_ids", "ex_pos") \
        + tuple(f"s.{k}" for k in PackedSamples.CODES)

    def file_filters(self, arrays: dict[str, np.ndarray]) -> dict[str, tuple[str, ...]]:
        """The filter chain of each of ``arrays`` (RITree.arrays) in the cache file."""
        return {k: ("delta", "shuffle", "lzma") if k in self._DELTA and a.dtype.kind in "iu"
                else ("lzma",) for k, a in arrays.items()}

    def header(self) -> dict:
        return {"layout": TREE_LAYOUT, "params": asdict(self.params), "diag": self.diag,
                **self.meta}

    _ARRAYS = ("box_lo", "box_hi", "class_of", "vp_pos", "vp_face", "dir_rect", "ex_node", "ex_kind",
               "ex_ids", "ex_pos", "ex_corner", "dir_err", "dir_flags", "vp_err", "vp_flags") \
        + tuple(f"{f}.{k}" for f in ("vp", "dir") for k in ("domain", "root", "child",
                                                            "leaf_corner")) \
        + tuple(f"s.{k}" for k in PackedSamples.STORED)

    @classmethod
    def from_parts(cls, header: dict, arrays: dict) -> "RITree":
        """The tree of a cache file's header and arrays; TreeCacheError (saying to re-bake)
        unless they are a layout-5 tree: header fields, dtypes and shapes (``check_file``),
        then every index against what it indexes, before any array is used."""
        a = {k: np.asarray(v) for k, v in arrays.items()}
        check_file(header, {k: (v.dtype, v.shape) for k, v in a.items()})
        lo, hi = a["box_lo"], a["box_hi"]
        try:
            _check_values(a, header["params"])
            vp_forest, dir_forest = (Forest.from_arrays(a, f, max_level) for f, max_level in
                                     (("vp", header["params"]["viewpoint_depth"]
                                       + header["params"]["viewpoint_refine"]),
                                      ("dir", header["params"]["direction_depth"])))
            samples = PackedSamples.from_stored({k: a[f"s.{k}"] for k in PackedSamples.STORED},
                                                lo, hi)
        except ValueError as e:
            raise TreeCacheError(f"RI-Tree file is inconsistent ({e}); re-bake the tree") from None
        ex_pos = a["ex_pos"]
        if ex_pos.dtype == np.uint16:
            ex_pos = (ex_pos / np.float32(EX_POS_SCALE)).astype(np.float32)
        return cls(params=BakeParams(**header["params"]), box_lo=lo,
                   box_hi=hi, diag=float(header["diag"]), class_of=a["class_of"],
                   vp_forest=vp_forest, vp_pos=a["vp_pos"], vp_face=a["vp_face"],
                   dir_forest=dir_forest, dir_rect=a["dir_rect"], samples=samples,
                   ex_node=a["ex_node"], ex_kind=a["ex_kind"], ex_ids=a["ex_ids"],
                   ex_pos=ex_pos, ex_corner=a["ex_corner"], dir_err=a["dir_err"],
                   dir_flags=a["dir_flags"], vp_err=a["vp_err"], vp_flags=a["vp_flags"],
                   meta={k: v for k, v in header.items() if k not in ("layout", "params", "diag")})


# A file's arrays may claim at most this many times the file's bytes in all (or
# MIN_EXPANSION_BYTES, whichever is larger): the sample scenes' trees claim 4-8 times theirs
# (camera and full trees of glass_sphere), so a small crafted file cannot claim gigabytes.
MAX_EXPANSION = 32
MIN_EXPANSION_BYTES = 64 << 20
_IDS = ("<i4", "<i8")
_INTS = ("|i1", "<i2", "<i4", "<i8")


def _file_table(c: dict) -> dict:
    """Array name -> (allowed dtype strings, shape) of a layout-5 tree with counts ``c``."""
    V, K, Kv, S, H, E = c["V"], c["K"], c["Kv"], c["S"], c["H"], c["E"]
    return {
        "box_lo": (("<f8",), (3,)), "box_hi": (("<f8",), (3,)), "class_of": (_INTS, (c["P"],)),
        "vp_pos": (("<f8",), (V, 3)), "vp_face": (_INTS, (V,)), "dir_rect": (("<f8",), (5 * V, 4)),
        "ex_node": (_IDS, (E,)), "ex_kind": (("|i1",), (E,)), "ex_ids": (_IDS, (E, 4)),
        "ex_pos": (("<u2", "<f4"), (E, 4, 2)), "ex_corner": (("|i1",), (E, 4)),
        "dir_err": (("<f4",), (K,)), "dir_flags": (("|u1",), (K,)),
        "vp_err": (("<f4",), (Kv,)), "vp_flags": (("|u1",), (Kv,)),
        "vp.domain": (("<f8",), (6, 4)), "vp.root": (_IDS, (6,)), "vp.child": (_IDS, (Kv,)),
        "vp.leaf_corner": (_IDS, (c["Lv"], 4)),
        "dir.domain": (("<f8",), (5 * V, 4)), "dir.root": (_IDS, (5 * V,)),
        "dir.child": (_IDS, (K,)), "dir.leaf_corner": (_IDS, (c["L"], 4)),
        "s.patch": (("<i2", "<i4"), (S,)), "s.null_bits": (("|u1",), ((S + 7) // 8,)),
        "s.tree_table": (("<u4",), (c["U"],)), "s.tree_code": (("|u1", "<u2", "<u4"), (S,)),
        "s.geom": (("|u1",), (H,)), "s.out_d_q": (("<i2",), (H, 2)), "s.uv_q": (("<u2",), (H, 2)),
        "s.point_q": (("<u2",), (c["Hp"], 3)), "s.normal_q": (("<i2",), (c["Hp"], 2)),
        "s.out_o_q": (("<u2",), (c["Ho"], 3))}


def check_file(header: dict, table: dict, file_bytes: int | None = None) -> None:
    """TreeCacheError (saying to re-bake) unless ``header`` and ``table`` ({name: (dtype,
    shape)}, as cache.load_tree's ``check`` hears them before reading any array) are a
    layout-5 tree's: the header fields the reader uses (type and range), exactly the tree's
    arrays, each of its dtype and of the shape the tree's counts give, the counts agreeing
    (a forest of quadtrees, samples and hits) and, with ``file_bytes``, the arrays claiming
    at most MAX_EXPANSION times the file's bytes."""
    def bad(msg):
        return TreeCacheError(f"RI-Tree file is inconsistent ({msg}); re-bake the tree")

    if header.get("layout") != TREE_LAYOUT:
        raise TreeCacheError(f"RI-Tree layout {repr(header.get('layout'))[:40]} is not "
                             f"supported: this riray reads layout {TREE_LAYOUT}; re-bake the tree")
    params, diag = header.get("params"), header.get("diag")
    kinds = {f.name: f.type for f in fields(BakeParams)}
    if not isinstance(params, dict) or set(params) != set(kinds) or any(
            type(v) is not int and (kinds[k] != "float" or type(v) is not float)
            for k, v in params.items()):
        raise bad(f"header 'params' must hold exactly the numbers {sorted(kinds)}")
    try:
        BakeParams(**params).validate()
    except ValueError as e:
        raise bad(str(e)) from None
    if type(diag) not in (int, float) or not 0 < diag < float("inf"):
        raise bad("header 'diag' must be a positive finite number")
    missing = sorted(set(RITree._ARRAYS) - set(table))
    unknown = sorted(set(table) - set(RITree._ARRAYS))
    if missing or unknown:
        raise bad(f"arrays {missing} missing" if missing else f"unknown arrays {unknown[:5]}")

    def n(name, axis=0):
        shape = table[name][1]
        return shape[axis] if len(shape) > axis else -1

    c = {"V": n("vp_pos"), "K": n("dir.child"), "Kv": n("vp.child"), "L": n("dir.leaf_corner"),
         "Lv": n("vp.leaf_corner"), "S": n("s.patch"), "H": n("s.geom"), "E": n("ex_node"),
         "U": n("s.tree_table"), "P": n("class_of"), "Hp": n("s.point_q"), "Ho": n("s.out_o_q")}
    for name, (dtypes, shape) in _file_table(c).items():
        dtype, got = table[name]
        if np.dtype(dtype).str not in dtypes or tuple(got) != shape:
            raise bad(f"array {name!r} is {np.dtype(dtype).str} {list(got)}, expected "
                      f"{'/'.join(dtypes)} {list(shape)}")
    for forest, trees, k, leaves in (("vp", 6, c["Kv"], c["Lv"]),
                                     ("dir", 5 * c["V"], c["K"], c["L"])):
        if not (leaves <= k and 0 <= k - 4 * (k - leaves) <= trees):
            raise bad(f"{forest} forest: {k} nodes with {leaves} leaves are not quadtrees of "
                      f"{trees} roots")
    if not (c["Hp"] <= c["H"] and c["Ho"] <= c["H"] <= c["S"] and c["U"] <= c["S"]
            and (c["U"] > 0 or c["S"] == 0)):
        raise bad("sample, hit and ray-tree hash counts disagree")
    claimed = sum(math.prod(shape) * np.dtype(dtype).itemsize for dtype, shape in table.values())
    if file_bytes is not None and claimed > max(MAX_EXPANSION * file_bytes, MIN_EXPANSION_BYTES):
        raise bad(f"its arrays claim {claimed} bytes, more than {MAX_EXPANSION} times the "
                  f"file's {file_bytes}")


def _check_values(a: dict, params: dict) -> None:
    """ValueError unless every id in ``a`` (a layout-5 tree's arrays, ``check_file``'s
    shapes) lies within what it indexes and the geometry is finite."""
    S, K, V = len(a["s.patch"]), len(a["dir.child"]), len(a["vp_pos"])

    def within(name, lo, hi):
        x = a[name]
        if x.size and (x.min() < lo or x.max() >= hi):
            raise ValueError(f"{name} holds values outside {lo}..{hi - 1}")

    within("vp.leaf_corner", -1, V)
    within("dir.leaf_corner", -1, S)
    within("vp_face", 0, 6)
    within("s.patch", -1, len(a["class_of"]))
    within("class_of", 0, 1 << 31)
    within("ex_node", 0, K)
    within("ex_ids", 0, S)
    within("ex_kind", 1, 3)
    within("ex_corner", -1, 4)
    ex_node = a["ex_node"]
    if np.any(np.diff(ex_node) <= 0) or np.any(a["dir.child"][ex_node] >= 0):
        raise ValueError("ex_node is not a sorted list of distinct leaves")
    pos = a["ex_pos"]
    if pos.size and not (0 <= pos.min() and pos.max() <= (EX_POS_SCALE if pos.dtype == np.uint16
                                                          else 1)):
        raise ValueError("ex_pos holds positions outside the cell")
    lo, hi = a["box_lo"], a["box_hi"]
    dom = np.concatenate([a["vp.domain"], a["dir.domain"]])
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.all(lo < hi)
            and np.all(np.isfinite(a["vp_pos"])) and np.all(np.isfinite(dom))
            and np.all(dom[:, 1] > dom[:, 0]) and np.all(dom[:, 3] > dom[:, 2])):
        raise ValueError("box, viewpoints or tree domains are not finite boxes")


def _ids(a: np.ndarray) -> np.ndarray:
    """Node or sample ids as int32 where they fit."""
    return a.astype(np.int32, copy=False) if a.size == 0 or a.max() < 2**31 - 1 else a


def _ex_pos_codes(pos: np.ndarray) -> np.ndarray:
    """Extra-sample positions as uint16 codes (x EX_POS_SCALE) where exact, else float32."""
    code = np.rint(np.asarray(pos, np.float64) * EX_POS_SCALE)
    if np.array_equal(code / EX_POS_SCALE, pos) and code.min(initial=0) >= 0 \
            and code.max(initial=0) <= EX_POS_SCALE:
        return code.astype(np.uint16)
    return np.asarray(pos, np.float32)


def first_use_order(leaf_corner: np.ndarray, ex_ids: np.ndarray, n: int) -> np.ndarray:
    """(n,) sample ids in the order of their first use: by the leaves' corners in node order,
    then by the extra samples, then unused ones in id order (new id -> old id). Samples of one
    direction tree and neighbouring cells get neighbouring ids, so their codes and the leaves'
    corner ids differ little from one to the next. Applied to a tree already in this order it
    is the identity."""
    uses = np.concatenate([np.asarray(leaf_corner, np.int64).reshape(-1),
                           np.asarray(ex_ids, np.int64).reshape(-1), np.arange(n)])
    uses = uses[uses >= 0]
    ids, first = np.unique(uses, return_index=True)
    return ids[np.argsort(first, kind="stable")]


def save(tree: RITree, path, header_extra: dict | None = None, cancel=None,
         progress=None) -> None:
    """Write ``tree`` to a .rit cache file (atomically, compressed; see ritree.cache), its header
    extended by ``header_extra``; ``cancel()`` turning true gives up (cache.SaveCancelled);
    ``progress(fraction)`` follows the compression."""
    arrays = tree.arrays()
    save_tree(path, {**tree.header(), **(header_extra or {})}, arrays, tree.file_filters(arrays),
              cancel, progress)


def load(path, scene=None) -> RITree:
    """Read a .rit cache file (header and array table checked before any array is read:
    ``check_file``). With ``scene``, refuse a tree baked for another geometry or material of
    the scene's object (StaleTreeError) or for other patch classes."""
    expect = None if scene is None else fingerprint(scene.object, scene.render.max_events)
    header, arrays = load_tree(path, expect_fingerprint=expect, check=check_file)
    try:
        tree = RITree.from_parts(header, arrays)
    except TreeCacheError as e:
        raise TreeCacheError(f"{path}: {e}") from None
    if scene is not None and tree.class_of.tolist() != [p.class_id for p in
                                                        scene.object.patches]:
        raise TreeCacheError(f"{path}: the RI-Tree's patch classes are not its object's; "
                             "re-bake the tree")
    return tree
