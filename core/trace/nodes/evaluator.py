"""The graph evaluator: every node the output needs, once, in the graph's order, through the
table of node evaluations (:data:`EVALUATORS`, one function per node type)."""

from __future__ import annotations

import numpy as np

from ...scene.graph import NODE_TYPES, SHADER, ShaderGraph
from . import colour, images, inputs, maths, procedural, shaders
from .values import Closure, ShadingPoints, closure, convert

# node type -> evaluation (node, inputs, shading points, wanted outputs) -> {output: value}:
# ``inputs`` holds every input's value converted to the input's kind (a linked shader input
# left unset is None), ``wanted`` the outputs some link reads (others may be skipped)
EVALUATORS = {**inputs.NODES, **maths.NODES, **colour.NODES, **procedural.NODES,
              **images.NODES, **shaders.NODES}
assert EVALUATORS.keys() == NODE_TYPES.keys(), set(EVALUATORS) ^ set(NODE_TYPES)


def _needed(graph: ShaderGraph) -> set:
    """Names of the nodes the output depends on."""
    need, todo = set(), [graph.output.node]
    by_name = {n.name: n for n in graph.nodes}
    while todo:
        name = todo.pop()
        if name in need:
            continue
        need.add(name)
        todo.extend(v.node for v in by_name[name].links.values())
    return need


def _inputs(node, values: dict, types: dict) -> dict:
    """The node's input values: linked ones converted from their source's kind, the others its
    constants."""
    inp = {}
    for key, (kind, _) in NODE_TYPES[node.type].inputs.items():
        link = node.links.get(key)
        if link is not None:
            src = NODE_TYPES[types[link.node]].outputs[link.output]
            inp[key] = convert(values[(link.node, link.output)], src, kind)
        else:
            v = node.inputs.get(key)
            inp[key] = v if kind == SHADER else np.asarray(v, float)
    return inp


def evaluate(graph: ShaderGraph, pts: ShadingPoints) -> Closure:
    """The closure at the graph's output for every shading point: emission and albedo (N, 3),
    finite (non-finite components are 0)."""
    values: dict = {}
    need = _needed(graph)
    types = {n.name: n.type for n in graph.nodes}
    used = {(lk.node, lk.output) for n in graph.nodes for lk in n.links.values()}
    used.add((graph.output.node, graph.output.output))
    with np.errstate(all="ignore"):
        for node in graph.nodes:
            if node.name not in need:
                continue
            want = {o for o in NODE_TYPES[node.type].outputs if (node.name, o) in used}
            run = EVALUATORS[node.type]
            for key, val in run(node, _inputs(node, values, types), pts, want).items():
                values[(node.name, key)] = val
        out = graph.output
        kind = NODE_TYPES[types[out.node]].outputs[out.output]
        cl = closure(convert(values[(out.node, out.output)], kind, SHADER))
        n = len(pts)
        em = np.broadcast_to(np.asarray(cl.emission, float), (n, 3))
        al = np.broadcast_to(np.asarray(cl.albedo, float), (n, 3))
        return Closure(emission=np.where(np.isfinite(em), em, 0.0),
                       albedo=np.where(np.isfinite(al), al, 0.0))
