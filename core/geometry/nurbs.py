"""Rational NURBS surfaces: the data type (evaluation lives beside it, vectorized over (u, v)).

Convention: ``points[i, j]`` is the Cartesian control point with index i along u and j along v,
``weights[i, j] > 0`` its weight; the surface is
    S(u, v) = sum N_i,p(u) N_j,q(v) w_ij P_ij / sum N_i,p(u) N_j,q(v) w_ij
on the domain [knots_u[p], knots_u[n_u]] x [knots_v[q], knots_v[n_v]].
Cyclic surfaces are represented unrolled (wrapped control points + periodic knots), so every
surface here is an ordinary NURBS surface.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class NurbsSurface:
    degree_u: int
    degree_v: int
    knots_u: np.ndarray      # (n_u + degree_u + 1,) non-decreasing float64
    knots_v: np.ndarray      # (n_v + degree_v + 1,)
    points: np.ndarray       # (n_u, n_v, 3) float64 Cartesian
    weights: np.ndarray      # (n_u, n_v) float64, > 0

    @property
    def domain(self) -> tuple[float, float, float, float]:
        """(u0, u1, v0, v1) parameter domain."""
        p, q = self.degree_u, self.degree_v
        nu, nv = self.points.shape[:2]
        return (float(self.knots_u[p]), float(self.knots_u[nu]),
                float(self.knots_v[q]), float(self.knots_v[nv]))
