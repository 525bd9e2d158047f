"""RI-Tree cache files beside the .blend, and whether a cache is fresh or stale.

Default path: ``//<blend name>.<object name>.rit`` (relative to the .blend, so it moves with
it); an unsaved file uses Blender's temporary folder until it is saved. A cache is *fresh* when
its header's fingerprint equals the object's current ``export.object_fingerprint`` (geometry,
transform, classes, material), *stale* otherwise. Fingerprints are memoized per object until the
next depsgraph update, so panels can ask on every redraw.
"""

from __future__ import annotations

import os

import bpy

from . import backend
from .export import object_fingerprint
from .report import ExportError

CACHE_EXT = ".rit"
_update_counter = [0]
_fp_memo: dict = {}
_header_memo: dict = {}


def default_relpath(obj) -> str:
    name = bpy.path.clean_name(obj.name)
    blend = bpy.data.filepath
    if blend:
        stem = os.path.splitext(os.path.basename(blend))[0]
        return f"//{stem}.{name}{CACHE_EXT}"
    return os.path.join(bpy.app.tempdir or os.path.join(os.path.expanduser("~"), ".cache"),
                        f"riray.{name}{CACHE_EXT}")


def cache_path(obj) -> str:
    """Absolute path of the object's cache file."""
    rel = obj.riray.cache_file or default_relpath(obj)
    return os.path.abspath(bpy.path.abspath(rel))


def check_writable(path: str) -> None:
    """ExportError unless a cache file can be written at ``path``: its folder exists or can be
    created, and is writable."""
    if os.path.isdir(path):
        raise ExportError(f"cache file {path} is a folder")
    base = os.path.dirname(path)
    while not os.path.exists(base):
        base = os.path.dirname(base)
    if not os.path.isdir(base):
        raise ExportError(f"cannot write the cache file {path}: {base} is a file, not a folder")
    if not os.access(base, os.W_OK | os.X_OK):
        raise ExportError(f"cannot write the cache file {path}: {base} is not writable")


def header(path: str) -> dict | None:
    """The cache header (memoized on path + mtime + size)."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    key = (path, st.st_mtime_ns, st.st_size)
    if key not in _header_memo:
        if len(_header_memo) > 64:
            _header_memo.clear()
        _header_memo[key] = backend.read_header(path)
    return _header_memo[key]


def fingerprint(obj, depsgraph, memo: bool = True) -> str:
    """The object's current fingerprint; memoized (UI redraws) unless ``memo`` is False or
    Blender runs in background mode (scripts may change data without a depsgraph update)."""
    if not memo or bpy.app.background:
        return object_fingerprint(obj, depsgraph)
    key = (obj.name, _update_counter[0], depsgraph.mode)
    if key not in _fp_memo:
        if len(_fp_memo) > 256:
            _fp_memo.clear()
        _fp_memo[key] = object_fingerprint(obj, depsgraph)
    return _fp_memo[key]


def tree_status(obj, depsgraph, memo: bool = True) -> dict:
    """{"state": missing | invalid | stale | fresh, "path", "message", "doc"}."""
    path = cache_path(obj)
    doc = header(path)
    if doc is None:
        state = "invalid" if os.path.exists(path) else "missing"
        msg = (f"no RI-Tree cache ({bpy.path.relpath(path) if bpy.data.filepath else path})"
               if state == "missing" else f"{path} is not a riray cache file")
        return {"state": state, "path": path, "message": msg, "doc": None}
    baked = doc.get("meta", {}).get("fingerprint", "")
    current = fingerprint(obj, depsgraph, memo)
    if not baked or baked != current:
        return {"state": "stale", "path": path, "doc": doc,
                "message": "the RI-Tree is stale (geometry, transform or material changed "
                           "since the bake)"}
    return {"state": "fresh", "path": path, "doc": doc, "message": "the RI-Tree is up to date"}


# --------------------------------------------------------------------------- handlers
@bpy.app.handlers.persistent
def _on_depsgraph_update(scene, depsgraph=None):
    _update_counter[0] += 1


@bpy.app.handlers.persistent
def _on_load(*_args):
    """After a .blend is loaded: forget memos; caches are found again from object.riray."""
    _update_counter[0] += 1
    _fp_memo.clear()
    _header_memo.clear()


def register():
    bpy.app.handlers.depsgraph_update_post.append(_on_depsgraph_update)
    bpy.app.handlers.load_post.append(_on_load)
    bpy.app.handlers.frame_change_post.append(_on_depsgraph_update)


def unregister():
    for lst, fn in ((bpy.app.handlers.depsgraph_update_post, _on_depsgraph_update),
                    (bpy.app.handlers.load_post, _on_load),
                    (bpy.app.handlers.frame_change_post, _on_depsgraph_update)):
        if fn in lst:
            lst.remove(fn)
