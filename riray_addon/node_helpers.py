"""Helpers over Blender shader node trees shared by the material mapping (materials.py) and the
shader-graph translation (nodegraph.py): the active output node, the node feeding a socket, and
an image's pixels as an array. No bpy import: they read the node objects they are given."""

from __future__ import annotations

import numpy as np

from ..core.imageio import srgb_to_linear

MAX_REROUTES = 256      # reroutes / muted nodes in a row before a chain counts as broken
RENDER_TARGETS = ("ALL", "CYCLES")   # output node targets a Cycles-like renderer uses


def output_node(tree):
    """The material / world output node Cycles would use: the active one among those that
    target all renderers or Cycles, else the first such, else any; None without one."""
    outs = [n for n in tree.nodes if n.type in ("OUTPUT_MATERIAL", "OUTPUT_WORLD")]
    ours = [n for n in outs if getattr(n, "target", "ALL") in RENDER_TARGETS]
    active = [n for n in ours if getattr(n, "is_active_output", False)]
    return (active or ours or outs or [None])[0]


def source(socket):
    """(node, output socket) feeding an input socket, through reroutes and muted nodes (as
    Blender passes them through); None when nothing valid is linked."""
    for _ in range(MAX_REROUTES):
        if not socket.is_linked:
            return None
        link = socket.links[0]
        if not link.is_valid or getattr(link, "is_muted", False) or \
                not link.from_socket.enabled:
            return None
        node, out = link.from_node, link.from_socket
        if node.type == "REROUTE":
            socket = node.inputs[0]
            continue
        if node.mute:
            passed = [li.from_socket for li in node.internal_links if li.to_socket == out]
            if not passed:
                return None
            socket = passed[0]
            continue
        return node, out
    return None


def image_pixels(img, linearize: bool = True) -> np.ndarray | None:
    """(H, W, 3) float64, top row first, or None if the image has no pixels; 8-bit sRGB images
    are linearized unless ``linearize`` is off (then the pixels are as stored)."""
    w, h = img.size[0], img.size[1]
    if w == 0 or h == 0:
        return None
    buf = np.empty(w * h * img.channels, dtype=np.float32)
    img.pixels.foreach_get(buf)
    px = buf.reshape(h, w, img.channels)[::-1, :, :3].astype(np.float64)
    if px.shape[2] < 3:
        px = np.repeat(px[:, :, :1], 3, axis=2)
    if linearize and not img.is_float and img.colorspace_settings.name == "sRGB":
        px = srgb_to_linear(px)
    return np.ascontiguousarray(px)
