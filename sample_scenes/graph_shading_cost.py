"""What shading the environment through node graphs costs, against the fixed texture kinds.

    .venv/bin/python sample_scenes/graph_shading_cost.py [--scene glass_sphere] [--size 300]
        [--open]

Builds the sample scene twice: as it is (environment materials and world with the fixed texture
kinds: checker, stripes, gradient, constant; a gradient sky) and with every material and the
world rewritten as the equivalent shader node graph (the graphs Blender users would build:
UV -> Checker, Separate XYZ -> Map Range -> Mix, Generated -> Clamp -> Mix -> Background).
``--open`` takes the ceiling away so that the sky is seen. Both are rendered exactly (one worker, so CPU times are this process's), and the script prints
per frame: CPU seconds spent evaluating materials and the world (textures vs graphs), the
whole environment pass (shade_rays: hits, shadow rays, shading) and the frame, and the largest
pixel difference between the two renders (the graphs reproduce the kinds up to the checker
bias, so only pixels on check boundaries may differ).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from riray.render.exact import render_exact
from riray.scene import samples
from riray.scene.camera import Shot
from riray.scene.graph import GraphNode, Link, ShaderGraph
from riray.scene.model import Material, World
from riray.trace import shading
from riray.trace.scene_tracer import SceneTracer


def texture_graph(mat: Material) -> ShaderGraph:
    """The node graph equal to a fixed-kind environment material."""
    tex = mat.color
    nodes = [GraphNode("tc", "tex_coord")]
    coords = Link("tc", "uv" if tex.coords == "uv" else "object")
    if tex.kind == "constant":
        color = tex.color
    elif tex.kind == "checker":
        # Blender's checker shows Color1 where the cell indices sum odd, riray's kind shows
        # ``color`` where they sum even; 2D on uv (z = 0 adds nothing)
        nodes.append(GraphNode("chk", "checker", links={"vector": coords}, inputs={
            "color1": tex.color2, "color2": tex.color, "scale": tex.scale}))
        color = Link("chk", "color")
    elif tex.kind == "stripes":
        nodes += [GraphNode("sep", "separate_xyz", links={"vector": coords}),
                  GraphNode("line", "combine_xyz", links={"x": Link("sep", "xyz"[tex.axis])}),
                  GraphNode("chk", "checker", links={"vector": Link("line", "vector")}, inputs={
                      "color1": tex.color2, "color2": tex.color, "scale": tex.scale})]
        color = Link("chk", "color")
    elif tex.kind == "gradient":
        nodes += [GraphNode("sep", "separate_xyz", links={"vector": coords}),
                  GraphNode("t", "map_range", links={"value": Link("sep", "xyz"[tex.axis])},
                            inputs={"from_min": tex.start, "from_max": tex.end}),
                  GraphNode("mix", "mix_color", links={"factor": Link("t", "result")},
                            inputs={"a": tex.color, "b": tex.color2})]
        color = Link("mix", "result")
    else:
        raise ValueError(f"{mat.name}: texture kind {tex.kind!r} has no graph here")
    shader = "emission" if mat.kind == "emission" else "diffuse"
    out = GraphNode("out", shader, **({"links": {"color": color}} if isinstance(color, Link)
                                      else {"inputs": {"color": color}}))
    if shader == "emission":
        out.inputs["strength"] = mat.strength
    nodes.append(out)
    return ShaderGraph(nodes=nodes, output=Link("out", "emission" if shader == "emission"
                                                 else "bsdf"))


def world_graph(w: World) -> ShaderGraph:
    """The node graph of the horizon -> zenith gradient sky: t = clamp(D_z, 0, 1)."""
    nodes = [GraphNode("tc", "tex_coord"),
             GraphNode("sep", "separate_xyz", links={"vector": Link("tc", "generated")}),
             GraphNode("t", "clamp", links={"value": Link("sep", "z")}),
             GraphNode("mix", "mix_color", links={"factor": Link("t", "result")},
                       inputs={"a": w.color, "b": w.zenith}),
             GraphNode("bg", "background", links={"color": Link("mix", "result")},
                       inputs={"strength": w.strength})]
    return ShaderGraph(nodes=nodes, output=Link("bg", "background"))


class Timer:
    """Wraps functions of the shading modules and adds up their CPU seconds."""

    def __init__(self):
        self.s = {}

    def wrap(self, module, name: str, key: str):
        fn = getattr(module, name)

        def timed(*a, **k):
            c0 = time.process_time()
            try:
                return fn(*a, **k)
            finally:
                self.s[key] = self.s.get(key, 0.0) + time.process_time() - c0

        setattr(module, name, timed)
        return lambda: setattr(module, name, fn)


def measure(scene, size: int) -> tuple[np.ndarray, dict]:
    t = Timer()
    undo = [t.wrap(shading, "eval_texture", "materials_s"),
            t.wrap(shading, "evaluate", "materials_s"),
            t.wrap(shading, "eval_world", "world_s"),
            t.wrap(shading.Environment, "shade_rays", "environment_s")]
    try:
        res = render_exact(SceneTracer(scene), Shot(width=size, height=size), workers=1)
    finally:
        for u in undo:
            u()
    t.s["frame_s"] = res.stats["summary"]["total_cpu_s"]
    return res.image, t.s


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="glass_sphere", choices=samples.SAMPLES)
    ap.add_argument("--size", type=int, default=300, help="frame width and height (pixels)")
    ap.add_argument("--open", action="store_true", help="no ceiling: the sky is seen")
    args = ap.parse_args()
    fixed = samples.build(args.scene)
    if args.open:
        fixed.meshes = [m for m in fixed.meshes if m.name != "ceiling"]
        del fixed.materials["ceiling"]
    graphs = samples.build(args.scene)
    graphs.meshes, graphs.materials = list(fixed.meshes), dict(fixed.materials)
    graphs.materials = {k: Material(name=k, kind="nodes", graph=texture_graph(m))
                        for k, m in graphs.materials.items()}
    graphs.world = World(kind="nodes", graph=world_graph(graphs.world),
                         ambient=graphs.world.ambient)
    img_a, a = measure(fixed, args.size)
    img_b, b = measure(graphs, args.size)
    diff = np.abs(img_a - img_b).max(axis=2)
    print(f"{args.scene}{' (open)' if args.open else ''} {args.size}x{args.size}, CPU seconds "
          "per frame (one worker)")
    print(f"{'':24}{'fixed kinds':>12}{'node graphs':>12}{'ratio':>8}")
    for key in ("materials_s", "world_s", "environment_s", "frame_s"):
        print(f"{key:24}{a.get(key, 0):12.3f}{b.get(key, 0):12.3f}"
              f"{b.get(key, 0) / max(a.get(key, 0), 1e-9):8.2f}")
    print(f"max pixel difference {diff.max():.3g}; pixels differing by > 1e-6: "
          f"{(diff > 1e-6).mean():.2%}")


if __name__ == "__main__":
    main()
