"""Meshes with UVs: OBJ loading and UV-space geometry maps (position, normal, tangent).

The UV-space shader (seed 003) needs, for every texel u, the surface point,
normal and tangent of the template mesh. These are precomputed once by
evaluating the mesh at every texel's uv (baking, not screen-space
rasterisation: nothing is seen from a camera).

Texel convention (same as Mitsuba's bitmap textures on an OBJ): texel (i, j),
row i from the top, sits at Mitsuba uv = ((j + ½)/W, (i + ½)/H), i.e. OBJ
``vt`` = (u, 1 − v_mitsuba). The tangent is ∂p/∂u (independent of the v
flip), Gram–Schmidt-orthogonalised against the normal like Mitsuba's shading
frame; ``bitangent_sign`` says whether n × t points along +∂p/∂v (Mitsuba v).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np


class MeshError(ValueError):
    """A mesh file is missing, malformed or unusable (e.g. no UVs, degenerate)."""


@dataclass
class UVMesh:
    vertices: np.ndarray  #: (V, 3) float
    faces: np.ndarray  #: (F, 3) int, vertex indices
    uvs: np.ndarray  #: (T, 2) float, OBJ convention (v up)
    face_uvs: np.ndarray  #: (F, 3) int, indices into uvs
    texture: Path | None = None  #: map_Kd of the first material, if any
    path: Path | None = None

    def vertex_normals(self) -> np.ndarray:
        """Area-weighted vertex normals."""
        v, f = self.vertices, self.faces
        fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
        vn = np.zeros_like(v)
        for k in range(3):
            np.add.at(vn, f[:, k], fn)
        norm = np.linalg.norm(vn, axis=1, keepdims=True)
        return vn / np.maximum(norm, 1e-20)


def _index(token: str, count: int, what: str, path: Path, line_no: int) -> int:
    i = int(token)
    i = i - 1 if i > 0 else count + i  # OBJ is 1-based; negative = relative to the end
    if not (0 <= i < count):
        raise MeshError(f"{path}:{line_no}: {what} index {token} out of range (have {count})")
    return i


def load_obj(path: str | Path) -> UVMesh:
    """Read a triangle/polygon OBJ with texture coordinates (polygons are fanned)."""
    path = Path(path)
    if not path.is_file():
        raise MeshError(f"{path}: no such mesh file")
    verts, uvs, faces, fuvs = [], [], [], []
    mtllib = None
    try:
        lines = path.read_text().splitlines()
    except UnicodeDecodeError as exc:
        raise MeshError(f"{path}: not a text OBJ file") from exc
    for n, line in enumerate(lines, 1):
        parts = line.split()
        if not parts or parts[0].startswith("#"):
            continue
        try:
            if parts[0] == "v":
                verts.append([float(x) for x in parts[1:4]])
            elif parts[0] == "vt":
                uvs.append([float(x) for x in parts[1:3]])
            elif parts[0] == "f":
                corners = [c.split("/") for c in parts[1:]]
                if len(corners) < 3:
                    raise MeshError(f"{path}:{n}: face with fewer than 3 corners")
                if any(len(c) < 2 or c[1] == "" for c in corners):
                    raise MeshError(f"{path}:{n}: face without texture coordinates (need v/vt)")
                vi = [_index(c[0], len(verts), "vertex", path, n) for c in corners]
                ti = [_index(c[1], len(uvs), "texcoord", path, n) for c in corners]
                for k in range(1, len(corners) - 1):
                    faces.append([vi[0], vi[k], vi[k + 1]])
                    fuvs.append([ti[0], ti[k], ti[k + 1]])
            elif parts[0] == "mtllib" and mtllib is None:
                mtllib = path.parent / " ".join(parts[1:])
        except MeshError:
            raise
        except (ValueError, IndexError) as exc:
            raise MeshError(f"{path}:{n}: malformed line {line!r}") from exc
    if not faces:
        raise MeshError(f"{path}: no faces")
    v = np.asarray(verts, np.float64)
    if not np.isfinite(v).all():
        raise MeshError(f"{path}: vertex positions contain NaN/Inf")
    texture = None
    if mtllib is not None and mtllib.is_file():
        for line in mtllib.read_text().splitlines():
            p = line.split()
            if p and p[0] == "map_Kd":
                texture = mtllib.parent / " ".join(p[1:])
                break
    return UVMesh(v, np.asarray(faces, np.int64), np.asarray(uvs, np.float64), np.asarray(fuvs, np.int64),
                  texture, path)


@dataclass
class GeometryMaps:
    """UV-space geometry of a mesh at resolution (H, W); invalid texels are zero."""

    position: np.ndarray  #: (H, W, 3)
    normal: np.ndarray  #: (H, W, 3) unit shading normal (interpolated vertex normal)
    tangent: np.ndarray  #: (H, W, 3) unit, ∂p/∂u orthogonalised against the normal
    bitangent_sign: np.ndarray  #: (H, W) ±1: sign of (n × t)·∂p/∂v (Mitsuba v)
    mask: np.ndarray  #: (H, W) bool, texel covered by the UV layout
    texel_size: np.ndarray  #: (H, W, 2) world length of one texel step along u and v


def texel_uvs(h: int, w: int):
    """Mitsuba uv of every texel centre, row-major (row 0 = top of the image = uv.y ≈ 0)."""
    import mitsuba as mi

    j, i = np.meshgrid((np.arange(w) + 0.5) / w, (np.arange(h) + 0.5) / h)
    return mi.Point2f(j.ravel().astype(np.float32), i.ravel().astype(np.float32))


def bake_geometry(mesh: UVMesh, resolution: int | tuple[int, int]) -> GeometryMaps:
    """Evaluate the mesh at every texel centre through Mitsuba's own UV parameterisation.

    ``Mesh.eval_parameterization`` returns exactly the surface interaction that
    Mitsuba's renderer produces at that uv (its vertex normals, its shading
    frame), so the UV-space shader and the ``ggx_uv`` plugin see the same
    geometry.
    """
    import mitsuba as mi

    h, w = (resolution, resolution) if isinstance(resolution, int) else resolution
    if h < 2 or w < 2:
        raise ValueError(f"resolution must be >= 2, got {(h, w)}")
    if mesh.path is None:
        raise MeshError("bake_geometry needs a mesh loaded from a file")
    kind = mesh.path.suffix.lower().lstrip(".")
    if kind not in ("obj", "ply"):
        raise MeshError(f"{mesh.path}: unsupported mesh format '{kind}' (obj or ply)")
    shape = mi.load_dict({"type": kind, "filename": str(mesh.path), "face_normals": False})
    si = shape.eval_parameterization(texel_uvs(h, w))
    valid = np.array(si.is_valid())
    if not valid.any():
        raise MeshError(f"{mesh.path}: no texel is covered by the UV layout (degenerate UVs?)")

    def grab(v):
        return np.where(valid[:, None], np.array(v).T, 0.0).reshape(h, w, 3).astype(np.float32)

    n = np.array(si.sh_frame.n).T
    dp_dv = np.array(si.dp_dv).T
    sign = np.sign(np.sum(np.cross(n, np.array(si.sh_frame.s).T) * dp_dv, axis=1))
    sign[sign == 0] = 1.0
    tsize = np.stack([np.linalg.norm(np.array(si.dp_du).T, axis=1) / w,
                      np.linalg.norm(dp_dv, axis=1) / h], axis=1)
    return GeometryMaps(
        position=grab(si.p), normal=grab(si.sh_frame.n), tangent=grab(si.sh_frame.s),
        bitangent_sign=np.where(valid, sign, 0.0).reshape(h, w).astype(np.float32),
        mask=valid.reshape(h, w),
        texel_size=np.where(valid[:, None], tsize, 0.0).reshape(h, w, 2).astype(np.float32),
    )
