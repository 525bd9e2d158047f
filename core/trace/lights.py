"""Geometry of the sampled light terms of environment shading (trace/shading.py): deterministic
per-point sample offsets, stratified cosine-weighted hemisphere directions (the sky term),
area lights (closed-form irradiance of a polygon, stratified points on the light, rays that
see it) and Blinn-Phong lobe directions (rough metals).

Points, normals and directions are columns (3, k); samples of k points are (k, n) arrays.
Every sample set is a fixed multi-jittered grid (stratified in 2D and along either coordinate)
placed by an offset hashed from the point's coordinates: the same point always gets the same
samples, and neighbouring points different ones, so the residual error is fine-grained noise
that the film's samples per pixel average, never bands.
"""

from __future__ import annotations

import numpy as np

from ..scene.model import Light

ELLIPSE_SIDES = 32       # an elliptic light's closed form is that of this polygon, scaled to
                         # the ellipse's area (irradiance within ~0.1 % of the ellipse's)
# Points are hashed on a grid of this step (scene units, a power of two: the division is
# exact): the same hit found in another batch of rays can differ in its last bits (numpy's
# vectorized sums round by the array's shape), and hashing raw bits gave it other samples,
# another noise value - a pixel changed with the number of render processes. Neighbouring
# pixels' points lie far more than a step apart. Cells beyond HASH_CELLS (points ~5e11 units
# out, past what a scene validates) share the edge cell.
HASH_STEP = 2.0 ** -24
HASH_CELLS = 2.0 ** 62
_MIX1, _MIX2 = np.uint64(0xBF58476D1CE4E5B9), np.uint64(0x94D049BB133111EB)
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_PRIMES = (np.uint64(0x8CB92BA72F3D8DD7), np.uint64(0xD6E8FEB86659FD93),
           np.uint64(0xA0761D6478BD642F))


def _splitmix(h: np.ndarray) -> np.ndarray:
    h = (h ^ (h >> np.uint64(30))) * _MIX1
    h = (h ^ (h >> np.uint64(27))) * _MIX2
    return h ^ (h >> np.uint64(31))


def point_offsets(p: np.ndarray, salt: int) -> np.ndarray:
    """(2, k) numbers in [0, 1) hashed from points ``p`` (3, k) on the grid of HASH_STEP and
    ``salt``."""
    cell = np.clip(np.floor(np.asarray(p, dtype=np.float64) / HASH_STEP), -HASH_CELLS,
                   HASH_CELLS)
    bits = np.ascontiguousarray(cell.astype(np.int64)).view(np.uint64)
    with np.errstate(over="ignore"):
        h = np.full(p.shape[1], np.uint64(salt) * _GOLDEN, np.uint64)
        for row, prime in zip(bits, _PRIMES):
            h = _splitmix(h ^ (row * prime))
        h2 = _splitmix(h + _GOLDEN)
    scale = 2.0 ** -53
    return np.stack([(h >> np.uint64(11)) * scale, (h2 >> np.uint64(11)) * scale])


def strata(side: int, offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(s, t) (k, side^2) each: one sample in each cell of a side x side grid over [0, 1)^2
    and in each of the side^2 strata of either coordinate alone (the multi-jittered
    arrangement), placed within its strata by the points' ``offsets`` (2, k)."""
    i, j = np.divmod(np.arange(side * side), side)
    s = (i[None, :] + (j[None, :] + offsets[0][:, None]) / side) / side
    t = (j[None, :] + (i[None, :] + offsets[1][:, None]) / side) / side
    return s, t


def tangent_frames(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit tangents (t, b) (3, k) each, with (t, b, n) right-handed orthonormal for unit n."""
    sign = np.where(n[2] >= 0, 1.0, -1.0)
    a = -1.0 / (sign + n[2])
    c = n[0] * n[1] * a
    t = np.stack([1.0 + sign * n[0] * n[0] * a, sign * c, -sign * n[0]])
    b = np.stack([c, sign + n[1] * n[1] * a, -n[1]])
    return t, b


def cosine_directions(n: np.ndarray, side: int, offsets: np.ndarray) -> np.ndarray:
    """(3, k, side^2) unit directions about normals ``n`` (3, k), cosine-weighted and
    stratified (Malley's method on a shifted grid)."""
    s, t = strata(side, offsets)
    r, phi = np.sqrt(s), 2.0 * np.pi * t
    x, y, z = r * np.cos(phi), r * np.sin(phi), np.sqrt(np.maximum(1.0 - s, 0.0))
    tx, bx = tangent_frames(n)
    return tx[:, :, None] * x + bx[:, :, None] * y + n[:, :, None] * z


def sphere_directions(n: int) -> np.ndarray:
    """(n, 3) unit directions spread evenly over the sphere (a Fibonacci lattice: equal-area
    bands, golden-angle turns)."""
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    r = np.sqrt(np.maximum(1.0 - z * z, 0.0))
    phi = np.pi * (3.0 - np.sqrt(5.0)) * k
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def lobe_directions(r: np.ndarray, shininess: float, side: int,
                    offsets: np.ndarray) -> np.ndarray:
    """(3, k, side^2) unit directions about the mirror directions ``r`` (3, k), distributed as
    cos^shininess about them and stratified."""
    s, t = strata(side, offsets)
    cos = s ** (1.0 / (shininess + 1.0))
    sin, phi = np.sqrt(np.maximum(1.0 - cos * cos, 0.0)), 2.0 * np.pi * t
    tx, bx = tangent_frames(r)
    return (tx[:, :, None] * (sin * np.cos(phi)) + bx[:, :, None] * (sin * np.sin(phi))
            + r[:, :, None] * cos)


class AreaLight:
    """An area light's frame and radiance: ``centre``, emission ``normal``, unit ``u``, ``v``
    along its sides, half sides ``hu``, ``hv`` (metres), ``radiance`` (3,) W/m^2/sr."""

    def __init__(self, light: Light):
        self.light = light
        self.centre = np.asarray(light.position, dtype=np.float64)
        self.normal = np.asarray(light.direction, dtype=np.float64)
        self.u = np.asarray(light.axis, dtype=np.float64)
        self.v = np.cross(self.normal, self.u)
        self.hu, self.hv = 0.5 * float(light.size[0]), 0.5 * float(light.size[1])
        self.ellipse = light.shape == "ellipse"
        self.area = light.area
        self.radiance = np.asarray(light.color, dtype=np.float64) * light.power / (
            np.pi * self.area)
        self.corners = self._polygon()

    def _polygon(self) -> np.ndarray:
        """(m, 3) the light's outline, counter-clockwise seen from the side it lights."""
        if self.ellipse:
            a = 2.0 * np.pi * np.arange(ELLIPSE_SIDES) / ELLIPSE_SIDES
            grow = np.sqrt(np.pi / (0.5 * ELLIPSE_SIDES * np.sin(2.0 * np.pi / ELLIPSE_SIDES)))
            x, y = grow * np.cos(a), grow * np.sin(a)
        else:
            x, y = np.array([1.0, -1.0, -1.0, 1.0]), np.array([1.0, 1.0, -1.0, -1.0])
        return self.centre + np.outer(x * self.hu, self.u) + np.outer(y * self.hv, self.v)

    def in_front(self, p: np.ndarray) -> np.ndarray:
        """(k,) bool: points ``p`` (3, k) on the lit side of the light's plane."""
        return np.einsum("i,ik->k", self.normal, p - self.centre[:, None]) > 0

    def sample_points(self, side: int, offsets: np.ndarray) -> np.ndarray:
        """(3, k, side^2) stratified points on the light (area-uniform)."""
        s, t = strata(side, offsets)
        if self.ellipse:
            r, phi = np.sqrt(s), 2.0 * np.pi * t
            x, y = r * np.cos(phi), r * np.sin(phi)
        else:
            x, y = 2.0 * s - 1.0, 2.0 * t - 1.0
        return (self.centre[:, None, None] + self.u[:, None, None] * (self.hu * x)
                + self.v[:, None, None] * (self.hv * y))

    def form_factor(self, p: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(F, whole): the closed-form integral of cos over the light's solid angle seen from
        points ``p`` with unit normals ``n`` (3, k) (Lambert's polygon formula: irradiance =
        radiance * F), valid (``whole``) where the whole light lies above their horizon."""
        to = self.corners.T[:, None, :] - p[:, :, None]             # (3, k, m)
        whole = np.all(np.einsum("ik,ikm->km", n, to) >= 0.0, axis=1)
        a = to / np.linalg.norm(to, axis=0)
        b = np.roll(a, -1, axis=2)
        cross = np.cross(a, b, axis=0)
        norm = np.linalg.norm(cross, axis=0)
        angle = np.arctan2(norm, np.einsum("ikm,ikm->km", a, b))
        proj = np.einsum("ik,ikm->km", n, cross) / np.where(norm > 0, norm, 1.0)
        return np.abs(0.5 * np.sum(angle * proj, axis=1)), whole

    def hit_distance(self, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """(n,) distance along rays (rows (n, 3), unit dirs) to the light's lit face; inf where
        they miss it or meet it from behind."""
        den = dirs @ self.normal
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((self.centre - origins) @ self.normal) / den
        ok = (den < 0) & (t > 0)
        q = origins + dirs * np.where(ok, t, 0.0)[:, None] - self.centre
        x, y = (q @ self.u) / self.hu, (q @ self.v) / self.hv
        inside = (x * x + y * y <= 1.0) if self.ellipse else (np.abs(x) <= 1) & (np.abs(y) <= 1)
        return np.where(ok & inside, t, np.inf)
