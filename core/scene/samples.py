"""The sample scenes (the paper's Figure 15-17 setting): one specular object on the table of the
box room from :mod:`.rooms`, three cameras ("far", "close", "zoom"), 300x300, max_events 8.

    SAMPLES                       the sample names
    build(name, material=None)    the Scene, built in memory (no files read except the teapot data)
    sample_path(name)             sample_scenes/<name>.json in the repository

Objects (world space, Z up, metres; every object stands on the table top, centred on it):
  teapot        Newell's Utah teapot (32 bicubic Bezier patches, sample_scenes/data/teapot.json),
                scaled to 0.6 m wide; classes: rim+body, handle, spout, lid knob, lid, bottom.
  vase_mirror   a closed (watertight) vase: one NURBS surface of revolution of a closed profile
                (axis -> outside -> rounded lip -> inside -> axis); mirror.
  vase_glass    the same vase, glass of IOR 1.5.
  glass_sphere  an exact rational NURBS sphere (r = 0.15 m), glass of IOR 1.5.
  bowl          a closed bowl with a lid and a knob: three closed solids of revolution, three
                classes (bowl, lid, knob); mirror.

Every surface is oriented with Su x Sv pointing out of the solid (for the teapot: out of the
pot), so refraction has a consistent inside.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..geometry.nurbs import NurbsSurface
from ..geometry.primitives import bezier_patch, revolve, sphere, transform
from .io import look_at_matrix
from .model import Camera, ObjectMaterial, Patch, RenderSettings, Scene, SpecularObject
from .rooms import room

SAMPLES = ("teapot", "vase_mirror", "vase_glass", "glass_sphere", "bowl")

# core/scene/samples.py -> repository root (core/..) -> sample_scenes/
SAMPLE_DIR = Path(__file__).resolve().parent.parent.parent / "sample_scenes"
TEAPOT_DATA = SAMPLE_DIR / "data" / "teapot.json"

# Gap between the table top and the object's lowest point (m): keeps the flat bottoms off the
# table plane so no ray meets two coincident surfaces; invisible at 300x300.
LIFT = 1e-3

TEAPOT_WIDTH = 0.6          # m, spout tip to handle back
# Class ids of the teapot groups (the paper's equivalence classes): the rim joins the body
# smoothly; the knob, lid, handle, spout and bottom are separated by creases or intersections.
TEAPOT_CLASSES = {"rim": 0, "body": 0, "handle": 1, "spout": 2, "lid_knob": 3, "lid": 4,
                  "bottom": 5}

# Closed profiles (r, z) in metres, cubic B-spline control polygons with clamped uniform knots,
# each running from the axis (bottom outside) up the outside, over a rounded lip, down the inside
# and back to the axis, so the surface of revolution is a closed solid. Points on the axis at both
# ends with a horizontal first/last leg give smooth poles. Walking this way puts Su x Sv outward.
VASE_PROFILE = np.array([
    (0.0, 0.0), (0.0375, 0.0), (0.075, 0.0), (0.088, 0.004), (0.095, 0.03),       # base + foot
    (0.135, 0.09), (0.15, 0.17), (0.12, 0.255), (0.072, 0.315), (0.064, 0.365),    # belly, waist
    (0.085, 0.415), (0.11, 0.45),                                                  # flare
    (0.1138, 0.4554), (0.1041, 0.4623),                                            # rounded lip
    (0.1002, 0.457), (0.0744, 0.4207), (0.0521, 0.3665), (0.0613, 0.3096),         # inside
    (0.1094, 0.2493), (0.138, 0.1689), (0.1238, 0.0944), (0.085, 0.045),
    (0.076, 0.028), (0.06, 0.02), (0.03, 0.02), (0.0, 0.02)])                     # inner floor
BOWL_PROFILE = np.array([
    (0.0, 0.0), (0.05, 0.0), (0.09, 0.0), (0.1, 0.004), (0.105, 0.015),           # base + foot
    (0.16, 0.03), (0.215, 0.06), (0.24, 0.1), (0.245, 0.13),                       # outside
    (0.245, 0.137), (0.233, 0.137),                                                # rounded rim
    (0.233, 0.13), (0.228, 0.1), (0.205, 0.068), (0.155, 0.042), (0.1, 0.028),     # inside
    (0.05, 0.025), (0.0, 0.025)])
# The lid: underside from the axis out to the rim (resting on, and slightly sunk into, the
# bowl's rounded rim), round the edge, back over the dome to the axis.
LID_PROFILE = np.array([
    (0.0, 0.2), (0.07, 0.2), (0.155, 0.18), (0.215, 0.148), (0.24, 0.135),         # underside
    (0.252, 0.134), (0.256, 0.141),                                                # edge
    (0.25, 0.148), (0.225, 0.165), (0.16, 0.198), (0.07, 0.215), (0.0, 0.215)])   # dome
KNOB_RADIUS = 0.028         # m, sphere on the lid's top
KNOB_CENTER_Z = 0.236       # m above the bowl's base: sunk 7 mm into the dome (top at 0.215)
GLASS_SPHERE_RADIUS = 0.15  # m

FAR_FACTOR = 1.7            # far camera distance / close camera distance ...
FAR_MIN = 1.6               # ... but at least this far (m), so small objects look small
RENDER = dict(width=300, height=300, max_events=8)
ROOM_SIZE = (8.0, 8.0, 4.0)        # m, the rooms.room defaults, passed explicitly
TABLE_SIZE = (1.6, 1.0, 0.75)      # m (length x, depth y, height): the top is at z = 0.75


# --------------------------------------------------------------------------- materials
def mirror_material() -> ObjectMaterial:
    """Mirror with a little specular highlight."""
    return ObjectMaterial(kind="mirror", tint=(0.95, 0.95, 0.95), specular=0.25, shininess=96.0)


def glass_material(ior: float = 1.5) -> ObjectMaterial:
    return ObjectMaterial(kind="glass", ior=float(ior), tint=(1.0, 1.0, 1.0), specular=0.25,
                          shininess=96.0)


def dielectric_material(ior: float = 1.5) -> ObjectMaterial:
    return ObjectMaterial(kind="dielectric", ior=float(ior), tint=(1.0, 1.0, 1.0),
                          specular=0.25, shininess=96.0)


_PRESETS = {"mirror": mirror_material, "glass": glass_material, "dielectric": dielectric_material}


def _material(material, default: ObjectMaterial) -> ObjectMaterial:
    if material is None:
        return default
    if isinstance(material, ObjectMaterial):
        return material
    if isinstance(material, str) and material in _PRESETS:
        return _PRESETS[material]()
    raise ValueError(f"material: expected None, an ObjectMaterial or one of {sorted(_PRESETS)}, "
                     f"got {material!r}")


# --------------------------------------------------------------------------- objects
def load_teapot_data(path: str | Path = TEAPOT_DATA) -> dict:
    """The teapot data set: {"vertices" (306, 3), "patches" (32, 16) 0-based, "groups"}."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"teapot data: {path} not found (sample_scenes/data/teapot.json "
                                "ships with the repository)")
    d = json.loads(path.read_text(encoding="utf-8"))
    verts = np.asarray(d["vertices"], dtype=np.float64)
    patches = np.asarray(d["patches"], dtype=np.int64) - int(d.get("index_base", 1))
    if verts.shape != (306, 3) or patches.shape != (32, 16):
        raise ValueError(f"teapot data {path}: expected 306 vertices and 32 patches of 16, got "
                         f"{verts.shape} and {patches.shape}")
    if patches.min() < 0 or patches.max() >= len(verts):
        raise ValueError(f"teapot data {path}: patch index out of range")
    return {"vertices": verts, "patches": patches, "groups": d["groups"]}


def teapot_control_nets(data: dict | None = None) -> np.ndarray:
    """(32, 4, 4, 3) control nets in Newell's units as listed (row i, column j)."""
    data = load_teapot_data() if data is None else data
    return data["vertices"][data["patches"]].reshape(32, 4, 4, 3)


def teapot_patches(width: float = TEAPOT_WIDTH) -> list[Patch]:
    """The 32 teapot patches scaled to ``width`` along x, base at z = 0, bbox centred on the
    z axis in x and y. Each listed net is transposed (u along the listing's columns) so that
    Su x Sv points out of the pot."""
    data = load_teapot_data()
    nets = teapot_control_nets(data)
    pts = nets.reshape(-1, 3)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    s = width / (hi[0] - lo[0])
    offset = -s * np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]])
    group_of = {i: g for g, ids in data["groups"].items() for i in ids}
    out = []
    for i, net in enumerate(nets):
        g = group_of[i]
        ctrl = np.transpose(net, (1, 0, 2)) * s + offset
        out.append(Patch(name=f"{g}_{i:02d}", class_id=TEAPOT_CLASSES[g],
                         surface=bezier_patch(ctrl)))
    return out


def vase_surface() -> NurbsSurface:
    return revolve(VASE_PROFILE)


def bowl_patches() -> list[Patch]:
    knob = sphere((0.0, 0.0, KNOB_CENTER_Z), KNOB_RADIUS)
    return [Patch("bowl", 0, surface=revolve(BOWL_PROFILE)),
            Patch("lid", 1, surface=revolve(LID_PROFILE)),
            Patch("knob", 2, surface=knob)]


def _translate(patches: list[Patch], offset) -> list[Patch]:
    m = np.eye(4)
    m[:3, 3] = offset
    return [Patch(p.name, p.class_id, surface=transform(p.surface, m)) for p in patches]


def patches_bbox(patches: list[Patch]) -> tuple[np.ndarray, np.ndarray]:
    """Bounding box of the control points (contains the surfaces: convex hull property)."""
    pts = np.concatenate([p.surface.points.reshape(-1, 3) for p in patches])
    return pts.min(axis=0), pts.max(axis=0)


# --------------------------------------------------------------------------- cameras
def _camera(name: str, location, target, lens: float) -> Camera:
    return Camera(name=name, matrix_world=look_at_matrix(location, target), lens=float(lens),
                  clip_start=0.01, clip_end=100.0)


def _fit_distance(points: np.ndarray, target, direction, lens: float, fill: float,
                  sensor: float = 36.0) -> float:
    """Distance along ``direction`` (unit, target -> camera) at which every point lies within
    ``fill`` of the half-frame of a square image (AUTO fit: sensor_width spans the width)."""
    d = np.asarray(direction, dtype=np.float64)
    right = np.cross(-d, (0.0, 0.0, 1.0))
    right /= np.linalg.norm(right)
    up = np.cross(right, -d)
    rel = points - np.asarray(target, dtype=np.float64)
    x, y, z = rel @ right, rel @ up, rel @ d
    half = fill * 0.5 * sensor / lens              # tan of the allowed half angle
    return float(np.max(z + np.maximum(np.abs(x), np.abs(y)) / half))


def _direction(azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    a, e = np.radians(azimuth_deg), np.radians(elevation_deg)
    return np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])


def sample_points(patches: list[Patch], n: int = 9) -> np.ndarray:
    """n x n surface points per patch (for framing and tests)."""
    from ..geometry.nurbs import evaluate
    out = []
    for p in patches:
        u0, u1, v0, v1 = p.surface.domain
        uu, vv = np.meshgrid(np.linspace(u0, u1, n), np.linspace(v0, v1, n), indexing="ij")
        out.append(evaluate(p.surface, uu.ravel(), vv.ravel(), derivatives=0)[0])
    return np.concatenate(out)


def make_cameras(points: np.ndarray, zoom_target, azimuth: float, elevation: float,
                 bounds: tuple[np.ndarray, np.ndarray]) -> list[Camera]:
    """far / close / zoom cameras for an object given by surface ``points``.

    close: 50 mm, the object fills ~85% of the frame. far: 35 mm from FAR_FACTOR x the close
    distance (at least FAR_MIN; clamped inside ``bounds``, the room's inner box), the object a
    fifth to a third of the frame with the table and walls around it. zoom: 135 mm from the close
    camera's position aimed at ``zoom_target``, so a section of the surface fills the frame.
    """
    lo, hi = points.min(axis=0), points.max(axis=0)
    centre = (lo + hi) / 2
    d = _direction(azimuth, elevation)
    close_dist = _fit_distance(points, centre, d, 50.0, 0.85)
    close_loc = centre + close_dist * d
    far_dist = max(FAR_FACTOR * close_dist, FAR_MIN)
    blo, bhi = (np.asarray(b, dtype=np.float64) for b in bounds)
    margin = 0.15
    with np.errstate(divide="ignore", invalid="ignore"):
        limits = np.where(d > 0, (bhi - margin - centre) / d,
                          np.where(d < 0, (blo + margin - centre) / d, np.inf))
    far_dist = float(min(far_dist, limits.min()))
    far_loc = centre + far_dist * d
    return [_camera("far", far_loc, centre, 35.0),
            _camera("close", close_loc, centre, 50.0),
            _camera("zoom", close_loc, zoom_target, 135.0)]


# --------------------------------------------------------------------------- scenes
def _object(name: str):
    """(patches in object space, base at z = 0 and centred on the z axis; default material;
    zoom spec; camera azimuth and elevation in degrees). The zoom spec is ("point", xyz) in
    object space, or ("band", z): the sampled surface point nearest the camera at height z."""
    if name == "teapot":
        patches = teapot_patches()
        # where the spout leaves the body: the spout/body intersection (two classes meet)
        spout = [p for p in patches if p.name.startswith("spout")]
        base = sample_points(spout[:2], 5)
        return patches, mirror_material(), ("point", base[np.argmin(base[:, 0])]), -60.0, 22.0
    if name in ("vase_mirror", "vase_glass"):
        mat = mirror_material() if name == "vase_mirror" else glass_material(1.5)
        # the neck just above the waist, up to the flared lip
        return [Patch("vase", 0, surface=vase_surface())], mat, ("band", 0.36), -70.0, 18.0
    if name == "glass_sphere":
        r = GLASS_SPHERE_RADIUS
        az, el = -70.0, 18.0
        # the silhouette on the right: refraction near grazing incidence next to the room
        view = -_direction(az, el)
        right = np.cross(view, (0.0, 0.0, 1.0))
        right /= np.linalg.norm(right)
        up = np.cross(right, view)
        target = np.array([0.0, 0.0, r]) + r * (0.85 * right + 0.25 * up)
        return ([Patch("sphere", 0, surface=sphere((0.0, 0.0, r), r))], glass_material(1.5),
                ("point", target), az, el)
    if name == "bowl":
        # the knob on the lid: three classes (knob, lid, bowl rim behind) in one view
        return (bowl_patches(), mirror_material(), ("point", (0.0, 0.0, KNOB_CENTER_Z - 0.01)),
                -65.0, 28.0)
    raise ValueError(f"name: unknown sample {name!r}; samples: {', '.join(SAMPLES)}")


def table_top() -> np.ndarray:
    """Centre of the table's top surface (world)."""
    return np.array([0.0, 0.0, TABLE_SIZE[2]])


def room_bounds() -> tuple[np.ndarray, np.ndarray]:
    """The room's inner box (world)."""
    hx, hy, sz = ROOM_SIZE[0] / 2, ROOM_SIZE[1] / 2, ROOM_SIZE[2]
    return np.array([-hx, -hy, 0.0]), np.array([hx, hy, sz])


def build(name: str, material=None) -> Scene:
    """The sample scene ``name`` (one of SAMPLES). ``material`` overrides the object material:
    an ObjectMaterial, or "mirror" / "glass" / "dielectric" (IOR 1.5 presets)."""
    if name not in SAMPLES:
        raise ValueError(f"name: unknown sample {name!r}; samples: {', '.join(SAMPLES)}")
    mat_override = None if material is None else _material(material, None)
    meshes, materials, lights, world = room(size=ROOM_SIZE, table_size=TABLE_SIZE)
    patches, default_mat, (zkind, zval), az, el = _object(name)
    lo, _ = patches_bbox(patches)
    offset = table_top() + (0.0, 0.0, LIFT - lo[2])
    patches = _translate(patches, offset)
    pts = sample_points(patches, 17)
    if zkind == "point":
        zoom = np.asarray(zval, dtype=np.float64) + offset
    else:
        z = float(zval) + offset[2]
        dense = sample_points(patches, 33)
        band = dense[np.abs(dense[:, 2] - z) < 0.01]
        zoom = band[np.argmax(band @ _direction(az, el))]
    cams = make_cameras(pts, zoom, az, el, room_bounds())
    obj_mat = default_mat if mat_override is None else mat_override
    return Scene(objects=[SpecularObject(name=name, patches=patches, material=obj_mat)],
                 meshes=meshes, materials=materials, lights=lights, world=world, cameras=cams,
                 render=RenderSettings(**RENDER), name=name)


def sample_path(name: str) -> Path:
    """sample_scenes/<name>.json; FileNotFoundError (naming the regeneration script) if missing."""
    if name not in SAMPLES:
        raise ValueError(f"name: unknown sample {name!r}; samples: {', '.join(SAMPLES)}")
    path = SAMPLE_DIR / f"{name}.json"
    if not path.is_file():
        raise FileNotFoundError(f"sample scene {name!r}: {path} does not exist; run "
                                "`python sample_scenes/build_scenes.py` to generate it")
    return path
