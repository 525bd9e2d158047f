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

from .answers import COL
from .cache import TreeCacheError, fingerprint, load_tree, save_tree
from .derive import fill
from .params import BOUNDARY, EX_POS_SCALE, PATH_CHANGE, TREE_LAYOUT, UNVERIFIED, BakeParams
from .quadtree import CORNERS, DenseLocator, Forest
from .samples import SAMPLE_FIELDS, PackedSamples, Samples, SampleTable
from ..trace.objectfn import RECORDED_EVENTS

# Re-exported: the tree's parts are imported from here.
__all__ = ["BOUNDARY", "EX_POS_SCALE", "PATH_CHANGE", "SAMPLE_FIELDS", "TREE_LAYOUT",
           "UNVERIFIED", "BakeParams", "PackedSamples", "RITree", "SampleTable", "Samples",
           "check_file", "first_use_order", "load", "save"]


@dataclass
class RITree:
    """The tree: its bake settings, box, forests, samples, extra samples and the bake's
    measured errors and flags (see the module docstring)."""

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
    ex_corner: np.ndarray             # (E, 4) corner slots: see bake.extras
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

    @cached_property
    def class_paths(self) -> np.ndarray:
        """(S,) uint64: each sample's path as the sequence of the classes (patch groups) its
        first hit and recorded events meet, hashed (``group_sequence_key``). Paths that differ
        only in which patch of one smooth group they meet (a reflection just either side of a
        seam inside the teapot's body) share it; the ray-tree hash (``table.tree``) tells them
        apart. Event kinds are not in it: on a mirror every event reflects."""
        tab = self.table
        pats = np.concatenate([tab.patch[:, None], tab.ev_patch], axis=1).astype(np.int64)
        return group_sequence_key(np.where(pats >= 0, self.class_of[np.maximum(pats, 0)], -1))

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
        unless they are a layout-6 tree: header fields, dtypes and shapes (``check_file``),
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
# Loaded and queried, a sample costs about this many bytes of memory (its decoded fields, its
# row of the query's sample table, the locators: 473 measured on glass_sphere's camera tree),
# and a file may ask for at most LOADED_PER_FILE_BYTE times its bytes that way (or
# MIN_LOADED_BYTES): glass_sphere's camera and full trees ask for 60-145 times theirs; samples
# that miss the object compress to almost nothing, so without this a 1 MB file could ask for
# gigabytes (with it, a file needs 4 MB to ask for 2 GiB).
LOADED_SAMPLE_BYTES = 512
LOADED_PER_FILE_BYTE = 512
MIN_LOADED_BYTES = 256 << 20
_IDS = ("<i4", "<i8")
_INTS = ("|i1", "<i2", "<i4", "<i8")


def _file_table(c: dict) -> dict:
    """Array name -> (allowed dtype strings, shape) of a layout-6 tree with counts ``c``."""
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
        "s.out_o_q": (("<u2",), (c["Ho"], 3)),
        "s.ev_patch": (("<i2", "<i4"), (H, RECORDED_EVENTS)),
        "s.ev_uv_q": (("<u2",), (H, 2 * RECORDED_EVENTS))}


def check_file(header: dict, table: dict, file_bytes: int | None = None) -> None:
    """TreeCacheError (saying to re-bake) unless ``header`` and ``table`` ({name: (dtype,
    shape)}, as cache.load_tree's ``check`` hears them before reading any array) are a
    layout-6 tree's: the header fields the reader uses (type and range), exactly the tree's
    arrays, each of its dtype and of the shape the tree's counts give, the counts agreeing
    (a forest of quadtrees, samples and hits) and, with ``file_bytes``, the arrays claiming
    at most MAX_EXPANSION times the file's bytes and its samples needing at most
    LOADED_PER_FILE_BYTE times them once loaded."""
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
    loaded = claimed + LOADED_SAMPLE_BYTES * max(c["S"], 0)
    if file_bytes is not None and loaded > max(LOADED_PER_FILE_BYTE * file_bytes,
                                               MIN_LOADED_BYTES):
        raise bad(f"its {c['S']} samples would need about {loaded >> 20} MiB loaded, more than "
                  f"{LOADED_PER_FILE_BYTE} times the file's {file_bytes} bytes")


def _check_values(a: dict, params: dict) -> None:
    """ValueError unless every id in ``a`` (a layout-6 tree's arrays, ``check_file``'s
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
    within("s.ev_patch", -1, len(a["class_of"]))
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


# splitmix64's multiplier and shifts: every bit of a class id reaches every bit of the key.
_MIX = np.uint64(0xBF58476D1CE4E5B9)


def group_sequence_key(groups: np.ndarray) -> np.ndarray:
    """(S,) uint64 keys of (S, K) sequences of class ids (-1: no event): equal sequences get
    equal keys, different ones different keys but with probability about K * 2^-64."""
    key = np.zeros(len(groups), np.uint64)
    with np.errstate(over="ignore"):
        for col in groups.T:
            key = (key ^ (col + 2).astype(np.uint64)) * _MIX
            key ^= key >> np.uint64(31)
    return key
