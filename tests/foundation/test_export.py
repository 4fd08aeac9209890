"""Export (foundation/export.py) against its oracles: the Khronos validator, a re-import by trimesh, Mitsuba's own
surface at each texel, the glTF conventions written out (sRGB base colour, roughness in G, F0 of
KHR_materials_specular) and the photo bake against a texture known in closed form."""

from __future__ import annotations

import io
import json
import shutil
import struct

import numpy as np
import pytest
import trimesh

from foundation.export import (FORMATS, ExportMaterial, ExportMesh, REIMPORT_PSNR_DB, reimport, reimport_check,
                               rotation_to_y_up, scatter, split_uv_mesh, texel_surface, unwrap, validate_gltf,
                               write_model)
from foundation.imageio import linear_to_srgb

NODE = shutil.which("node")
needs_node = pytest.mark.skipif(NODE is None, reason="node is not installed: the Khronos validator runs under node")


def _sphere(subdiv: int = 3):
    m = trimesh.creation.icosphere(subdivisions=subdiv)
    return np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int64)


def _colour(p: np.ndarray) -> np.ndarray:
    """A smooth colour field over the unit sphere, in (0.1, 0.9)."""
    return np.clip(0.5 + 0.4 * np.stack([np.sin(2 * p[:, 0]), np.cos(2 * p[:, 1]), p[:, 2]], 1), 0, 1)


@pytest.fixture(scope="module")
def model():
    v, f = _sphere()
    at = unwrap(v, f, 256, 4)
    vv = v[at.vertex_of]
    surf = texel_surface(vv, at.faces, at.uvs, at.width, at.height, {"colour": _colour(vv)})
    tex = scatter(surf.mask, surf.attributes["colour"])
    rough = np.full(tex.shape[:2], 0.6, np.float32)
    mesh = ExportMesh(vv, at.faces, at.uvs, _colour(vv))
    mat = ExportMaterial(name="sphere", base_colour=tex, roughness=rough, specular=np.full(tex.shape[:2], 0.35),
                         normal=np.dstack([np.zeros_like(rough), np.zeros_like(rough), np.ones_like(rough)]))
    return mesh, mat, surf, at


def test_texel_surface_is_mitsubas_surface(model):
    """A per-vertex attribute equal to the position interpolates to the texel's surface point (float32 rounding,
    1e-5); every covered texel's point lies on the mesh (radius within the flat triangles' sag of the unit sphere)."""
    mesh, _, surf, at = model
    v = mesh.positions
    s2 = texel_surface(v, at.faces, at.uvs, at.width, at.height, {"p": v})
    assert np.abs(s2.attributes["p"] - s2.position).max() < 1e-5
    r = np.linalg.norm(surf.position, axis=1)
    assert r.max() < 1 + 1e-5 and r.min() > 0.98
    assert surf.mask.mean() > 0.4  # xatlas packs the charts: most of the square is used


def test_split_uv_mesh_keeps_each_corner():
    """An OBJ's (position, uv) corners become one vertex each, the uv flipped to glTF's v-down."""
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    fuv = np.array([[0, 1, 2], [4, 2, 3]])  # vertex 0 has two uvs (a seam)
    uvs = np.array([[0, 0], [1, 0], [1, 1], [0, 1], [0.5, 0.25]])
    f2, uv2, of = split_uv_mesh(faces, fuv, uvs)
    assert len(of) == 5 and sorted(of.tolist()) == [0, 0, 1, 2, 3]
    for tri, tri_uv, tri2 in zip(faces, fuv, f2):
        assert (of[tri2] == tri).all()
        assert np.allclose(uv2[tri2], np.c_[uvs[tri_uv][:, 0], 1 - uvs[tri_uv][:, 1]])


def test_rotation_to_y_up():
    rng = np.random.default_rng(0)
    for up in [*rng.normal(size=(5, 3)), np.array([0.0, -1.0, 0.0]), np.array([0.0, 1.0, 0.0])]:
        r = rotation_to_y_up(up)
        assert np.allclose(r @ r.T, np.eye(3), atol=1e-9) and np.isclose(np.linalg.det(r), 1)
        assert np.allclose(r @ (up / np.linalg.norm(up)), [0, 1, 0], atol=1e-9)


@pytest.mark.parametrize("fmt", FORMATS)
def test_write_and_read_back(model, tmp_path, fmt):
    """Every format re-imports (trimesh) with the vertex and triangle counts written, UVs in [0, 1] equal to those
    written (1e-6), the texture's size, and a render of the re-import within REIMPORT_PSNR_DB of the original's;
    the validator: :func:`test_khronos_validator_reports_no_issue`."""
    mesh, mat, _, at = model
    files = write_model(tmp_path, "m", fmt, mesh, mat)
    assert all(p.is_file() for p in files)
    r = reimport(files[0])
    assert len(r.vertices) == len(mesh.positions) and len(r.faces) == len(mesh.faces)
    assert np.abs(r.uvs - mesh.uvs).max() < 1e-6
    assert r.base_colour.shape == (at.height, at.width, 3)
    check = reimport_check(files[0], mesh, mat)
    assert check["uv_in_range"] and check["render_psnr"] >= REIMPORT_PSNR_DB, check


@needs_node
@pytest.mark.parametrize("fmt", ["glb", "gltf"])
def test_khronos_validator_reports_no_issue(model, tmp_path, fmt):
    """Both glTF forms (with a normal map, tangents, KHR_materials_specular, COLOR_0): 0 errors, 0 warnings; and the
    validator does catch a broken file (a truncated GLB)."""
    mesh, mat, _, _ = model
    path = write_model(tmp_path, "m", fmt, mesh, mat)[0]
    issues = validate_gltf(path)["issues"]
    assert issues["numErrors"] == 0 and issues["numWarnings"] == 0, issues["messages"]
    if fmt == "glb":
        bad = tmp_path / "bad.glb"
        bad.write_bytes(path.read_bytes()[: len(path.read_bytes()) // 2])
        assert validate_gltf(bad)["issues"]["numErrors"] > 0


def test_reimport_check_fails_on_flipped_uvs(model, tmp_path):
    """The check can fail: UVs written v-up (the OBJ convention, wrongly) render another picture."""
    mesh, mat, _, _ = model
    bad = ExportMesh(mesh.positions, mesh.faces, np.c_[mesh.uvs[:, 0], 1 - mesh.uvs[:, 1]], mesh.colours)
    files = write_model(tmp_path, "bad", "glb", bad, mat)
    check = reimport_check(files[0], mesh, mat)
    assert check["render_psnr"] < 30, check


def _glb_json_and_images(path):
    data = path.read_bytes()
    n = struct.unpack_from("<I", data, 12)[0]
    doc = json.loads(data[20:20 + n])
    blob_start = 20 + n + 8
    images = {}
    for im in doc["images"]:
        bv = doc["bufferViews"][im["bufferView"]]
        from PIL import Image

        raw = data[blob_start + bv.get("byteOffset", 0):blob_start + bv.get("byteOffset", 0) + bv["byteLength"]]
        images[im["name"]] = np.asarray(Image.open(io.BytesIO(raw)))
    return doc, images


def test_colour_spaces_and_material_conventions(tmp_path):
    """Base colour is sRGB-encoded (linear 0.2 → round(255·srgb(0.2)) = 124), roughness sits linear in G (0.6 → 153),
    metalness in B; KHR_materials_specular gives F0 = 0.04 · 2 · specular = ggx_uv's 0.08 · specular."""
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], np.float64)
    mesh = ExportMesh(v, np.array([[0, 1, 2], [0, 2, 3]]), np.array([[0, 1], [1, 1], [1, 0], [0, 0]], np.float64))
    s = np.full((4, 4), 0.35, np.float32)
    mat = ExportMaterial(base_colour=np.full((4, 4, 3), 0.2, np.float32), roughness=np.full((4, 4), 0.6),
                         metallic=np.full((4, 4), 1.0), metallic_factor=1.0, specular=s)
    path = write_model(tmp_path, "q", "glb", mesh, mat)[0]
    doc, images = _glb_json_and_images(path)
    assert int(images["base_colour"][0, 0, 0]) == int(round(255 * float(linear_to_srgb(np.float32(0.2))))) == 124
    mr = images["metallic_roughness"][0, 0]
    assert int(mr[1]) == 153 and int(mr[2]) == 255
    ext = doc["materials"][0]["extensions"]["KHR_materials_specular"]
    f0_gltf = 0.04 * ext["specularColorFactor"][0] * ext["specularFactor"] * images["specular"][0, 0, 3] / 255
    assert abs(f0_gltf - 0.08 * 0.35) < 0.08 / 255
    assert doc["asset"]["version"] == "2.0"


def test_photo_bake_recovers_a_known_texture():
    """Photos of a sphere emitting a known colour field, baked back into its atlas through their cameras
    (visibility by ray casting): the texels seen get the field back within 0.02 mean absolute error (bilinear photo
    lookups at 96 px), and at least 95 % of them are seen by one of 8 cameras around it."""
    from inverse.capture import CaptureCamera, MITSUBA_FROM_COLMAP, project_photos, render_mesh

    import mitsuba as mi

    v, f = _sphere(4)
    col = _colour(v)
    cams, photos = [], []
    for k in range(8):
        a = 2 * np.pi * k / 8
        eye = [3.2 * np.cos(a), 1.2 * (-1) ** k, 3.2 * np.sin(a)]
        m = np.array(mi.ScalarTransform4f().look_at(origin=eye, target=[0, 0, 0], up=[0, 1, 0]).matrix, np.float64)
        c = CaptureCamera(f"c{k}", 96, 96, 140.0, 48.0, 48.0, (m @ np.linalg.inv(MITSUBA_FROM_COLMAP)).tolist())
        cams.append(c)
        photos.append(render_mesh(v, f, col, c, spp=16))
    at = unwrap(v, f, 128, 2)
    vv = v[at.vertex_of]
    surf = texel_surface(vv, at.faces, at.uvs, at.width, at.height, {"colour": _colour(vv)})
    acc, w = project_photos(v, f, surf.position, surf.normal, cams, photos)
    seen = w > 0
    assert seen.mean() > 0.95
    baked = acc[seen] / w[seen, None]
    truth = _colour(surf.position[seen] / np.linalg.norm(surf.position[seen], axis=1, keepdims=True))
    assert np.abs(baked - truth).mean() < 0.02
    gains = [np.array([2.0, 1.0, 0.5])] * len(cams)  # a photo twice as bright in red is divided back
    acc2, _ = project_photos(v, f, surf.position, surf.normal, cams, [p * g for p, g in zip(photos, gains)], gains)
    assert np.allclose(acc2, acc, atol=1e-5)
