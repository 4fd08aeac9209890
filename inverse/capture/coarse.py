"""Coarse meshes of a capture: the one a photogrammetry tool made (OBJ + MTL texture, PLY, GLB), or one made here
from sparse points (screened Poisson, as the CPU allows: no dense stereo, no Delaunay meshing; see
docs/capture.md)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from foundation.errors import UsageError

POISSON_DEPTH = 8  #: octree depth of the screened Poisson reconstruction (depth 8: the shape, holes where untextured)
#: Poisson vertices of the lowest point density dropped when the points' normals are turned by the nearest camera (the
#: surface invented where that guess flips them); points with view directions need no trim
TRIM_QUANTILE = 0.08


def load_coarse_mesh(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(vertices, triangles, linear vertex colours or None) of a tool's mesh (:func:`foundation.mesh.load_mesh_colours`:
    a texture, an OBJ's MTL or a GLB's, is sampled to vertex colours)."""
    from foundation.mesh import load_mesh_colours

    path = Path(path)
    if not path.is_file():
        raise UsageError(f"{path}: no such mesh file")
    if path.suffix.lower() not in (".obj", ".ply", ".glb", ".gltf", ".off", ".stl"):
        raise UsageError(f"{path}: mesh expected as OBJ, PLY, GLB/glTF, OFF or STL")
    return load_mesh_colours(path)


def inliers(points: np.ndarray, k: int = 8, sigmas: float = 2.0, tail: float = 0.01) -> np.ndarray:
    """Points worth a surface: statistical outliers (mean distance to their ``k`` neighbours beyond mean + ``sigmas``
    σ) and the far ``tail`` of each axis (a few background points would stretch Poisson's octree over the whole
    room, leaving the object a handful of cells) dropped."""
    from scipy.spatial import cKDTree

    d = cKDTree(points).query(points, k + 1)[0][:, 1:].mean(1)
    keep = d <= d.mean() + sigmas * d.std()
    lo, hi = np.quantile(points[keep], tail, axis=0), np.quantile(points[keep], 1 - tail, axis=0)
    pad = 0.05 * (hi - lo)
    return keep & np.all((points >= lo - pad) & (points <= hi + pad), axis=1)


def coarse_mesh_from_points(points: np.ndarray, colours: np.ndarray | None, cam_centres: np.ndarray,
                            depth: int = POISSON_DEPTH, view_dirs: np.ndarray | None = None
                            ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """A screened Poisson surface of sparse points: normals from 10 neighbours, turned toward the side each point was
    seen from (``view_dirs``, :func:`~inverse.capture.sources.model_points`), else toward the nearest camera and the
    faces of least point support trimmed; the largest piece kept; vertex colours from the nearest point.

    The side matters: on an orbit every camera is about as near as any other, so the nearest one is on the wrong side
    of a third of a skull's points, and Poisson then closes inside-out pockets that render black."""
    import pymeshlab
    from scipy.spatial import cKDTree

    pts = np.asarray(points, np.float64)
    if len(pts) < 100:
        raise UsageError(f"{len(pts)} triangulated points: too few for a mesh (at least 100)")
    keep = inliers(pts)
    if view_dirs is not None:
        view_dirs = np.asarray(view_dirs, np.float64)
        keep &= np.linalg.norm(view_dirs, axis=1) > 1e-6  # a point of an empty track has no side
    pts, colours = pts[keep], (None if colours is None else np.asarray(colours)[keep])
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=pts))
    ms.compute_normal_for_point_clouds(k=10, smoothiter=2)
    n = ms.current_mesh().vertex_normal_matrix()
    toward = view_dirs[keep] if view_dirs is not None else cam_centres[cKDTree(cam_centres).query(pts)[1]] - pts
    n = np.where((toward * n).sum(1, keepdims=True) < 0, -n, n)
    ms.clear()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=pts, v_normals_matrix=n))
    ms.generate_surface_reconstruction_screened_poisson(depth=depth, preclean=True)
    m = ms.current_mesh()
    q = m.vertex_scalar_array() if m.has_vertex_scalar() else np.zeros(0)  # Poisson's point density
    if view_dirs is None and len(q) and np.ptp(q) > 0:
        ms.compute_selection_by_condition_per_vertex(condselect=f"q < {np.quantile(q, TRIM_QUANTILE)}")
        ms.meshing_remove_selected_vertices()
    ms.meshing_remove_connected_component_by_diameter(mincomponentdiag=pymeshlab.PercentageValue(20))
    ms.meshing_remove_unreferenced_vertices()
    m = ms.current_mesh()
    v, f = m.vertex_matrix().astype(np.float64), m.face_matrix().astype(np.int64)
    if len(f) < 20:
        raise UsageError(f"the Poisson surface of {len(pts)} points has {len(f)} faces: no usable mesh")
    c = None
    if colours is not None:
        c = np.asarray(colours, np.float32)[cKDTree(pts).query(v)[1]]
    return v, f, c


def _axes_centre(cams) -> np.ndarray:
    """The point nearest to every camera's optical axis (least squares): where an orbit looks."""
    a, b = np.zeros((3, 3)), np.zeros(3)
    for c in cams:
        m = c.matrix
        d = m[:3, 2] / np.linalg.norm(m[:3, 2])
        p = np.eye(3) - np.outer(d, d)
        a += p
        b += p @ m[:3, 3]
    return np.linalg.lstsq(a, b, rcond=None)[0]


def visual_hull(cams, masks: dict, res: int = 96, bounds: tuple[np.ndarray, np.ndarray] | None = None):
    """(vertices, triangles) of the visual hull of ``masks`` (name → (H, W) bool) seen by capture cameras: the voxels
    of a ``res``³ grid that project into the object's mask in every photo that sees them, meshed by marching cubes.
    Closed by construction; it cannot see concavities. ``bounds`` default: a cube about the point the cameras look
    at, as wide as 0.8 × their median distance to it."""
    from scipy.ndimage import gaussian_filter
    from skimage.measure import marching_cubes

    cams = [c for c in cams if c.name in masks]
    if len(cams) < 2:
        raise UsageError(f"a visual hull needs masks of at least 2 photos, got {len(cams)}")
    if bounds is None:
        centre = _axes_centre(cams)
        half = 0.4 * float(np.median([np.linalg.norm(c.centre - centre) for c in cams]))
        bounds = (centre - half, centre + half)
    lo, hi = (np.asarray(b, np.float64) for b in bounds)
    axes = [np.linspace(lo[k], hi[k], res) for k in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    inside = np.ones(len(grid), bool)
    for c in cams:
        m = np.asarray(masks[c.name], bool)
        uv, z = c.project(grid)
        col, row = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
        seen = (z > 0) & (col >= 0) & (col < m.shape[1]) & (row >= 0) & (row < m.shape[0])
        inside[seen] &= m[row[seen], col[seen]]
    occ = gaussian_filter(inside.reshape(res, res, res).astype(np.float32), 0.7)
    if occ.max() < 0.5:
        raise UsageError("the masks' visual hull is empty (masks and cameras disagree)")
    step = (hi - lo) / (res - 1)
    v, f, _, _ = marching_cubes(np.pad(occ, 1), 0.5, spacing=tuple(step))
    return v + lo - step, f[:, ::-1].astype(np.int64)  # outward winding
