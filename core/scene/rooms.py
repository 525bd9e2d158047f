"""The paper's Figure 15 environment: a box room with differently textured walls and a table.

Geometry is in metres, Z up. The room spans x in [-sx/2, sx/2], y in [-sy/2, sy/2], z in
[0, sz]; its faces wind so that their normals point into the room. The table is centred on the
z axis with its top surface at z = table_size[2], where the specular object is meant to sit.
Every mesh carries per-vertex UVs in metres along the surface (u along the face, v up the walls),
so the uv-mapped procedural textures have sizes in metres.
"""

from __future__ import annotations

import numpy as np

from .model import Light, Material, Mesh, Texture, World

TABLE_TOP_THICKNESS = 0.05   # m
TABLE_LEG_WIDTH = 0.06       # m, square legs
TABLE_LEG_INSET = 0.05       # m, from the top's edges


def _quad(p0, eu, ev) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One rectangle p0 + [0,1] eu + [0,1] ev as 2 triangles facing eu x ev; UVs in metres."""
    p0, eu, ev = (np.asarray(a, dtype=np.float64) for a in (p0, eu, ev))
    verts = np.array([p0, p0 + eu, p0 + eu + ev, p0 + ev])
    lu, lv = np.linalg.norm(eu), np.linalg.norm(ev)
    uvs = np.array([[0.0, 0.0], [lu, 0.0], [lu, lv], [0.0, lv]])
    return verts, np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int64), uvs


def _merge(parts) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    verts, tris, uvs, n = [], [], [], 0
    for v, t, uv in parts:
        verts.append(v)
        tris.append(t + n)
        uvs.append(uv)
        n += len(v)
    return np.concatenate(verts), np.concatenate(tris), np.concatenate(uvs)


def _box(lo, hi) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """An axis-aligned box [lo, hi] with outward-facing sides (24 vertices, 12 triangles)."""
    (x0, y0, z0), (x1, y1, z1) = lo, hi
    dx, dy, dz = x1 - x0, y1 - y0, z1 - z0
    return _merge([
        _quad((x0, y0, z1), (dx, 0, 0), (0, dy, 0)),      # top    +z
        _quad((x0, y0, z0), (0, dy, 0), (dx, 0, 0)),      # bottom -z
        _quad((x0, y0, z0), (dx, 0, 0), (0, 0, dz)),      # front  -y
        _quad((x1, y1, z0), (-dx, 0, 0), (0, 0, dz)),     # back   +y
        _quad((x1, y0, z0), (0, dy, 0), (0, 0, dz)),      # right  +x
        _quad((x0, y1, z0), (0, -dy, 0), (0, 0, dz)),     # left   -x
    ])


def _tex(kind: str, color, color2=(0.0, 0.0, 0.0), **kw) -> Texture:
    return Texture(kind=kind, color=color, color2=color2, coords="uv", **kw)


def room(size=(8.0, 8.0, 4.0), table: bool = True, table_size=(1.6, 1.0, 0.75),
         light_power: float = 600.0, sun: bool = False, ceiling: bool = True
         ) -> tuple[list[Mesh], dict[str, Material], list[Light], World]:
    """Build the room: (meshes, materials, lights, world), about 80 triangles.

    Walls: north (+y) an orange-to-yellow gradient up the wall, south (-y) vertical stripes
    0.5 m wide, east (+x) a 0.5 m checker, west (-x) a blue-to-teal gradient along the wall;
    floor a 1 m checker; ceiling plain. ``table`` adds a table of ``table_size`` (length along x,
    depth along y, height) in metres with a 12.5 cm checker top and four legs. Lights: a point
    light of ``light_power`` W below the ceiling, off-centre; ``sun`` adds a sun light (it only
    reaches the inside when ``ceiling`` is False, since lights cast shadows). World: a grey-blue
    sky gradient with ambient irradiance 0.6 W/m^2.
    """
    sx, sy, sz = (float(s) for s in size)
    tx, ty, th = (float(s) for s in table_size)
    if min(sx, sy, sz) <= 0 or (table and min(tx, ty, th) <= TABLE_TOP_THICKNESS):
        raise ValueError(f"room size {size} and table size {table_size} must be positive "
                         f"(table height > {TABLE_TOP_THICKNESS} m)")
    if table and (tx >= sx or ty >= sy or th >= sz):
        raise ValueError(f"table {table_size} does not fit in the room {size}")
    hx, hy = sx / 2, sy / 2
    faces = {  # name -> (p0, eu, ev, texture); eu x ev points into the room
        "floor": ((-hx, -hy, 0), (sx, 0, 0), (0, sy, 0),
                  _tex("checker", (0.75, 0.72, 0.65), (0.25, 0.22, 0.2), scale=1.0)),
        "wall_north": ((-hx, hy, 0), (sx, 0, 0), (0, 0, sz),
                       _tex("gradient", (0.8, 0.35, 0.1), (0.9, 0.8, 0.2), axis=1, end=sz)),
        "wall_south": ((hx, -hy, 0), (-sx, 0, 0), (0, 0, sz),
                       _tex("stripes", (0.8, 0.8, 0.8), (0.15, 0.35, 0.6), axis=0, scale=2.0)),
        "wall_east": ((hx, hy, 0), (0, -sy, 0), (0, 0, sz),
                      _tex("checker", (0.7, 0.2, 0.2), (0.9, 0.85, 0.8), scale=2.0)),
        "wall_west": ((-hx, -hy, 0), (0, sy, 0), (0, 0, sz),
                      _tex("gradient", (0.1, 0.2, 0.7), (0.1, 0.7, 0.6), axis=0, end=sy)),
    }
    if ceiling:
        faces["ceiling"] = ((-hx, -hy, sz), (0, sy, 0), (sx, 0, 0),
                            Texture(kind="constant", color=(0.85, 0.85, 0.85)))
    meshes, materials = [], {}
    for name, (p0, eu, ev, tex) in faces.items():
        v, t, uv = _quad(p0, eu, ev)
        materials[name] = Material(name=name, color=tex)
        meshes.append(Mesh(name=name, vertices=v, triangles=t, material=name, uvs=uv))
    if table:
        z0 = th - TABLE_TOP_THICKNESS
        v, t, uv = _box((-tx / 2, -ty / 2, z0), (tx / 2, ty / 2, th))
        materials["table_top"] = Material(
            name="table_top", color=_tex("checker", (0.9, 0.9, 0.85), (0.1, 0.1, 0.12), scale=8.0))
        meshes.append(Mesh(name="table_top", vertices=v, triangles=t, material="table_top", uvs=uv))
        ix, iy = tx / 2 - TABLE_LEG_INSET, ty / 2 - TABLE_LEG_INSET
        w = TABLE_LEG_WIDTH
        legs = [_box((x - w * (x > 0), y - w * (y > 0), 0.0),
                     (x + w * (x < 0), y + w * (y < 0), z0))
                for x in (-ix, ix) for y in (-iy, iy)]
        v, t, uv = _merge(legs)
        materials["table_legs"] = Material(name="table_legs",
                                           color=Texture(kind="constant", color=(0.35, 0.2, 0.1)))
        meshes.append(Mesh(name="table_legs", vertices=v, triangles=t, material="table_legs",
                           uvs=uv))
    lights = [Light(name="lamp", kind="point", position=(0.2 * sx, -0.15 * sy, sz - 0.4),
                    power=float(light_power))]
    if sun:
        d = np.array([-0.4, 0.3, -1.0])
        d /= np.linalg.norm(d)
        lights.append(Light(name="sun", kind="sun", direction=tuple(float(x) for x in d),
                            strength=3.0))
    world = World(kind="gradient", color=(0.6, 0.65, 0.7), zenith=(0.25, 0.4, 0.8), ambient=0.6)
    return meshes, materials, lights, world
