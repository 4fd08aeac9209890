"""Models that leave Mitsuba: a triangle mesh with UVs, vertex colours and a metallic-roughness material, written as
glTF 2.0 (``.glb`` or ``.gltf`` + ``.bin`` + PNGs, through ``pygltflib``) or Wavefront OBJ + MTL; a UV atlas for a
mesh without one (``xatlas``); texel maps of any per-vertex quantity baked through Mitsuba's own UV parameterisation;
the Khronos validator; a re-import (``trimesh``).

Conventions written into every file (glTF 2.0 §3.4, §3.9): +Y up, metres (``ExportMesh.to_gltf`` is the rigid map
and scale from the source's frame); UV (0, 0) at the top-left texel, v down — the same as Mitsuba's bitmap lookup, so a
Mitsuba uv is a glTF uv; OBJ ``vt`` = (u, 1 − v). Base colour is sRGB-encoded 8-bit; normal, metallic-roughness and
specular textures are linear. Roughness is perceptual (α = r², as ggx_uv); ggx_uv's ``F0 = 0.08·specular`` is written
as ``KHR_materials_specular`` with ``specularColorFactor`` 2 (its F0 = 0.04 · colour · specular).
"""

from __future__ import annotations

import json
import shutil
import subprocess
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import FailureError, UsageError
from .mesh import vertex_normals

FORMATS = ("glb", "gltf", "obj")
#: the Khronos glTF validator 2.0.0-dev.3.10 from npm, vendored with its licence (Apache-2.0)
VALIDATOR = Path(__file__).resolve().parent / "vendor" / "gltf-validator"


@dataclass
class ExportMesh:
    """A triangle mesh as written: every vertex carries its own uv (seams are split)."""

    positions: np.ndarray  #: (V, 3) in the source's frame and units
    faces: np.ndarray  #: (F, 3) int
    uvs: np.ndarray | None = None  #: (V, 2) glTF/Mitsuba uv (v down)
    colours: np.ndarray | None = None  #: (V, 3) linear RGB → COLOR_0
    #: 4×4: source frame → glTF (+Y up, metres): rotation × ``metres_per_unit``, applied on writing
    to_gltf: np.ndarray = field(default_factory=lambda: np.eye(4))
    #: the tangents' w: −1 where the winding was turned round (:func:`outward`) and the normal map's frame kept
    tangent_sign: float = 1.0

    def gltf_positions(self) -> np.ndarray:
        p = np.c_[self.positions, np.ones(len(self.positions))] @ self.to_gltf.T
        return p[:, :3].astype(np.float32)

    def gltf_normals(self) -> np.ndarray:
        r = self.to_gltf[:3, :3]
        return _unit(vertex_normals(self.positions, self.faces) @ r.T).astype(np.float32)

    def gltf_tangents(self) -> np.ndarray:
        """(V, 4) ∂p/∂u orthogonalised against the normal, w = :attr:`tangent_sign`: the bitangent is N × T · w, the
        frame ggx_uv's tangent-space normal maps are expressed in (Gram–Schmidt,
        :func:`mi_plugins.shading.frame_from_normal_tangent`)."""
        v, f, uv = self.gltf_positions().astype(np.float64), self.faces, self.uvs
        e1, e2 = v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]
        d1, d2 = uv[f[:, 1]] - uv[f[:, 0]], uv[f[:, 2]] - uv[f[:, 0]]
        det = d1[:, 0] * d2[:, 1] - d2[:, 0] * d1[:, 1]
        det = np.where(np.abs(det) < 1e-20, 1e-20, det)
        dpdu = (e1 * d2[:, 1:2] - e2 * d1[:, 1:2]) / det[:, None]
        t = np.zeros_like(v)
        for k in range(3):
            np.add.at(t, f[:, k], dpdu)
        n = self.gltf_normals().astype(np.float64)
        t = t - n * (t * n).sum(1, keepdims=True)
        bad = np.linalg.norm(t, axis=1) < 1e-12
        t[bad] = np.cross(n[bad], [0.0, 0.0, 1.0]) + np.cross(n[bad], [1.0, 0.0, 0.0]) * 1e-3
        return np.c_[_unit(t), np.full(len(t), self.tangent_sign)].astype(np.float32)


@dataclass
class ExportMaterial:
    """glTF metallic-roughness material; maps are (H, W, C) float arrays in their own units."""

    name: str = "material"
    base_colour: np.ndarray | None = None  #: (H, W, 3) linear RGB (written sRGB-encoded)
    base_colour_factor: tuple = (1.0, 1.0, 1.0, 1.0)
    normal: np.ndarray | None = None  #: (H, W, 3) unit tangent-space normals (z out)
    roughness: np.ndarray | None = None  #: (H, W) perceptual roughness
    metallic: np.ndarray | None = None  #: (H, W)
    roughness_factor: float = 1.0
    metallic_factor: float = 0.0
    specular: np.ndarray | None = None  #: (H, W) ggx_uv's specular level (F0 = 0.08·specular)
    specular_factor: float | None = None  #: a constant ggx_uv specular level where there is no map
    extra_maps: dict = field(default_factory=dict)  #: name → (H, W) linear maps written beside (e.g. displacement)
    double_sided: bool = False


def _unit(x: np.ndarray) -> np.ndarray:
    return x / np.maximum(np.linalg.norm(x, axis=-1, keepdims=True), 1e-12)


def outward(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, bool]:
    """The faces wound so that the normals point away from the centroid on average (a scan wound inside out shows its
    inside in a viewer that culls back faces), and whether they were turned round."""
    n = vertex_normals(v, f)
    inward = float(np.mean(np.sum(n * (v - v.mean(0)), axis=1))) < 0
    return (f[:, ::-1].copy(), True) if inward else (f, False)


def rotation_to_y_up(up: np.ndarray) -> np.ndarray:
    """The rotation (3×3) that takes the unit vector ``up`` to +Y (the shortest one; Rodrigues)."""
    a = _unit(np.asarray(up, np.float64))
    b = np.array([0.0, 1.0, 0.0])
    v, c = np.cross(a, b), float(a @ b)
    if c < -1 + 1e-9:
        return np.diag([1.0, -1.0, -1.0])
    k = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + k + k @ k / (1 + c)


def similarity(rotation: np.ndarray, scale: float, centre: np.ndarray | None = None) -> np.ndarray:
    """4×4: translate ``centre`` to the origin, rotate, scale."""
    m = np.eye(4)
    m[:3, :3] = scale * np.asarray(rotation, np.float64)
    if centre is not None:
        m[:3, 3] = -m[:3, :3] @ np.asarray(centre, np.float64)
    return m


# -- UV atlas and texel maps -------------------------------------------------------------------------------------------

@dataclass
class Atlas:
    """A mesh split along its UV seams: ``vertex_of`` maps each new vertex to the source vertex it copies."""

    uvs: np.ndarray  #: (V', 2) glTF/Mitsuba uv
    faces: np.ndarray  #: (F, 3) into the new vertices, same triangle order as the source
    vertex_of: np.ndarray  #: (V',) source vertex index
    width: int
    height: int


def unwrap(v: np.ndarray, f: np.ndarray, resolution: int = 1024, padding: int = 4) -> Atlas:
    """xatlas charts packed into one ``resolution``² texture with about ``padding`` texels between charts (xatlas
    is deterministic for a given mesh)."""
    import xatlas

    if len(f) == 0:
        raise UsageError("the mesh has no triangles to unwrap")
    atlas = xatlas.Atlas()
    atlas.add_mesh(np.ascontiguousarray(v, np.float32), np.ascontiguousarray(f, np.uint32))
    po = xatlas.PackOptions()
    po.resolution, po.padding, po.bilinear = int(resolution), int(padding), True
    atlas.generate(xatlas.ChartOptions(), po)
    vmap, idx, uv = atlas[0]
    # one square texture of ``resolution``²: the packed rectangle's longer side spans it (a power of two when asked)
    wh = np.array([atlas.width, atlas.height], np.float64)
    uv = np.asarray(uv, np.float64) * wh / wh.max()
    return Atlas(uvs=uv, faces=np.asarray(idx, np.int64), vertex_of=np.asarray(vmap, np.int64),
                 width=int(resolution), height=int(resolution))


def split_uv_mesh(faces: np.ndarray, face_uvs: np.ndarray, uvs_obj: np.ndarray) -> tuple[np.ndarray, np.ndarray,
                                                                                            np.ndarray]:
    """An OBJ's separate position and uv indices as one index per (position, uv) pair: (faces', uv', vertex_of)
    with uv' in glTF/Mitsuba convention (v down)."""
    pairs = np.stack([faces.ravel(), face_uvs.ravel()], 1)
    uniq, inv = np.unique(pairs, axis=0, return_inverse=True)
    uv = np.asarray(uvs_obj, np.float64)[uniq[:, 1]]
    return inv.reshape(-1, 3), np.c_[uv[:, 0], 1.0 - uv[:, 1]], uniq[:, 0]


def mitsuba_mesh(v: np.ndarray, f: np.ndarray, uvs: np.ndarray, normals: bool = False,
                 attributes: dict[str, np.ndarray] | None = None):
    """An in-memory ``mi.Mesh`` with per-vertex uv (and area-weighted vertex normals, and ``vertex_NAME``
    attributes of (V, C) arrays, C ∈ {1, 3})."""
    import mi_plugins  # noqa: F401  (the variant)
    import mitsuba as mi

    mesh = mi.Mesh("export", len(v), len(f), has_vertex_normals=normals, has_vertex_texcoords=True)
    p = mi.traverse(mesh)
    p["vertex_positions"] = mi.Float(np.ascontiguousarray(v, np.float32).ravel())
    p["faces"] = mi.UInt32(np.ascontiguousarray(f, np.uint32).ravel())
    if normals:
        p["vertex_normals"] = mi.Float(vertex_normals(v, f).astype(np.float32).ravel())
    p["vertex_texcoords"] = mi.Float(np.ascontiguousarray(uvs, np.float32).ravel())
    p.update()
    for name, a in (attributes or {}).items():
        a = np.asarray(a, np.float32).reshape(len(v), -1)
        mesh.add_attribute(f"vertex_{name}", a.shape[1], mi.Float(a.ravel()))
    return mesh


@dataclass
class TexelSurface:
    """The surface at every texel centre (row 0 at uv.y ≈ 0): where it is, which way it faces, what it interpolates."""

    mask: np.ndarray  #: (H, W) bool, a chart covers the texel centre
    position: np.ndarray  #: (N, 3) of the covered texels, row-major
    normal: np.ndarray  #: (N, 3) interpolated vertex normal
    attributes: dict  #: name → (N, C) interpolated per-vertex attributes


def texel_surface(v: np.ndarray, f: np.ndarray, uvs: np.ndarray, width: int, height: int,
                  attributes: dict[str, np.ndarray] | None = None) -> TexelSurface:
    """Evaluate the mesh (vertices with their own uv) at every texel centre through Mitsuba's
    ``Mesh.eval_parameterization`` (the surface the renderer sees at that uv), and its per-vertex ``attributes``
    (name → (V, C), C ∈ {1, 3}) barycentrically there."""
    import mi_plugins  # noqa: F401  (the variant)
    import mitsuba as mi

    mesh = mitsuba_mesh(v, f, uvs, normals=True, attributes=attributes)
    j, i = np.meshgrid((np.arange(width) + 0.5) / width, (np.arange(height) + 0.5) / height)
    si = mesh.eval_parameterization(mi.Point2f(j.ravel().astype(np.float32), i.ravel().astype(np.float32)))
    valid = np.array(si.is_valid())
    if not valid.any():
        raise FailureError("no texel is covered by the UV layout (degenerate UVs?)")
    out = {}
    for name, a in (attributes or {}).items():
        c = np.asarray(a).reshape(len(v), -1).shape[1]
        ev = mesh.eval_attribute_1 if c == 1 else mesh.eval_attribute_3
        # only the covered lanes: an uncovered one holds no triangle to interpolate from
        out[name] = np.array(ev(f"vertex_{name}", si, si.is_valid())).reshape(c, -1).T[valid]
    return TexelSurface(mask=valid.reshape(height, width), position=np.array(si.p).T[valid],
                        normal=np.array(si.sh_frame.n).T[valid], attributes=out)


def fill_texels(values: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(H, W, C) map with the texels outside ``mask`` set to the nearest covered texel's value (charts bleed into
    their padding, so that filtering and mipmaps do not pull in the background)."""
    from scipy.ndimage import distance_transform_edt

    if mask.all():
        return values
    idx = distance_transform_edt(~mask, return_distances=False, return_indices=True)
    return values[idx[0], idx[1]]


def scatter(mask: np.ndarray, values: np.ndarray) -> np.ndarray:
    """(H, W, C) map holding ``values`` (N, C) at the covered texels, filled outward (:func:`fill_texels`)."""
    out = np.zeros((*mask.shape, values.shape[1]), np.float32)
    out[mask] = values
    return fill_texels(out, mask)


# -- writing -----------------------------------------------------------------------------------------------------------

def _png_bytes(img: np.ndarray, srgb: bool) -> bytes:
    import io

    from PIL import Image

    from .imageio import to_uint8_srgb

    a = np.asarray(img, np.float32)
    a8 = to_uint8_srgb(a) if srgb else np.round(np.clip(a, 0, 1) * 255).astype(np.uint8)
    buf = io.BytesIO()
    Image.fromarray(a8).save(buf, format="PNG")
    return buf.getvalue()


def material_images(m: ExportMaterial) -> dict[str, bytes]:
    """The material's textures as PNG bytes by slot (base colour sRGB-encoded, the rest linear)."""
    out = {}
    if m.base_colour is not None:
        out["base_colour"] = _png_bytes(m.base_colour[..., :3], srgb=True)
    if m.normal is not None:
        out["normal"] = _png_bytes(_unit(np.asarray(m.normal, np.float64)) * 0.5 + 0.5, srgb=False)
    if m.roughness is not None or m.metallic is not None:
        ref = m.roughness if m.roughness is not None else m.metallic
        r = np.ones(ref.shape[:2]) if m.roughness is None else np.asarray(m.roughness).reshape(ref.shape[:2])
        k = np.zeros(ref.shape[:2]) if m.metallic is None else np.asarray(m.metallic).reshape(ref.shape[:2])
        # glTF: roughness in G, metalness in B (R: occlusion when packed; 1 here)
        out["metallic_roughness"] = _png_bytes(np.stack([np.ones_like(r), r, k], -1), srgb=False)
    if m.specular is not None:
        s = np.asarray(m.specular).reshape(m.specular.shape[:2])
        out["specular"] = _png_bytes(np.stack([s, s, s, s], -1), srgb=False)  # the spec reads A
    return out


def build_gltf(mesh: ExportMesh, material: ExportMaterial, images: dict[str, bytes],
               embed_images: bool, image_uris: dict[str, str] | None = None):
    """A ``pygltflib.GLTF2`` (one mesh, one node, one material) and its binary buffer."""
    import pygltflib as g

    blob = bytearray()
    views: list = []
    accessors: list = []

    def add_view(data: bytes, target: int | None) -> int:
        while len(blob) % 4:
            blob.append(0)
        views.append(g.BufferView(buffer=0, byteOffset=len(blob), byteLength=len(data), target=target))
        blob.extend(data)
        return len(views) - 1

    def add_accessor(a: np.ndarray, kind: str, target: int | None, bounds: bool = False) -> int:
        ctype = g.UNSIGNED_INT if a.dtype == np.uint32 else g.FLOAT
        view = add_view(np.ascontiguousarray(a).tobytes(), target)
        acc = g.Accessor(bufferView=view, componentType=ctype, count=len(a), type=kind)
        if bounds:
            acc.min, acc.max = a.min(0).tolist(), a.max(0).tolist()
        accessors.append(acc)
        return len(accessors) - 1

    pos = mesh.gltf_positions()
    attrs = g.Attributes(POSITION=add_accessor(pos, g.VEC3, g.ARRAY_BUFFER, bounds=True),
                         NORMAL=add_accessor(mesh.gltf_normals(), g.VEC3, g.ARRAY_BUFFER))
    if mesh.uvs is not None:
        attrs.TEXCOORD_0 = add_accessor(np.asarray(mesh.uvs, np.float32), g.VEC2, g.ARRAY_BUFFER)
        if material.normal is not None:
            attrs.TANGENT = add_accessor(mesh.gltf_tangents(), g.VEC4, g.ARRAY_BUFFER)
    if mesh.colours is not None:
        attrs.COLOR_0 = add_accessor(np.clip(mesh.colours, 0, 1).astype(np.float32), g.VEC3, g.ARRAY_BUFFER)
    idx = add_accessor(np.asarray(mesh.faces, np.uint32).ravel(), g.SCALAR, g.ELEMENT_ARRAY_BUFFER)

    gl_images, textures, slot_tex = [], [], {}
    for slot, data in images.items():
        if embed_images:
            gl_images.append(g.Image(bufferView=add_view(data, None), mimeType="image/png", name=slot))
        else:
            gl_images.append(g.Image(uri=(image_uris or {})[slot], name=slot))
        textures.append(g.Texture(source=len(gl_images) - 1, sampler=0))
        slot_tex[slot] = len(textures) - 1

    pbr = g.PbrMetallicRoughness(baseColorFactor=list(material.base_colour_factor),
                                 metallicFactor=float(material.metallic_factor),
                                 roughnessFactor=float(material.roughness_factor))
    if "base_colour" in slot_tex:
        pbr.baseColorTexture = g.TextureInfo(index=slot_tex["base_colour"])
    if "metallic_roughness" in slot_tex:
        pbr.metallicRoughnessTexture = g.TextureInfo(index=slot_tex["metallic_roughness"])
    mat = g.Material(name=material.name, pbrMetallicRoughness=pbr, doubleSided=material.double_sided)
    if "normal" in slot_tex:
        mat.normalTexture = g.NormalMaterialTexture(index=slot_tex["normal"])
    used_ext = []
    if "specular" in slot_tex or material.specular_factor is not None:
        spec = {"specularColorFactor": [2.0, 2.0, 2.0]}  # F0 = 0.04 · 2 · specular = ggx_uv's 0.08 · specular
        if "specular" in slot_tex:
            spec.update(specularFactor=1.0, specularTexture={"index": slot_tex["specular"]})
        else:
            spec["specularFactor"] = float(np.clip(material.specular_factor, 0, 1))
        mat.extensions = {"KHR_materials_specular": spec}
        used_ext.append("KHR_materials_specular")
    if material.extra_maps:
        mat.extras = {"maps": {k: f"{k}.png" for k in material.extra_maps}}
    while len(blob) % 4:
        blob.append(0)
    gltf = g.GLTF2(
        asset=g.Asset(version="2.0", generator="photoreal export"),
        scene=0, scenes=[g.Scene(nodes=[0])], nodes=[g.Node(mesh=0, name=material.name)],
        meshes=[g.Mesh(name=material.name, primitives=[g.Primitive(attributes=attrs, indices=idx, material=0)])],
        materials=[mat], accessors=accessors, bufferViews=views, buffers=[g.Buffer(byteLength=len(blob))],
        images=gl_images, textures=textures,
        samplers=[g.Sampler(magFilter=g.LINEAR, minFilter=g.LINEAR_MIPMAP_LINEAR, wrapS=g.REPEAT, wrapT=g.REPEAT)]
        if textures else [],
        extensionsUsed=used_ext)
    return gltf, bytes(blob)


def write_model(folder: Path, stem: str, fmt: str, mesh: ExportMesh, material: ExportMaterial) -> list[Path]:
    """Write ``folder/stem.{glb,gltf,obj}`` and the files it refers to; returns every file written."""
    from .imageio import write_png

    if fmt not in FORMATS:
        raise UsageError(f"--format {fmt!r}: one of {', '.join(FORMATS)}")
    folder.mkdir(parents=True, exist_ok=True)
    images = material_images(material)
    written = []
    for k, m in material.extra_maps.items():
        written.append(write_png(folder / f"{k}.png", np.asarray(m, np.float32).reshape(m.shape[0], m.shape[1], -1)
                                 [..., :1].repeat(3, -1), linear=False))
    if fmt == "glb":
        gltf, blob = build_gltf(mesh, material, images, embed_images=True)
        gltf.set_binary_blob(blob)
        path = folder / f"{stem}.glb"
        gltf.save_binary(str(path))
        return [path, *written]
    uris = {slot: f"{stem}_{slot}.png" for slot in images}
    for slot, data in images.items():
        (folder / uris[slot]).write_bytes(data)
        written.append(folder / uris[slot])
    if fmt == "gltf":
        gltf, blob = build_gltf(mesh, material, images, embed_images=False, image_uris=uris)
        gltf.buffers[0].uri = f"{stem}.bin"
        (folder / f"{stem}.bin").write_bytes(blob)
        path = folder / f"{stem}.gltf"
        gltf.save_json(str(path))
        return [path, folder / f"{stem}.bin", *written]
    # OBJ + MTL: positions in glTF's frame (+Y up, metres) as Blender's importer expects; vt = (u, 1 − v)
    p, n = mesh.gltf_positions(), mesh.gltf_normals()
    lines = [f"# photoreal export: +Y up, metres\nmtllib {stem}.mtl\no {material.name}"]
    col = mesh.colours
    lines += [f"v {a:.7g} {b:.7g} {c:.7g}" + ("" if col is None else " {:.5f} {:.5f} {:.5f}".format(*np.clip(col[i], 0, 1)))
              for i, (a, b, c) in enumerate(p)]
    lines += [f"vn {a:.6f} {b:.6f} {c:.6f}" for a, b, c in n]
    if mesh.uvs is not None:
        lines += [f"vt {u:.7f} {1.0 - w:.7f}" for u, w in mesh.uvs]
    lines.append(f"usemtl {material.name}")
    fmt_v = "{0}/{0}/{0}" if mesh.uvs is not None else "{0}//{0}"
    lines += ["f " + " ".join(fmt_v.format(int(i) + 1) for i in tri) for tri in mesh.faces]
    mtl = [f"newmtl {material.name}", "Kd 1 1 1" if material.base_colour is not None else
           "Kd {:.5f} {:.5f} {:.5f}".format(*material.base_colour_factor[:3]), "Ks 0 0 0", "illum 1",
           f"Pr {material.roughness_factor:.4f}", f"Pm {material.metallic_factor:.4f}"]
    if "base_colour" in uris:
        mtl.append(f"map_Kd {uris['base_colour']}")
    if "normal" in uris:
        mtl.append(f"norm {uris['normal']}")
    if "metallic_roughness" in uris:  # the PBR extension of MTL reads one channel per map: both from the packed file
        mtl += [f"map_Pr -imfchan g {uris['metallic_roughness']}", f"map_Pm -imfchan b {uris['metallic_roughness']}"]
    (folder / f"{stem}.mtl").write_text("\n".join(mtl) + "\n")
    path = folder / f"{stem}.obj"
    path.write_text("\n".join(lines) + "\n")
    return [path, folder / f"{stem}.mtl", *written]


# -- checking ----------------------------------------------------------------------------------------------------------

def validate_gltf(path: str | Path, timeout: float = 120.0) -> dict:
    """The Khronos glTF validator's report of a .glb/.gltf file (``issues.numErrors`` …), run under node; a
    :class:`FailureError` naming what is missing where node is not installed."""
    node = shutil.which("node")
    if node is None:
        raise FailureError("the glTF validator needs node (Debian: apt install nodejs); not on PATH")
    script = VALIDATOR / "validate.js"
    r = subprocess.run([node, str(script), str(path)], capture_output=True, text=True, timeout=timeout)
    if r.returncode != 0:
        raise FailureError(f"{path}: the glTF validator failed: {r.stderr.strip().splitlines()[-1:]}")
    return json.loads(r.stdout)


@dataclass
class Reimport:
    """What ``trimesh`` reads back of an exported file."""

    vertices: np.ndarray  #: (V, 3) as stored (glTF frame)
    faces: np.ndarray
    uvs: np.ndarray | None  #: glTF convention (v down)
    colours: np.ndarray | None  #: (V, 3) linear, from COLOR_0 / OBJ vertex colours
    base_colour: np.ndarray | None  #: (H, W, 3) linear


def reimport(path: str | Path) -> Reimport:
    """Load an exported model with trimesh (its own glTF/OBJ readers) as one mesh."""
    import trimesh

    from .imageio import srgb_to_linear

    scene = trimesh.load(str(path), force="scene", process=False)
    geoms = list(scene.geometry.values())
    if len(geoms) != 1:
        raise FailureError(f"{path}: expected one mesh, trimesh read {len(geoms)}")
    m = geoms[0]
    vis = m.visual
    uvs = base = cols = None
    if getattr(vis, "uv", None) is not None:
        uvs = np.asarray(vis.uv, np.float64).copy()
        uvs[:, 1] = 1.0 - uvs[:, 1]  # trimesh keeps OBJ's v up for both formats
        mat = vis.material
        img = getattr(mat, "baseColorTexture", None) or getattr(mat, "image", None)
        if img is not None:
            base = srgb_to_linear(np.asarray(img.convert("RGB"), np.float32) / 255.0)
    vc = getattr(vis, "vertex_attributes", {}).get("color") if hasattr(vis, "vertex_attributes") else None
    if vc is not None:
        cols = np.asarray(vc, np.float64)[:, :3]
        cols = cols / 255.0 if cols.max() > 1.0 else cols
    return Reimport(np.asarray(m.vertices, np.float64), np.asarray(m.faces), uvs, cols, base)


@dataclass
class ExportSettings:
    """``photoreal export``: what every kind of result is written with."""

    format: str = "glb"  #: glb (one file), gltf (+ .bin + PNGs) or obj (+ .mtl + PNGs)
    #: morph results: the base-colour texture baked from the photos through the fitted cameras ('photos': a capture's
    #: run only) or from the vertex colours ('colours'); 'auto': photos where the run's capture is found and the run
    #: ended unlit (the better on held-out photos then: docs/results/export.md), else colours
    texture: str = "auto"
    texture_size: int = 1024  #: side of the baked texture (morph results)
    padding: int = 4  #: texels between UV charts (morph results)
    eval_width: int = 256  #: width of the held-out renders the exported textures are scored with
    spp: int = 16  #: samples per pixel of those renders and of previews
    seed: int = 0

    def __post_init__(self):
        from . import validate

        if self.format not in FORMATS:
            raise UsageError(f"format {self.format!r}: one of {', '.join(FORMATS)}")
        if self.texture not in ("auto", "photos", "colours"):
            raise UsageError(f"texture {self.texture!r}: auto, photos or colours")
        validate.integer("texture_size", self.texture_size, 16, 8192)
        validate.integer("padding", self.padding, 0, 64)
        validate.integer("eval_width", self.eval_width, 16, 4096)
        validate.integer("spp", self.spp, 1)
        validate.seed("seed", self.seed)


def _unlit_render(v: np.ndarray, f: np.ndarray, uv: np.ndarray, texture: np.ndarray, res: int, spp: int) -> np.ndarray:
    """The textured mesh (two-sided diffuse, its base colour) under a white sky, seen orthographically from the front
    (along −Z) and from above (along −Y) of its bounding box, side by side: one of them sees a flat tile or a face."""
    import tempfile

    import mi_plugins  # noqa: F401  (the variant)
    import mitsuba as mi

    lo, hi = v.min(0), v.max(0)
    c, half = (lo + hi) / 2, 0.55 * float(max(np.ptp(v, axis=0).max(), 1e-9))
    m = mitsuba_mesh(v, f, uv)
    views = []
    with tempfile.TemporaryDirectory(prefix="photoreal-check-") as work:
        ply = Path(work) / "m.ply"
        m.write_ply(str(ply))
        for axis, up in ((2, [0, 1, 0]), (1, [0, 0, -1])):
            eye = c.copy()
            eye[axis] = hi[axis] + 10 * half
            scene = mi.load_dict({
                "type": "scene", "integrator": {"type": "path", "max_depth": 2},
                "env": {"type": "constant", "radiance": 1.0},
                "mesh": {"type": "ply", "filename": str(ply), "face_normals": True,
                         "bsdf": {"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": {
                             "type": "bitmap", "bitmap": mi.Bitmap(np.ascontiguousarray(texture, np.float32)),
                             "raw": True, "filter_type": "bilinear", "wrap_mode": "clamp"}}}},
                "sensor": {"type": "orthographic",
                           "to_world": mi.ScalarTransform4f().look_at(origin=eye.tolist(), target=c.tolist(), up=up)
                           @ mi.ScalarTransform4f().scale([half, half, 1]),
                           "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"}},
                           "sampler": {"type": "independent"}}})
            views.append(np.array(mi.render(scene, spp=spp, seed=0))[..., :3])
            del scene
    return np.concatenate(views, 1)


#: a render of the re-imported model against the same render of what was exported: at least this PSNR (the 8-bit sRGB
#: base colour is the only loss: 1/255 steps in sRGB)
REIMPORT_PSNR_DB = 40.0


def reimport_check(path: str | Path, mesh: ExportMesh, material: ExportMaterial, res: int = 192, spp: int = 16) -> dict:
    """Read the file back (trimesh) and compare with what was written: vertex and triangle counts, UVs in [0, 1], the
    base colour's size, and an unlit render of each (along −Z and −Y of the glTF frame) — PSNR ≥ :data:`REIMPORT_PSNR_DB`."""
    from .metrics import masked_psnr

    r = reimport(path)
    out = {"vertices": int(len(r.vertices)), "vertices_written": int(len(mesh.positions)),
           "triangles": int(len(r.faces)), "triangles_written": int(len(mesh.faces)),
           "uv_in_range": None if r.uvs is None else bool(((r.uvs >= 0) & (r.uvs <= 1)).all()),
           "texture_size": None if r.base_colour is None else list(r.base_colour.shape[1::-1]),
           "position_error": float(np.abs(r.vertices - mesh.gltf_positions()).max())
           if len(r.vertices) == len(mesh.positions) else None}
    if r.base_colour is not None and r.uvs is not None and material.base_colour is not None:
        a = _unlit_render(mesh.gltf_positions(), mesh.faces, mesh.uvs, material.base_colour, res, spp)
        b = _unlit_render(r.vertices, r.faces, r.uvs, r.base_colour, res, spp)
        covered = (a.max(-1) < 0.999) | (b.max(-1) < 0.999)  # the white sky would only add agreeing pixels
        out["render_psnr"] = float(masked_psnr(b, a, covered))
        out["render_covered"] = float(covered.mean())
        out["render_psnr_min"] = REIMPORT_PSNR_DB
    return out
