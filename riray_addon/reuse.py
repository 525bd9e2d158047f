"""What the "RI-Tree Preview" engine keeps between frames and renders: the parts of a frame that
are slow to build and rarely change - the object's PatchTracer (with its occlusion proxy), the
loaded RI-Tree and the environment (its mesh BVH, lights, world, shadow occluder).

Each part is kept under a *key* that covers everything it is built from; a frame whose key
equals the kept one reuses the part, any other builds it anew and replaces it. Keys are content
fingerprints of the exported core scene (blake2b of the numpy arrays' bytes and of every other
value; ``fingerprint``), not names, so an animated mesh, light, material, world or control
point is picked up: the tracer's key is the object's patches, the environment's its meshes,
materials, lights and world (and the object's patches where a light casts shadows: the object
is then a shadow caster), the tree's the cache file's path, size and modification time with the
object's key (a loaded tree derives its hit points from the tracer). The query over the tree is
made anew each frame (cheap once tree and tracer are kept): it reads the frame's options.

Only the last part of each kind is kept (``Memo``): memory stays at one scene's worth. No bpy
and no core imports: the engine passes the builders, and the logic is tested without Blender.
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
import time

DIGEST_BYTES = 20
# A Texture Coordinate node's camera matrix changes with every camera move; a graph that never
# reads the node's Camera output does not depend on it (core/trace/nodes/inputs.py).
COORD_NODE, CAMERA_OUTPUT, CAMERA_PROP = "tex_coord", "camera", "camera_matrix"


class Memo:
    """The last value built of each kind, with its key."""

    def __init__(self):
        self._kept: dict = {}       # kind -> (key, value)

    def get(self, kind: str, key, build):
        """(value, reused): the kept value of ``kind`` when its key equals ``key``, else
        ``build()``, kept in its place (the old value is let go first, so two never live
        together)."""
        kept = self._kept.get(kind)
        if kept is not None and kept[0] == key:
            return kept[1], True
        self._kept.pop(kind, None)
        value = build()
        self._kept[kind] = (key, value)
        return value, False

    def kinds(self) -> list[str]:
        return list(self._kept)

    def clear(self) -> None:
        self._kept.clear()


MEMO = Memo()     # the engine's, for the life of the Blender session (cleared on file load)


class FrameParts:
    """The parts one frame uses: taken from a Memo or built, each timed (its key's fingerprint
    included); ``seconds`` by part, ``reused`` the parts that were not built."""

    def __init__(self, memo: Memo):
        self.memo, self.seconds, self.reused = memo, {}, []

    def get(self, kind: str, key, build):
        """The part ``kind`` under the key ``key()``, built by ``build()`` when not kept."""
        t0 = time.perf_counter()
        value, reused = self.memo.get(kind, key(), build)
        self._done(kind, t0, reused)
        return value

    def timed(self, kind: str, build, reused: bool = False):
        """``build()``, timed as the part ``kind`` (``reused``: it only looks the part up)."""
        t0 = time.perf_counter()
        value = build()
        self._done(kind, t0, reused)
        return value

    def _done(self, kind: str, t0: float, reused: bool) -> None:
        self.seconds[kind] = time.perf_counter() - t0
        if reused:
            self.reused.append(kind)


# --------------------------------------------------------------------------- keys
def fingerprint(*values) -> str:
    """blake2b of ``values``: numpy arrays by dtype, shape and bytes, dataclasses field by field,
    dicts (sorted by key), lists, tuples and scalars by value; TypeError for anything else."""
    h = hashlib.blake2b(digest_size=DIGEST_BYTES)
    for v in values:
        _feed(h, v)
    return h.hexdigest()


def object_key(obj) -> str:
    """Key of a PatchTracer: the specular object's patches (it never reads the material)."""
    return fingerprint(obj.patches)


def environment_key(scene, obj_key: str) -> str:
    """Key of an environment (core build_environment): meshes, materials, lights, world, and
    the object (``obj_key``) when it casts shadows."""
    shadows = any(light.shadows for light in scene.lights)
    return fingerprint(scene.meshes, scene.materials, scene.lights, scene.world,
                       obj_key if shadows else None)


def tree_key(path: str, obj_key: str) -> tuple:
    """Key of a loaded RI-Tree: the file (path, inode - a bake replaces the file -, size,
    modification time) and the object it derives its hit points from (OSError when the file
    is gone)."""
    st = os.stat(path)
    return path, st.st_ino, st.st_size, st.st_mtime_ns, obj_key


def _feed(h, v) -> None:
    if hasattr(v, "__array_interface__") and not v.dtype.hasobject:   # numpy arrays, scalars
        a = v.__array__()
        h.update(f"a{a.dtype.str}{a.shape}".encode())
        h.update(memoryview(a.ravel(order="C")).cast("B"))
    elif v is None or isinstance(v, (str, int, float, complex)):
        h.update(f"{type(v).__name__}:{v!r};".encode())
    elif type(v).__name__ == "ShaderGraph":
        _feed(h, _graph_view(v))
    elif dataclasses.is_dataclass(v) and not isinstance(v, type):
        h.update(f"d{type(v).__name__}".encode())
        for f in dataclasses.fields(v):
            h.update(f.name.encode())
            _feed(h, getattr(v, f.name))
    elif isinstance(v, dict):
        h.update(f"m{len(v)}".encode())
        for k in sorted(v, key=repr):
            _feed(h, k)
            _feed(h, v[k])
    elif isinstance(v, (list, tuple)):
        h.update(f"l{len(v)}".encode())
        for x in v:
            _feed(h, x)
    else:
        raise TypeError(f"cannot fingerprint a {type(v).__name__}")


def _graph_view(graph) -> tuple:
    """A shader graph as fingerprinted: its nodes, with a Texture Coordinate node's camera
    matrix left out where nothing reads the node's Camera output."""
    read = {(lk.node, lk.output) for n in graph.nodes for lk in n.links.values()}
    read.add((graph.output.node, graph.output.output))
    nodes = []
    for n in graph.nodes:
        props = n.props
        if n.type == COORD_NODE and (n.name, CAMERA_OUTPUT) not in read:
            props = {k: v for k, v in props.items() if k != CAMERA_PROP}
        nodes.append((n.name, n.type, n.inputs, n.links, props))
    return nodes, graph.output, graph.version
