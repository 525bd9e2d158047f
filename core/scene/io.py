"""The JSON scene format, version 1 (specified in docs/scene-format.md): scene files.

``load_scene`` / ``scene_from_dict`` validate everything and raise :class:`SceneError` naming the
JSON path of the offending field and the problem, e.g.
``object.patches[3].weights[2][1]: weight must be > 0 (got -1.0)``. ``save_scene`` /
``scene_to_dict`` write the canonical form (floats with repr precision, so save -> load is exact);
``save_scene`` validates the dict it writes and replaces the file atomically.

Modules: ``io`` (files: bounded reading, JSON text, atomic saving), ``parse`` (dict -> Scene),
``format`` (the format's kinds and fields; Scene -> dict), ``validate`` (field checks, limits,
SceneError), ``images`` (image files a scene refers to).
"""

from __future__ import annotations

import json
import os
import sys

from ..files import atomic_write, read_regular
from ..imageio import MAX_IMAGE_SIDE
from .format import scene_to_dict
from .images import in_memory_images
from .model import Scene
from .parse import parse_scene, look_at_matrix, scene_from_dict
from .validate import MAX_COORD, SceneError, at_key

__all__ = ["MAX_COORD", "MAX_IMAGE_SIDE", "MAX_SCENE_BYTES", "SceneError", "in_memory_images",
           "load_scene", "look_at_matrix", "save_scene", "scene_from_dict", "scene_to_dict"]

# Largest scene file read, bytes: JSON parses to several times its size in Python objects.
MAX_SCENE_BYTES = 1 << 28


def _no_duplicates(pairs):
    d = dict(pairs)
    if len(d) != len(pairs):                # linear time: a set, not a count per key
        seen = set()
        for k, _ in pairs:
            if k in seen:
                raise SceneError(f"duplicate key {k!r} in a JSON object")
            seen.add(k)
    return d


class _LongInt:
    """Stands for an integer literal longer than Python converts to int
    (sys.get_int_max_str_digits) while the scene is parsed again to find where it is."""

    def __init__(self, digits: int):
        self.digits = digits


def _long_int_path(text: str) -> str:
    """The JSON path of the first integer literal in ``text`` too long to convert, and its size."""
    limit = sys.get_int_max_str_digits()
    unknown = f"an integer of more than {limit} digits is out of range"

    def parse_int(t: str):
        digits = len(t.lstrip("-"))
        return _LongInt(digits) if digits > limit else 0

    try:
        d = json.loads(text, parse_int=parse_int)
    except (ValueError, RecursionError):
        return unknown
    stack = [(d, "")]
    while stack:
        v, path = stack.pop()
        if isinstance(v, _LongInt):
            return f"{path or 'top level'}: integer of {v.digits} digits is out of range"
        items = v.items() if isinstance(v, dict) else enumerate(v) if isinstance(v, list) else ()
        stack.extend((x, at_key(path, k)) for k, x in reversed(list(items)))
    return unknown


def _read_json(path: str):
    """The parsed JSON of the scene file ``path`` (a regular file of at most MAX_SCENE_BYTES)."""
    try:
        data = read_regular(path, MAX_SCENE_BYTES)
    except ValueError as e:
        raise SceneError(str(e)) from None
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as e:
        raise SceneError(f"{path}: not UTF-8 text (byte 0x{data[e.start]:02x} at offset "
                         f"{e.start}); scene files are UTF-8 JSON") from None
    try:
        return json.loads(text, object_pairs_hook=_no_duplicates)
    except json.JSONDecodeError as e:
        raise SceneError(f"{path}: invalid JSON at line {e.lineno} column {e.colno}: "
                         f"{e.msg}") from None
    except RecursionError:
        raise SceneError(f"{path}: JSON nested too deeply (no scene needs more than a few "
                         "levels)") from None
    except SceneError as e:                 # a duplicate key
        raise SceneError(f"{path}: {e}") from None
    except ValueError:                      # an integer too long to convert
        raise SceneError(f"{path}: {_long_int_path(text)}") from None


def load_scene(path: str | os.PathLike) -> Scene:
    """Read, validate and build a scene file; images load relative to the file's folder."""
    path = os.fspath(path)
    return scene_from_dict(_read_json(path), os.path.dirname(os.path.abspath(path)))


def _dumps(v, indent: int = 0) -> str:
    """JSON text: objects one key per line, flat lists of scalars on one line."""
    pad = " " * (indent + 2)
    if isinstance(v, dict) and v:
        items = [f"{pad}{json.dumps(k)}: {_dumps(x, indent + 2)}" for k, x in v.items()]
        return "{\n" + ",\n".join(items) + "\n" + " " * indent + "}"
    if isinstance(v, list) and any(isinstance(x, (dict, list)) for x in v):
        items = [pad + _dumps(x, indent + 2) for x in v]
        return "[\n" + ",\n".join(items) + "\n" + " " * indent + "]"
    return json.dumps(v, allow_nan=False)


def save_scene(scene: Scene, path: str | os.PathLike) -> None:
    """Validate and write ``scene`` as JSON to ``path`` (temporary file + os.replace).

    Image paths are written as stored (relative to the scene file's folder, or absolute); the
    image files themselves are not written.
    """
    d = scene_to_dict(scene)
    parse_scene(d, None, load_images=False)
    text = _dumps(d) + "\n"
    atomic_write(path, lambda f: f.write(text.encode("utf-8")))
