"""RI-Tree cache files beside the .blend, and whether a cache is fresh or stale.

Default path: ``//<blend name>.<object name>.rit`` (relative to the .blend, so it moves with
it). "//" paths of an unsaved file lie in Blender's temporary folder. Where a managed cache
(no explicit cache file) was baked is kept in ``object.riray.baked_cache``, so renaming the
object keeps its cache. On save, caches follow the file: a "//" cache is copied to where the
same setting points beside the saved .blend (a managed one renamed after the object's current
name), and the old file is removed when it only served this .blend (unsaved, or the object was
renamed); Save As keeps the old .blend's cache. Absolute cache paths never move. A cache is *fresh* when
its header's fingerprint equals the object's current ``export.object_fingerprint`` (geometry,
transform, classes, material), *stale* otherwise. Fingerprints are memoized per object until the
next depsgraph update, so panels can ask on every redraw.
"""

from __future__ import annotations

import os
import shutil

import bpy

from . import backend
from .export import object_fingerprint
from .jobs import running_job
from .report import ExportError

CACHE_EXT = ".rit"
_update_counter = [0]
_fp_memo: dict = {}
_header_memo: dict = {}
_saving: dict = {}          # save_pre -> save_post: what was copied and changed


def _base(blend: str) -> str:
    """Folder "//" stands for: the .blend's, or Blender's temporary folder while unsaved."""
    if blend:
        return os.path.dirname(os.path.abspath(blend))
    return bpy.app.tempdir or os.path.join(os.path.expanduser("~"), ".cache")


def resolve(setting: str, blend: str | None = None) -> str:
    """Absolute path of a cache path setting; "//" is relative to ``blend`` (default: the open
    file)."""
    blend = bpy.data.filepath if blend is None else blend
    if setting.startswith("//"):
        return os.path.normpath(os.path.join(_base(blend), setting[2:]))
    return os.path.abspath(setting)


def as_setting(path: str) -> str:
    """``path`` as a setting: "//..." when it lies under the open file's "//" folder."""
    rel = os.path.relpath(path, _base(bpy.data.filepath))
    return path if rel.startswith("..") or os.path.isabs(rel) else "//" + rel.replace(os.sep, "/")


def default_relpath(obj, blend: str | None = None) -> str:
    """``//<blend name>.<object name>.rit`` ("untitled" while the file is unsaved)."""
    blend = bpy.data.filepath if blend is None else blend
    stem = os.path.splitext(os.path.basename(blend))[0] if blend else "untitled"
    return f"//{stem}.{bpy.path.clean_name(obj.name)}{CACHE_EXT}"


def setting(obj) -> str:
    """The cache path setting in use: the explicit cache file, else where the last bake went,
    else the default."""
    p = obj.riray
    return p.cache_file or p.baked_cache or default_relpath(obj)


def cache_path(obj, blend: str | None = None) -> str:
    """Absolute path of the object's cache file."""
    return resolve(setting(obj), blend)


def bake_target(obj) -> str:
    """Where a new bake of ``obj`` goes: its cache path, unless that managed cache is another
    object's too (a duplicate copies the settings), then its own default path."""
    path = cache_path(obj)
    if not obj.riray.cache_file and obj.riray.baked_cache and any(
            o != obj and cache_path(o) == path for o in bpy.data.objects):
        return resolve(default_relpath(obj))
    return path


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


def tree_status(obj, depsgraph, memo: bool = True, current: str | None = None) -> dict:
    """{"state": missing | invalid | stale | fresh, "path", "message", "doc"}; ``current``: the
    object's fingerprint when the caller has it (else it is computed)."""
    path = cache_path(obj)
    doc = header(path)
    if doc is None:
        state = "invalid" if os.path.exists(path) else "missing"
        msg = (f"no RI-Tree cache ({bpy.path.relpath(path) if bpy.data.filepath else path})"
               if state == "missing" else f"{path} is not a riray cache file")
        return {"state": state, "path": path, "message": msg, "doc": None}
    baked = doc.get("meta", {}).get("fingerprint", "")
    current = fingerprint(obj, depsgraph, memo) if current is None else current
    if not baked or baked != current:
        return {"state": "stale", "path": path, "doc": doc,
                "message": "the RI-Tree is stale (geometry, transform or material changed "
                           "since the bake)"}
    return {"state": "fresh", "path": path, "doc": doc, "message": "the RI-Tree is up to date"}


# --------------------------------------------------------------------------- handlers
def _copy(src: str, dst: str) -> None:
    os.makedirs(os.path.dirname(dst), exist_ok=True)
    tmp = f"{dst}.tmp{os.getpid()}"
    shutil.copyfile(src, tmp)
    os.replace(tmp, dst)


@bpy.app.handlers.persistent
def _on_save_pre(filepath="", *_args):
    """Copy every "//" cache to where its setting points beside the file being saved, and
    point managed caches there (the saved file must hold the new settings)."""
    old_blend, new_blend = bpy.data.filepath, os.path.abspath(filepath or bpy.data.filepath)
    _saving.clear()
    _saving.update(blend=old_blend, copies=[], settings={})
    for obj in bpy.data.objects:
        old = cache_path(obj)
        explicit = obj.riray.cache_file
        if running_job(obj.name) or not os.path.isfile(old) or (
                explicit and not explicit.startswith("//")):
            continue
        new_setting = explicit or default_relpath(obj, new_blend)
        new = resolve(new_setting, new_blend)
        if new != old:
            try:
                _copy(old, new)
            except OSError as exc:
                print(f"riray: {obj.name}: could not copy the cache {old} -> {new}: {exc}")
                continue
            _saving["copies"].append((old, new))
        if not explicit and obj.riray.baked_cache != new_setting:
            _saving["settings"][obj.name] = obj.riray.baked_cache
            obj.riray.baked_cache = new_setting


def _restore_settings() -> None:
    for name, value in _saving.get("settings", {}).items():
        obj = bpy.data.objects.get(name)
        if obj is not None:
            obj.riray.baked_cache = value


@bpy.app.handlers.persistent
def _on_save_post(filepath="", *_args):
    """Saved: remove old caches that only served this file (it was unsaved, or an object was
    renamed); a copy saved with "Save Copy" leaves the open file's settings as they were."""
    if not _saving:
        return
    saved_as = os.path.abspath(filepath) if filepath else bpy.data.filepath
    if bpy.data.filepath != saved_as:                  # Save Copy: the open file is unchanged
        _restore_settings()
    elif _saving["blend"] in ("", saved_as):
        in_use = {cache_path(o) for o in bpy.data.objects}
        for old, _ in _saving["copies"]:
            if old not in in_use and os.path.isfile(old):
                os.remove(old)
    _saving.clear()
    forget()


@bpy.app.handlers.persistent
def _on_save_fail(*_args):
    """The save failed: settings and caches as before."""
    _restore_settings()
    for _, new in _saving.get("copies", []):
        if os.path.isfile(new):
            os.remove(new)
    _saving.clear()


@bpy.app.handlers.persistent
def _on_depsgraph_update(scene, depsgraph=None):
    _update_counter[0] += 1


def forget() -> None:
    """Forget the memoized fingerprints and cache headers: statuses are computed afresh."""
    _update_counter[0] += 1
    _fp_memo.clear()
    _header_memo.clear()


@bpy.app.handlers.persistent
def _on_load(*_args):
    """After a .blend is loaded: caches are found again from object.riray."""
    forget()


def _handlers():
    h = bpy.app.handlers
    return ((h.depsgraph_update_post, _on_depsgraph_update), (h.load_post, _on_load),
            (h.frame_change_post, _on_depsgraph_update), (h.save_pre, _on_save_pre),
            (h.save_post, _on_save_post), (h.save_post_fail, _on_save_fail))


def register():
    for lst, fn in _handlers():
        lst.append(fn)


def unregister():
    for lst, fn in _handlers():
        if fn in lst:
            lst.remove(fn)
