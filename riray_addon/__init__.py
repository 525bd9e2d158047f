"""riray's Blender add-on: export to the core engine, the "Bake RI-Tree" panel and operator, and
the "RI-Tree Preview" render engine.

Inside the extension zip this package is ``bl_ext.<repo>.riray.riray_addon`` and reaches the
engine as ``..core`` (relative imports only). ``backend``, ``jobs``, ``worker`` and ``report``
never import bpy (the bake worker process imports them without Blender).
"""

from __future__ import annotations

_MODULES = ("properties", "cache", "engine", "operators", "ui")


def _modules():
    import importlib
    return [importlib.import_module(f".{name}", __name__) for name in _MODULES]


def register():
    for mod in _modules():
        mod.register()


def unregister():
    for mod in reversed(_modules()):
        mod.unregister()
