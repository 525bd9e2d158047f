"""The Figure 15 room: valid scene content, inward-facing walls, exact file round trip."""

import numpy as np
import pytest

from riray.geometry.nurbs import NurbsSurface
from riray.scene.io import load_scene, save_scene, scene_from_dict, scene_to_dict
from riray.scene.model import Patch, Scene, SpecularObject
from riray.scene.rooms import room


def scene_with_room(**kw):
    meshes, materials, lights, world = room(**kw)
    surf = NurbsSurface(1, 1, np.array([0, 0, 1, 1.0]), np.array([0, 0, 1, 1.0]),
                        np.array([[[0, 0, 1.0], [0, 1, 1]], [[1, 0, 1], [1, 1, 1]]]), np.ones((2, 2)))
    obj = SpecularObject(name="o", patches=[Patch(name="p", class_id=0, surface=surf)])
    return Scene(objects=[obj], meshes=meshes, materials=materials, lights=lights, world=world)


def test_room_validates_and_round_trips(tmp_path):
    s = scene_with_room(sun=True, ceiling=False)
    assert sum(len(m.triangles) for m in s.meshes) < 2000
    assert {"checker", "stripes", "gradient"} <= {m.color.kind for m in s.materials.values()}
    assert [li.kind for li in s.lights] == ["point", "sun"]
    d = scene_to_dict(s)
    assert scene_to_dict(scene_from_dict(d)) == d
    save_scene(s, tmp_path / "room.json")
    assert scene_to_dict(load_scene(tmp_path / "room.json")) == d


def test_walls_face_inwards_and_table_top_height():
    s = scene_with_room(size=(6.0, 5.0, 3.0), table_size=(1.2, 0.8, 0.7))
    centre = np.array([0.0, 0.0, 1.5])
    for m in s.meshes:
        v = m.vertices[m.triangles]
        n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
        assert m.uvs is not None and m.uvs.shape == (len(m.vertices), 2)
        if not m.name.startswith("table"):
            assert np.all(np.einsum("ij,ij->i", n, centre - v[:, 0]) > 0), m.name
    top = next(m for m in s.meshes if m.name == "table_top")
    assert top.vertices[:, 2].max() == 0.7
    lo, hi = np.min([m.vertices.min(0) for m in s.meshes], 0), np.max([m.vertices.max(0) for m in s.meshes], 0)
    np.testing.assert_allclose([lo, hi], [[-3, -2.5, 0], [3, 2.5, 3]])


def test_room_rejects_table_that_does_not_fit():
    with pytest.raises(ValueError, match="does not fit"):
        room(size=(1.0, 1.0, 1.0))
