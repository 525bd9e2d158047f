"""Direction cube (paper 3.1) and the inward hemicube of a bounding-box face.

Cube faces are numbered c = 2 * axis + (sign > 0): 0 = -X, 1 = +X, 2 = -Y, 3 = +Y, 4 = -Z,
5 = +Z. A direction d maps to its dominant axis (largest |component|; ties go to the lower
axis, so every direction has exactly one face) and to w = d / max|d_i|, with
(u, v) = (w_y, w_z) on X faces, (w_x, w_z) on Y faces, (w_x, w_y) on Z faces.

Bounding-box faces use the same numbering (face 2a + 1 is the box's max face along axis a).
Rays entering through box face f travel inward along its axis, so their cube face is never the
outward one: the five possible cube faces are the *hemicube* of f, slots 0..4: slot 0 the
opposite face (full square), slots 1..4 the four side faces (half squares: the coordinate
along f's axis has the inward sign).
"""

from __future__ import annotations

import numpy as np

from ..rowops import argmax3

UV_AXES = ((1, 2), (0, 2), (0, 1))   # world axes carrying (u, v) on the faces of each axis
U_AXIS = np.array([p[0] for p in UV_AXES])   # (u, v) axes of each dominant axis, as arrays
V_AXIS = np.array([p[1] for p in UV_AXES])
N_SLOTS = 5


def dir_to_cube(d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(face, u, v) for non-zero directions d (N, 3)."""
    a = np.abs(d)
    axis = argmax3(a)
    rows = np.arange(len(d))
    m = a[rows, axis]
    face = 2 * axis + (d[rows, axis] > 0)
    return face, d[rows, U_AXIS[axis]] / m, d[rows, V_AXIS[axis]] / m


def cube_to_dir(face: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Unit directions for cube faces and (u, v) in [-1, 1]^2."""
    face = np.asarray(face)
    axis = face // 2
    d = np.zeros((len(face), 3))
    rows = np.arange(len(face))
    d[rows, axis] = np.where(face % 2 == 1, 1.0, -1.0)
    d[rows, U_AXIS[axis]] = u
    d[rows, V_AXIS[axis]] = v
    return d / np.linalg.norm(d, axis=1)[:, None]


def _hemicube_tables():
    """SLOT[f, c]: slot of cube face c in box face f's hemicube (-1: impossible);
    CUBE[f, s]: cube face of slot s; DOMAIN[f, s] = (u0, u1, v0, v1)."""
    slot = -np.ones((6, 6), np.int64)
    cube = np.zeros((6, N_SLOTS), np.int64)
    dom = np.zeros((6, N_SLOTS, 4))
    for f in range(6):
        a, inward = f // 2, (-1.0 if f % 2 == 1 else 1.0)
        faces = [2 * a + (inward > 0)] + [2 * b + s for b in range(3) if b != a for s in (0, 1)]
        for s, c in enumerate(faces):
            slot[f, c] = s
            cube[f, s] = c
            lim = [[-1.0, 1.0], [-1.0, 1.0]]
            if s > 0:                       # side face: f's axis coordinate is inward
                k = UV_AXES[c // 2].index(a)
                lim[k] = [0.0, 1.0] if inward > 0 else [-1.0, 0.0]
            dom[f, s] = (lim[0][0], lim[0][1], lim[1][0], lim[1][1])
    return slot, cube, dom


SLOT, CUBE, DOMAIN = _hemicube_tables()
