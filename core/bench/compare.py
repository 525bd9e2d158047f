"""The fair setup for comparing riray with Blender's renderers (sample_scenes/blender_bench.py).

riray computes a Whitted-style answer: one ray per pixel, the specular object's exact chain of
reflections/refractions, the environment's colour where the chain leaves. A path tracer such as
Cycles converges to the same image only when the environment has no light transport of its own
to integrate. ``whitted_scene`` makes that so, on the riray side and (through
sample_scenes/build_blend.py, which builds the .blend from this very Scene) on the Blender side:

- every environment material becomes *emission-only* with the same colour texture (strength 1):
  what a ray sees where it leaves the object is the texture colour, with no lighting to sample;
- the lights are removed (emission ignores them; nothing else is lit);
- the object keeps its kind, IOR and tint but loses the Phong highlight and diffuse terms, so
  it is a pure sharp mirror (Glossy BSDF, roughness 0) or a pure refractor (Refraction BSDF,
  roughness 0) - both deterministic in Cycles;
- the world (sky gradient, a background shader) is emission already.

What remains different is sampling: riray shoots one ray through each pixel centre, Cycles
integrates a 1.5-pixel filter (anti-aliasing); the bpy script therefore also renders Cycles with
a 0.01-pixel filter (point sampling) as a check that both compute the same answer.
"""

from __future__ import annotations

import copy

from ..scene.model import Material, Scene


def whitted_scene(scene: Scene) -> Scene:
    """A copy of ``scene`` with emission-only environment materials, no lights and a pure
    specular object (see the module doc)."""
    out = copy.deepcopy(scene)
    out.materials = {k: Material(name=m.name, kind="emission", color=m.color, strength=1.0)
                     for k, m in scene.materials.items()}
    out.lights = []
    mat = out.object.material
    mat.diffuse = 0.0
    mat.specular = 0.0
    out.world.ambient = 0.0
    return out
