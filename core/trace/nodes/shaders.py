"""Shader nodes as a Whitted renderer reads Cycles' closures: Emission / Background / Principled
emission -> emission, Diffuse / Principled base colour -> albedo, Mix Shader -> weighted sum,
Add Shader -> sum."""

from __future__ import annotations

import numpy as np

from .values import Closure, closure, expand, saturate


# Every node evaluation: (node, inputs, shading points, wanted outputs) -> {output: value}
def emission(node, inp, pts, want) -> dict:
    """Emission or Background: colour * strength emitted (its output is named as its type)."""
    e = np.asarray(inp["color"], float) * expand(inp["strength"])
    return {node.type: Closure(emission=e, albedo=np.zeros(3))}


def diffuse(node, inp, pts, want) -> dict:
    return {"bsdf": Closure(emission=np.zeros(3), albedo=np.asarray(inp["color"], float))}


def principled(node, inp, pts, want) -> dict:
    e = np.asarray(inp["emission_color"], float) * expand(inp["emission_strength"])
    return {"bsdf": Closure(emission=e, albedo=np.asarray(inp["base_color"], float))}


def mix_shader(node, inp, pts, want) -> dict:
    f = expand(saturate(np.asarray(inp["factor"], float)))
    a, b = closure(inp["shader1"]), closure(inp["shader2"])
    return {"shader": Closure(emission=(1.0 - f) * a.emission + f * b.emission,
                              albedo=(1.0 - f) * a.albedo + f * b.albedo)}


def add_shader(node, inp, pts, want) -> dict:
    a, b = closure(inp["shader1"]), closure(inp["shader2"])
    return {"shader": Closure(emission=a.emission + b.emission, albedo=a.albedo + b.albedo)}


NODES = {"emission": emission, "background": emission, "diffuse": diffuse,
         "principled": principled, "mix_shader": mix_shader, "add_shader": add_shader}
