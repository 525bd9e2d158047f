"""Every riray setting (scene, object, material, world, view layer) set to a value other than
its default, and read back as plain data, for the save -> reopen tests in test_settings.py.
They call fill() / read() in their own Blender and run this file as a script in a Blender of
another version:

    python settings_roundtrip.py EXTENSION.zip OUT.blend OUT.json

(installs the zip into a private BLENDER_USER_RESOURCES, fills the settings, saves OUT.blend
and writes what it set to OUT.json). No bpy import at module level: the script must set
BLENDER_USER_RESOURCES first.
"""

import json
import os
import sys
import tempfile

OBJECT = "riray_ball"
MATERIAL = "riray_glass"
WORLD = "riray_world"
SKIP = {"rna_type", "name"}


def owners(bpy) -> dict:
    """The data-blocks (and view layer) whose riray settings are checked, by kind."""
    scene = bpy.context.scene
    return {"scene": scene, "object": bpy.data.objects[OBJECT],
            "material": bpy.data.materials[MATERIAL], "world": bpy.data.worlds[WORLD],
            "view_layer": scene.view_layers[0]}


def _other_value(prop, name, bpy):
    """A valid value of ``prop`` that is not its default."""
    kind = prop.type
    if kind == "BOOLEAN":
        return not prop.default
    if kind == "INT":
        return prop.default + 1 if prop.default < prop.hard_max else prop.default - 1
    if kind == "FLOAT":
        return prop.default + 0.25 if prop.default + 0.25 <= prop.hard_max else prop.default - 0.25
    if kind == "ENUM":
        return next(i.identifier for i in prop.enum_items if i.identifier != prop.default)
    if kind == "STRING":
        return f"//{name}.rit" if prop.subtype == "FILE_PATH" else f"riray {name}"
    if kind == "POINTER" and prop.fixed_type.identifier == "Object":
        return bpy.data.objects[OBJECT]
    raise TypeError(f"no test value for {name} ({kind})")


def _dump(group) -> dict:
    out = {}
    for prop in group.bl_rna.properties:
        if prop.identifier in SKIP:
            continue
        value = getattr(group, prop.identifier)
        if prop.type == "COLLECTION":
            value = [_dump(item) for item in value]
        elif prop.type == "POINTER":
            value = None if value is None else value.name
        out[prop.identifier] = value
    return out


def fill(bpy) -> dict:
    """Build the data-blocks in the current file and set every riray setting; returns read()."""
    bpy.ops.surface.primitive_nurbs_surface_sphere_add(radius=0.5)
    bpy.context.active_object.name = OBJECT
    obj = bpy.data.objects[OBJECT]
    obj.data.materials.append(bpy.data.materials.new(MATERIAL))
    bpy.context.scene.world = bpy.data.worlds.new(WORLD)
    for kind, owner in owners(bpy).items():
        group = owner.riray
        for prop in group.bl_rna.properties:
            name = prop.identifier
            if name in SKIP:
                continue
            if prop.type == "COLLECTION":
                items = getattr(group, name)
                for value in (2, 0, 5):
                    items.add().group = value
            else:
                setattr(group, name, _other_value(prop, f"{kind}.{name}", bpy))
    return read(bpy)


def read(bpy) -> dict:
    """{kind: {setting: value}} with objects as names and collections as lists of dicts."""
    return {kind: _dump(owner.riray) for kind, owner in owners(bpy).items()}


def main(argv) -> int:
    zip_path, blend, out_json = argv
    os.environ["BLENDER_USER_RESOURCES"] = tempfile.mkdtemp(prefix="riray_settings_")
    import bpy
    res = bpy.ops.extensions.package_install_files(filepath=zip_path, repo="user_default",
                                                   enable_on_install=True)
    if res != {"FINISHED"}:
        print(f"could not install {zip_path}", file=sys.stderr)
        return 1
    bpy.ops.wm.read_homefile(use_empty=True)
    values = fill(bpy)
    bpy.ops.wm.save_as_mainfile(filepath=blend)
    with open(out_json, "w", encoding="utf-8") as fh:
        json.dump({"version": list(bpy.app.version), "settings": values}, fh)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
