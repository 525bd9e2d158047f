"""Differences between the supported Blender versions (4.2 LTS to 5.0), in one place.

Everything is detected from the API itself, not from version numbers. Needs only bpy, so
scripts outside the add-on (sample_scenes/build_blend.py, the tests) load this file directly.

- ID properties: up to 4.5 the settings registered with ``bpy.props`` live in the same ID
  property storage as custom properties (``id["riray"]`` *is* ``id.riray``); from 5.0 they
  live apart (``id.bl_system_properties_get()``) and ``id["riray"]`` is only a custom property.
- Materials and worlds: ``use_nodes`` (False for new ones) decides before 5.0 whether the node
  tree is used at all; from 5.0 it always is.
- "//" paths in FILE_PATH string properties need the option PATH_SUPPORTS_BLEND_RELATIVE
  from 4.5 on (5.0 warns without it); 4.2 does not know the option.
- Multilayer EXR output: ``file_format = 'OPEN_EXR_MULTILAYER'`` before 5.0,
  ``media_type = 'MULTI_LAYER_IMAGE'`` from 5.0.
"""

import bpy


BLEND_RELATIVE = ({"PATH_SUPPORTS_BLEND_RELATIVE"}
                  if "is_path_supports_blend_relative" in bpy.types.Property.bl_rna.properties
                  else set())
"""``options`` of a FILE_PATH StringProperty that holds "//" (blend-relative) paths."""


def separate_system_properties(idb) -> bool:
    """True when registered properties are stored apart from custom properties (5.0+)."""
    return hasattr(idb, "bl_system_properties_get")


def registered_storage(idb, name: str):
    """The ID-property group holding the registered pointer property ``name`` of ``idb``, or
    None when nothing is stored for it yet."""
    if separate_system_properties(idb):
        store = idb.bl_system_properties_get()
        return None if store is None else store.get(name)
    return idb.get(name)


def custom_property(idb, name: str):
    """The custom property ``idb[name]`` when it is *not* the registered storage (5.0+), else
    None (before 5.0 the two are one and the same)."""
    if separate_system_properties(idb):
        return idb.get(name)
    return None


def node_tree(idb):
    """The shader node tree of a material or world, created if needed (4.2: ``use_nodes``)."""
    if idb.node_tree is None:
        idb.use_nodes = True
    return idb.node_tree


def shader_tree(idb):
    """The node tree Blender renders a material or world with, or None: before 5.0 ``use_nodes``
    off means the viewport / world colour is used instead (5.0 always uses the nodes)."""
    prop = idb.bl_rna.properties.get("use_nodes")
    if prop is not None and not getattr(prop, "is_deprecated", False) and not idb.use_nodes:
        return None
    return idb.node_tree


def new_material(name: str):
    """``bpy.data.materials.new`` with its default node tree (Principled BSDF) on every version."""
    mat = bpy.data.materials.new(name)
    node_tree(mat)
    return mat


def new_world(name: str):
    """``bpy.data.worlds.new`` with its default node tree (Background) on every version."""
    world = bpy.data.worlds.new(name)
    node_tree(world)
    return world


def set_multilayer_exr(image_settings) -> None:
    """Make an ImageFormatSettings write multilayer OpenEXR."""
    if "media_type" in image_settings.bl_rna.properties:
        image_settings.media_type = "MULTI_LAYER_IMAGE"
    else:
        image_settings.file_format = "OPEN_EXR_MULTILAYER"
