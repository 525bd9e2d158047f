"""The scene model: plain dataclasses, world space, metres, linear RGB in [0, inf).

Conventions (shared by every module):
- Right-handed world, Z up (Blender's).
- Colours are linear (scene-referred) RGB triples; the PNG writer applies the sRGB transfer.
- A scene holds one or more *specular objects* (each baked into its own RI-Tree), made of
  patches, and an *environment* of triangle meshes that their output rays see; a ray leaving
  one specular object may meet another.
- Patch ids are the index of the patch in ``SpecularObject.patches``; class ids group patches
  joined smoothly (the paper's equivalence classes). -1 is reserved for "no patch" (environment).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from ..geometry.nurbs import NurbsSurface
from .graph import ShaderGraph

RGB = tuple[float, float, float]


# --------------------------------------------------------------------------- textures / materials
@dataclass
class Texture:
    """A colour source evaluated at surface points.

    kind:
      "constant"  color
      "checker"   color, color2, scale (checks per unit of the coordinate)
      "stripes"   color, color2, scale, axis (0/1/2: stripes vary along that coordinate)
      "gradient"  color -> color2 linearly along ``axis`` from ``start`` to ``end`` (clamped)
      "image"     an image file (PNG or .npy float HxWx3) at uv * scale, bilinear, repeat wrap,
                  uv (0, 0) = bottom-left of the image
    coords: "uv" (mesh UVs) or "world" (world xyz; uv = xy for 2D kinds). Evaluation and exact
    rules: trace/textures.py; file defaults (coords "uv" for images): docs/scene-format.md.
    """

    kind: str = "constant"
    color: RGB = (0.8, 0.8, 0.8)
    color2: RGB = (0.2, 0.2, 0.2)
    scale: float = 1.0
    axis: int = 2
    start: float = 0.0
    end: float = 1.0
    coords: str = "world"
    path: str | None = None          # image file, relative to the scene file
    image: np.ndarray | None = field(default=None, repr=False)  # loaded HxWx3 float64, linear


@dataclass
class Material:
    """An environment material. kind: "diffuse" (Lambert, lit), "emission" (unlit colour) or
    "nodes" (a shader node graph, ``graph``: emission plus a lit diffuse albedo, evaluated by
    trace/nodes.py; ``color`` and ``strength`` are not used). A "diffuse" material with
    ``metallic`` m > 0 reflects: m of its colour is a metal of that tint and ``roughness``
    (0..1, Blender's), the rest stays diffuse, under a dielectric layer of normal
    reflectance ``specular`` when it is > 0 (trace/shading.py)."""

    name: str
    kind: str = "diffuse"
    color: Texture = field(default_factory=Texture)
    strength: float = 1.0
    graph: ShaderGraph | None = None
    metallic: float = 0.0
    roughness: float = 0.5
    specular: float = 0.0                # normal reflectance of a dielectric specular layer


@dataclass
class ObjectMaterial:
    """The specular object's material.

    kind:
      "mirror"      reflection only
      "glass"       refraction with ``ior``; total internal reflection; no Fresnel
      "dielectric"  at the first hit: Fresnel-weighted reflection + the transmitted (glass) chain
    Final colour = diffuse*base_color*lambert + specular*phong(shininess)
                   + (1 - diffuse) * tint * (colour carried by the output ray(s)).
    """

    kind: str = "mirror"
    ior: float = 1.5
    tint: RGB = (1.0, 1.0, 1.0)
    base_color: RGB = (0.8, 0.8, 0.8)
    diffuse: float = 0.0
    specular: float = 0.3
    shininess: float = 64.0


# --------------------------------------------------------------------------- geometry containers
@dataclass
class Patch:
    """One patch of the specular object: a rational NURBS surface (Bezier is the special case)
    or a triangle mesh (one patch id for the whole mesh). A mesh is flat shaded, or smooth
    where ``normals`` gives each triangle corner its unit normal (the shading normal at a hit
    is their barycentric blend); a ray crossing a mesh enters the object through the front
    of a triangle (its winding normal (v1-v0)x(v2-v0) faces the ray) and leaves through its
    back."""

    name: str
    class_id: int
    surface: NurbsSurface | None = None
    vertices: np.ndarray | None = None   # (n, 3) float64, mesh patches only
    triangles: np.ndarray | None = None  # (m, 3) int64, mesh patches only
    normals: np.ndarray | None = None    # (m, 3, 3) float64 unit corner normals, or None (flat)

    @property
    def is_mesh(self) -> bool:
        return self.surface is None


@dataclass
class SpecularObject:
    name: str
    patches: list[Patch]
    material: ObjectMaterial = field(default_factory=ObjectMaterial)


@dataclass
class Mesh:
    """An environment triangle mesh in world space."""

    name: str
    vertices: np.ndarray                 # (n, 3) float64
    triangles: np.ndarray                # (m, 3) int64
    material: str                        # name of a Material in Scene.materials
    uvs: np.ndarray | None = None        # (n, 2) per-vertex UVs, or None
    smooth: bool = False                 # interpolate vertex normals (else flat)


@dataclass
class Light:
    """kind "point": ``position``, radiant ``power`` in W (irradiance = power/(4 pi r^2)).
    kind "sun": ``direction`` the light travels along (unit), ``strength`` in W/m^2.
    kind "area": a one-sided Lambertian emitter centred at ``position``, facing ``direction``
    (unit), its first side along ``axis`` (unit, perpendicular to it); ``size`` (metres along
    axis, along direction x axis), ``shape`` "rectangle" or "ellipse"; radiant ``power`` in W
    (radiance = power / (pi * area), Cycles' convention)."""

    name: str
    kind: str = "point"
    color: RGB = (1.0, 1.0, 1.0)
    position: tuple[float, float, float] = (0.0, 0.0, 5.0)
    power: float = 1000.0
    direction: tuple[float, float, float] = (0.0, 0.0, -1.0)
    strength: float = 3.0
    shadows: bool = True
    axis: tuple[float, float, float] = (1.0, 0.0, 0.0)
    size: tuple[float, float] = (1.0, 1.0)
    shape: str = "rectangle"

    @property
    def area(self) -> float:
        """Emitting area in m^2 (area lights)."""
        a = float(self.size[0]) * float(self.size[1])
        return a * np.pi / 4.0 if self.shape == "ellipse" else a


@dataclass
class World:
    """What a ray that escapes everything sees, times ``strength``. kind: "color", "gradient"
    (``color`` at and below the horizon -> ``zenith``, t = clamp(direction z, 0, 1)), "image"
    (equirectangular, +X at the image centre, like Blender), "nodes" (the emission of the
    shader node graph ``graph`` for the ray direction, trace/nodes.py). With ``sky`` set it
    also lights diffuse surfaces, the occlusion of the scene sampled (trace/shading.py)."""

    kind: str = "color"
    color: RGB = (0.05, 0.05, 0.05)
    zenith: RGB = (0.3, 0.4, 0.7)
    path: str | None = None
    image: np.ndarray | None = field(default=None, repr=False)
    strength: float = 1.0
    ambient: float = 0.0                 # constant ambient term for diffuse environment shading
    graph: ShaderGraph | None = None
    sky: bool = False                    # the world lights diffuse surfaces (occlusion sampled)


@dataclass
class Camera:
    """Blender camera conventions: looks down its local -Z, up is local +Y.

    lens and sensor sizes in mm; sensor_fit "AUTO" | "HORIZONTAL" | "VERTICAL"; shift in units of
    the fitted sensor dimension (Blender's rule); ortho_scale = size in metres of the fitted frame
    side (the larger side for AUTO). Exact rules: scene/camera.py.
    """

    name: str
    matrix_world: np.ndarray             # (4, 4) camera-to-world, rotation orthonormal
    kind: str = "perspective"            # or "orthographic"
    lens: float = 50.0
    sensor_width: float = 36.0
    sensor_height: float = 24.0
    sensor_fit: str = "AUTO"
    shift_x: float = 0.0
    shift_y: float = 0.0
    ortho_scale: float = 7.0
    clip_start: float = 0.1
    clip_end: float = 1000.0


@dataclass
class RenderSettings:
    width: int = 300
    height: int = 300
    max_events: int = 8                  # reflections/refractions before f returns the null ray


@dataclass
class Scene:
    objects: list[SpecularObject]
    meshes: list[Mesh] = field(default_factory=list)
    materials: dict[str, Material] = field(default_factory=dict)
    lights: list[Light] = field(default_factory=list)
    world: World = field(default_factory=World)
    cameras: list[Camera] = field(default_factory=list)
    render: RenderSettings = field(default_factory=RenderSettings)
    name: str = "scene"

    @property
    def object(self) -> SpecularObject:
        """The scene's specular object; ValueError when it has several (``view`` picks one)."""
        if len(self.objects) != 1:
            raise ValueError(f"the scene has {len(self.objects)} specular objects "
                             f"({object_names(self.objects)}); name the one meant")
        return self.objects[0]

    def object_index(self, name: str) -> int:
        """The index of the specular object called ``name`` (ValueError naming the others)."""
        for i, obj in enumerate(self.objects):
            if obj.name == name:
                return i
        raise ValueError(f"no specular object named {name!r}; objects: "
                         f"{object_names(self.objects)}")

    def view(self, index: int) -> "Scene":
        """The scene as specular object ``index`` sees it: that object alone (its bake, its
        tree and its exact tracer), the environment, lights, world, cameras and render
        settings shared (not copied) with this scene."""
        return replace(self, objects=[self.objects[index]])

    def camera(self, name: str | None) -> Camera:
        """The camera called ``name`` (the first one when None)."""
        if not self.cameras:
            raise ValueError("scene has no cameras")
        if name is None:
            return self.cameras[0]
        for cam in self.cameras:
            if cam.name == name:
                return cam
        raise ValueError(f"no camera named {name!r}; cameras: {[c.name for c in self.cameras]}")


def object_names(objects) -> str:
    """The names of specular objects, comma separated, for messages."""
    return ", ".join(repr(o.name) for o in objects)
