"""Input nodes: Texture Coordinate, Geometry and Object Info, read from the shading points."""

from __future__ import annotations

import numpy as np

from ...scene.graph import NODE_TYPES
from .values import affine, dot, expand, safe_normalize


# Every node evaluation: (node, inputs, shading points, wanted outputs) -> {output: value}
def tex_coord(node, inp, pts, want) -> dict:
    pr, n, wi = node.props, pts.normal, pts.incoming
    return {"generated": affine(pr["generated_matrix"], pts.position),
            "normal": safe_normalize(n @ np.asarray(pr["normal_matrix"]).T),
            "uv": np.column_stack([pts.uv, np.zeros(len(pts))]),
            "object": affine(pr["object_matrix"], pts.position),
            "camera": affine(pr["camera_matrix"], pts.position),
            "reflection": 2.0 * expand(dot(n, wi)) * n - wi}


def geometry(node, inp, pts, want) -> dict:
    return {"position": pts.position, "normal": pts.normal, "true_normal": pts.true_normal,
            "incoming": pts.incoming, "backfacing": pts.backfacing.astype(float)}


def object_info(node, inp, pts, want) -> dict:
    return {k: np.asarray(node.props[k], float) for k in NODE_TYPES[node.type].outputs}


NODES = {"tex_coord": tex_coord, "geometry": geometry, "object_info": object_info}
