"""The tree's ray samples: as traced (``Samples``, float32), as packed codes (``PackedSamples``:
what bake shards return and a cache file holds) and decoded once for rendering
(``SampleTable``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..trace.objectfn import RECORDED_EVENTS, one_reflection_hash
from .answers import COL
from .codec import (decode_params, decode_points, decode_unit_vectors, encode_params, encode_points,
                    encode_unit_vectors)
from .derive import kept_rows, valid_codes

SAMPLE_FIELDS = ("out_o", "out_d", "point", "normal", "patch", "null", "tree", "uv", "ev_patch",
                 "ev_uv")


@dataclass
class Samples:
    """Ray samples (S of them); float32 geometry, int32 patch ids; ``uv`` (S, 2) float32 the
    first hit's normalized patch parameters (ObjectRays.uv; with an EventRecord its
    ``first_uv``: on a mesh, the triangle); ``ev_patch`` (S, K) int32 and ``ev_uv`` (S, K, 2)
    float32 the patch (-1: none) and recorded parameters of the hits of events 1..K after the
    first (trace.objectfn.EventRecord, K = RECORDED_EVENTS)."""

    out_o: np.ndarray
    out_d: np.ndarray
    point: np.ndarray
    normal: np.ndarray
    patch: np.ndarray
    null: np.ndarray
    tree: np.ndarray
    uv: np.ndarray | None = None      # None: zeros (hand-made samples without patch parameters)
    ev_patch: np.ndarray | None = None  # None: no recorded events (-1)
    ev_uv: np.ndarray | None = None     # None: zeros

    def __post_init__(self):
        n = len(self.patch)
        if self.uv is None:
            self.uv = np.zeros((n, 2), np.float32)
        if self.ev_patch is None:
            self.ev_patch = np.full((n, RECORDED_EVENTS), -1, np.int32)
        if self.ev_uv is None:
            self.ev_uv = np.zeros((n, RECORDED_EVENTS, 2), np.float32)

    @classmethod
    def empty(cls) -> "Samples":
        z3 = np.zeros((0, 3), np.float32)
        return cls(z3, z3.copy(), z3.copy(), z3.copy(), np.zeros(0, np.int32),
                   np.zeros(0, bool), np.zeros(0, np.uint32), np.zeros((0, 2), np.float32))

    @classmethod
    def from_rays(cls, res, record=None) -> "Samples":
        """From an ``ObjectRays`` result (trace.objectfn) and its EventRecord (None: none)."""
        return cls(res.out_o.astype(np.float32) if hasattr(res, "out_o") else
                   res.out_origin.astype(np.float32), res.out_dir.astype(np.float32),
                   res.point.astype(np.float32), res.normal.astype(np.float32),
                   res.patch.astype(np.int32), res.null.astype(bool), res.tree.astype(np.uint32),
                   (res.uv if record is None else record.first_uv).astype(np.float32),
                   None if record is None else record.patch.astype(np.int32),
                   None if record is None else record.uv.astype(np.float32))

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
                             ev_patch=self.ev_patch.astype(
                                 np.int16 if self.ev_patch.max(initial=0) < 32767 else np.int32),
                             ev_uv_q=encode_params(self.ev_uv.reshape(-1, 2)).reshape(
                                 len(self), 2 * RECORDED_EVENTS),
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
    ev_patch: np.ndarray    # (S, K) int16/int32 the patches of events 1..K (-1: none)
    ev_uv_q: np.ndarray     # (S, 2K) uint16 their normalized patch parameter codes
    patch: np.ndarray       # (S,) int16/int32
    null: np.ndarray        # (S,) bool
    tree: np.ndarray        # (S,) uint32 ray-tree hash
    lo: np.ndarray
    hi: np.ndarray
    geom: np.ndarray | None = None  # (S,) uint8 derive.GEOM_* (None: all stored)
    pending: bool = False   # the derived hits' point and normal codes are not computed yet

    FIELDS = ("out_o_q", "out_d_q", "point_q", "normal_q", "uv_q", "ev_patch", "ev_uv_q",
              "patch", "null", "tree")
    CODES = FIELDS[:7]          # the output codes (stored for hits only)
    CODE_FORMS = {"out_o_q": (np.uint16, 3), "out_d_q": (np.int16, 2), "point_q": (np.uint16, 3),
                  "normal_q": (np.int16, 2), "uv_q": (np.uint16, 2),
                  "ev_patch": (None, RECORDED_EVENTS),      # int16 or int32, as patch
                  "ev_uv_q": (np.uint16, 2 * RECORDED_EVENTS)}   # dtype, columns
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

    @property
    def ev_uv(self) -> np.ndarray:
        return decode_params(self.ev_uv_q.reshape(-1, 2)).reshape(len(self), RECORDED_EVENTS, 2)

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
            ok = q.dtype in (np.int16, np.int32) if dtype is None else q.dtype == dtype
            if not ok or q.ndim != 2 or q.shape[1] != cols:
                name = "int16/int32" if dtype is None else np.dtype(dtype).name
                raise ValueError(f"s.{k} is not (n, {cols}) {name} codes")
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
            codes[k] = np.full((n,) + q.shape[1:], -1 if k == "ev_patch" else 0, q.dtype)
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
    ev_patch: np.ndarray    # (S, K) int32 the patches of events 1..K (-1: none)
    ev_uv: np.ndarray       # (S, K, 2) float32 their normalized patch parameters

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
                   once=once, ev_patch=np.asarray(samples.ev_patch, np.int32),
                   ev_uv=np.asarray(samples.ev_uv, np.float32))
