"""UV-space geometry maps (position, normal, tangent) of a mesh with UVs (OBJ loading: foundation.mesh).

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

import numpy as np

from foundation.errors import UsageError
from foundation.mesh import MeshError, UVMesh


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
        raise UsageError(f"resolution must be >= 2, got {(h, w)}")
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
