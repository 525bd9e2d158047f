"""riray_addon/reuse.py without Blender: the memo keeps the last part of each kind and gives it
back for an equal key only; the keys follow the exported content (a moved control point,
vertex, light, material or world, a rewritten cache file), not names; a moving camera leaves
a shader graph that never reads camera coordinates unchanged."""

import copy
import gc
import importlib.util
import os
import weakref
from pathlib import Path

import numpy as np
import pytest

from riray.scene import samples
from riray.scene.graph import GraphNode, Link, ShaderGraph
from riray.scene.model import Material, World

ROOT = Path(__file__).resolve().parents[2]
_spec = importlib.util.spec_from_file_location("riray_addon_reuse",
                                               ROOT / "riray_addon" / "reuse.py")
reuse = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(reuse)


class Part:
    """A stand-in for a built part (weak references show when it is let go)."""

    def __init__(self, tag):
        self.tag = tag


def test_memo_keeps_only_the_last_part_of_each_kind():
    memo, built = reuse.Memo(), []

    def build(tag):
        return lambda: built.append(tag) or Part(tag)

    first, reused = memo.get("object", "k1", build("a"))
    again, reused_again = memo.get("object", "k1", build("b"))
    assert (reused, reused_again) == (False, True) and again is first and built == ["a"]
    memo.get("environment", "k1", build("e"))               # another kind: kept beside it
    old = weakref.ref(first)
    del first, again
    second, reused = memo.get("object", "k2", build("c"))
    gc.collect()
    assert not reused and second.tag == "c" and old() is None   # the old part is let go
    assert sorted(memo.kinds()) == ["environment", "object"]
    third, reused = memo.get("object", "k1", build("d"))      # k1 was dropped: built again
    assert not reused and third.tag == "d" and built == ["a", "e", "c", "d"]
    memo.clear()
    assert memo.kinds() == []


def test_frame_parts_time_and_name_what_was_reused():
    parts = reuse.FrameParts(reuse.Memo())
    parts.get("object", lambda: "k", lambda: Part("a"))
    parts.timed("query", lambda: Part("q"))
    later = reuse.FrameParts(parts.memo)
    later.get("object", lambda: "k", lambda: Part("b"))
    later.timed("proxy", lambda: None, reused=True)
    assert parts.reused == [] and later.reused == ["object", "proxy"]
    assert set(parts.seconds) == {"object", "query"} and min(later.seconds.values()) >= 0.0


def keys(scene):
    obj = reuse.object_key(scene.object)
    return obj, reuse.environment_key(scene, obj)


def test_keys_follow_the_exported_content():
    scene = samples.build("vase_mirror")
    assert any(light.shadows for light in scene.lights)     # the object is a shadow caster
    obj0, env0 = keys(scene)
    assert keys(copy.deepcopy(scene)) == (obj0, env0)       # equal content, equal keys
    moved = copy.deepcopy(scene)
    moved.object.patches[0].surface.points[1, 1, 2] += 1e-9
    obj1, env1 = keys(moved)
    assert obj1 != obj0 and env1 != env0                   # its shadow moved too
    renamed = copy.deepcopy(scene)
    renamed.object.name, renamed.object.material.tint = "other", (0.5, 0.5, 0.5)
    assert keys(renamed) == (obj0, env0)                   # the tracer reads neither
    edits = {"vertex": lambda s: s.meshes[0].vertices.__setitem__((0, 0), 7.0),
             "triangle": lambda s: s.meshes[0].triangles.__setitem__(
                 0, s.meshes[0].triangles[0, ::-1]),
             "light": lambda s: setattr(s.lights[0], "position", (0.0, 0.0, 1.0)),
             "power": lambda s: setattr(s.lights[0], "power", 1.0),
             "material": lambda s: setattr(next(iter(s.materials.values())).color,
                                           "color", (1.0, 0.0, 0.0)),
             "world": lambda s: setattr(s.world, "strength", 2.0)}
    for what, edit in edits.items():
        changed = copy.deepcopy(scene)
        edit(changed)
        obj, env = keys(changed)
        assert obj == obj0 and env != env0, what
    no_shadows = copy.deepcopy(scene)
    for light in no_shadows.lights:
        light.shadows = False
    moved_too = copy.deepcopy(no_shadows)
    moved_too.object.patches[0].surface.points[1, 1, 2] += 1e-9
    assert keys(no_shadows)[1] == keys(moved_too)[1]       # no shadows: the object is not in it


def coords_graph(camera_matrix, output: str) -> ShaderGraph:
    """An emission of the Texture Coordinate node's ``output``."""
    return ShaderGraph(nodes=[GraphNode("tc", "tex_coord", props={"camera_matrix": camera_matrix}),
                              GraphNode("out", "emission", links={"color": Link("tc", output)})],
                       output=Link("out", "emission"))


def test_camera_matrix_counts_only_where_the_graph_reads_it():
    m0 = tuple(tuple(float(i == j) for j in range(4)) for i in range(4))
    m1 = (m0[0], m0[1], m0[2][:3] + (2.0,), m0[3])          # the camera moved
    for output, same in (("uv", True), ("camera", False)):
        a, b = (Material("m", kind="nodes", graph=coords_graph(m, output)) for m in (m0, m1))
        assert (reuse.fingerprint(a) == reuse.fingerprint(b)) is same, output
        wa, wb = (World(kind="nodes", graph=coords_graph(m, output)) for m in (m0, m1))
        assert (reuse.fingerprint(wa) == reuse.fingerprint(wb)) is same, output


def test_tree_key_follows_the_file(tmp_path):
    path = tmp_path / "x.rit"
    path.write_bytes(b"tree one")
    k0 = reuse.tree_key(str(path), "obj")
    assert reuse.tree_key(str(path), "obj") == k0
    assert reuse.tree_key(str(path), "other object") != k0
    st = os.stat(path)
    path.write_bytes(b"tree two")                            # same size, rewritten
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns + 1))
    assert reuse.tree_key(str(path), "obj") != k0
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))
    path.write_bytes(b"tree three")                          # another size
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert reuse.tree_key(str(path), "obj") != k0
    k1 = reuse.tree_key(str(path), "obj")
    other = tmp_path / "new.rit"                            # a bake replaces the file
    other.write_bytes(b"tree four!")
    os.utime(other, ns=(st.st_atime_ns, st.st_mtime_ns))
    os.replace(other, path)
    assert reuse.tree_key(str(path), "obj") != k1


def test_fingerprint_values():
    a = np.arange(12.0).reshape(3, 4)
    assert reuse.fingerprint(a) == reuse.fingerprint(np.asfortranarray(a))
    assert reuse.fingerprint(a) != reuse.fingerprint(a.reshape(4, 3))
    assert reuse.fingerprint(a) != reuse.fingerprint(a.astype(np.float32))
    assert reuse.fingerprint(1) != reuse.fingerprint(1.0) != reuse.fingerprint(True)
    assert reuse.fingerprint({"a": 1, "b": 2}) == reuse.fingerprint({"b": 2, "a": 1})
    with pytest.raises(TypeError):          # never by identity: an unknown value is an error
        reuse.fingerprint(object())
