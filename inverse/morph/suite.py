"""The generalisation suite of the morph: meshes of different kinds that the defaults were not tuned on.

=============  =====================================================  ============================================
name           kind                                                   source
=============  =====================================================  ============================================
``bunny``      scanned, organic, closed                               pymeshlab's wheel (Stanford bunny, 28k v.)
``bone``       scanned, organic, small and elongated                  pymeshlab's wheel (``bone.ply``)
``josie``      scanned head, an open sheet (a face-and-skull scan)    Cyberware scan (inventor-data, LGPL-2+)
``cow``        artist-made organic with thin legs, horns and tail     pymeshlab's wheel (``cow.obj``)
``airplane``   CAD / man-made with thin wings and fins                pymeshlab's wheel (``airplane.obj``)
``table``      generated CAD: a slab on four thin legs                :func:`table_mesh`
``pedestal``   generated: a vase standing on a large flat base        :func:`pedestal_mesh`
=============  =====================================================  ============================================

The village and the armadillo (what the defaults were tuned on) are not part of it.

Four more meshes were added after the defaults were last changed, to check them on meshes nothing was decided
on (``UNSEEN``; ``photoreal bench morph --parts suite --suite paul face000 bracket mpface``; ``mpface`` on
2026-11-29, after every default of that day):

=============  =====================================================  ============================================
``paul``       scanned head, an open sheet (josie's sibling scan)     Cyberware scan (inventor-data, LGPL-2+)
``face000``    a real single-view range scan of a head: ragged        pymeshlab's wheel
               border, holes, 86k vertices                            (``rangemaps/face000.ply``)
``bracket``    generated machined part: an L bracket with a hole      :func:`bracket_mesh`
``mpface``     an artist-made low-poly face: an open sheet of 468     MediaPipe's canonical face model
               vertices, no skull                                     (``scenes/assets/face``, Apache-2.0)
=============  =====================================================  ============================================
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from foundation.assets import FACE, pymeshlab_sample
from foundation.errors import UsageError
from foundation.mesh import write_ply

SUITE = ("bunny", "bone", "josie", "cow", "airplane", "table", "pedestal")
UNSEEN = ("paul", "face000", "bracket", "mpface")
KINDS = {"bunny": "scan, organic", "bone": "scan, organic, elongated", "josie": "scan, head, open sheet",
         "cow": "organic, thin legs", "airplane": "CAD, thin wings", "table": "CAD, thin legs (generated)",
         "pedestal": "large flat base (generated)", "paul": "unseen: scan, head, open sheet",
         "face000": "unseen: range scan, ragged border", "bracket": "unseen: machined part (generated)",
         "mpface": "unseen: low-poly face, open sheet"}


def _orient(v: np.ndarray, f: np.ndarray, outward: np.ndarray) -> np.ndarray:
    """Flip the triangles whose normal points against ``outward`` (one direction per triangle)."""
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    bad = np.sum(n * outward, axis=1) < 0
    f = f.copy()
    f[bad] = f[bad][:, [0, 2, 1]]
    return f


def box_mesh(lo, hi) -> tuple[np.ndarray, np.ndarray]:
    """An axis-aligned box, 12 outward triangles; each face has its own 4 vertices, so that the renderer's
    smooth vertex normals stay flat on it (shared corners would bend every face's shading normal)."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    c = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    v = c[np.array(quads).ravel()]
    f = np.array([t for q in range(6) for t in ((4 * q, 4 * q + 1, 4 * q + 2), (4 * q, 4 * q + 2, 4 * q + 3))])
    return v, _orient(v, f, v[f].mean(1) - 0.5 * (lo + hi))


def _merge(parts) -> tuple[np.ndarray, np.ndarray]:
    vs, fs, off = [], [], 0
    for v, f in parts:
        vs.append(v)
        fs.append(f + off)
        off += len(v)
    return np.concatenate(vs), np.concatenate(fs)


def table_mesh() -> tuple[np.ndarray, np.ndarray]:
    """A table: 1.2 × 0.06 × 0.8 top on four 0.05-wide legs, 0.7 high (thin parts: legs 1/30 of its size)."""
    parts = [box_mesh((-0.6, 0.7, -0.4), (0.6, 0.76, 0.4))]
    for x in (-0.52, 0.47):
        for z in (-0.32, 0.27):
            parts.append(box_mesh((x, 0.0, z), (x + 0.05, 0.7, z + 0.05)))
    return _merge(parts)


def pedestal_mesh(n_theta: int = 64, n_y: int = 48) -> tuple[np.ndarray, np.ndarray]:
    """A vase (surface of revolution with a waist and a lip, closed by caps) on a 1.6 × 0.1 × 1.6 slab."""
    y = np.linspace(0.1, 1.0, n_y)
    t = (y - 0.1) / 0.9
    r = 0.22 + 0.12 * np.sin(np.pi * t * 1.5) ** 2 - 0.08 * t + 0.05 * np.exp(-((t - 0.95) / 0.05) ** 2)
    th = np.linspace(0, 2 * np.pi, n_theta, endpoint=False)
    v = np.stack([np.outer(r, np.cos(th)), np.repeat(y[:, None], n_theta, 1), np.outer(r, np.sin(th))], -1).reshape(-1, 3)
    i = np.arange(n_y - 1)[:, None] * n_theta
    j = np.arange(n_theta)[None, :]
    a, b = i + j, i + (j + 1) % n_theta
    c, d = a + n_theta, b + n_theta
    side = np.concatenate([np.stack([a, b, d], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)])
    # Caps with their own rim vertices (a sharp rim: flat shading on the caps).
    nv = len(v)
    v = np.concatenate([v, v[:n_theta], v[-n_theta:], [[0, y[0], 0], [0, y[-1], 0]]])
    ring0, ring1 = nv + np.arange(n_theta), nv + n_theta + np.arange(n_theta)
    bottom, top = nv + 2 * n_theta, nv + 2 * n_theta + 1
    caps = np.concatenate([np.stack([np.full(n_theta, bottom), ring0, np.roll(ring0, -1)], -1),
                           np.stack([np.full(n_theta, top), ring1, np.roll(ring1, -1)], -1)])
    f = np.concatenate([side, caps])
    cen = v[f].mean(1)
    outward = np.where(np.arange(len(f))[:, None] < len(side), cen * [1, 0, 1],
                       np.where(np.arange(len(f))[:, None] < len(side) + n_theta, [[0, -1, 0]], [[0, 1, 0]]))
    vase = (v, _orient(v, f, outward))
    return _merge([box_mesh((-0.8, 0.0, -0.8), (0.8, 0.1, 0.8)), vase])


def bracket_mesh(voxel: float = 0.015) -> tuple[np.ndarray, np.ndarray]:
    """An L bracket: a 1.6 × 0.2 × 0.8 base plate and a 0.3 × 1.0 × 0.8 upright at one end, a hole of radius 0.15
    through the upright at height 0.6 (volume 0.4508); marching cubes of its signed-distance bound (pymeshlab's
    ``create_implicit_surface``, ``voxel`` apart), so flat faces, sharp edges and a cylinder meet."""
    import pymeshlab

    base = "max(max(abs(x)-0.8, abs(z)-0.4), abs(y)-0.1)"
    upright = "max(max(abs(x+0.65)-0.15, abs(z)-0.4), abs(y-0.5)-0.5)"
    hole = "(0.15 - sqrt((y-0.6)*(y-0.6)+z*z))"
    ms = pymeshlab.MeshSet()
    ms.create_implicit_surface(expr=f"max(min({base}, {upright}), {hole})", voxelsize=voxel,
                               minx=-1.0, miny=-0.3, minz=-0.6, maxx=1.0, maxy=1.2, maxz=0.6)
    m = ms.current_mesh()
    return np.asarray(m.vertex_matrix(), np.float64), np.asarray(m.face_matrix(), np.int64)


GENERATED = {"table": table_mesh, "pedestal": pedestal_mesh, "bracket": bracket_mesh}


def suite_mesh(name: str, folder: str | Path) -> Path:
    """The mesh file of suite case ``name`` (generated ones are written into ``folder``)."""
    if name in GENERATED:
        v, f = GENERATED[name]()
        path = Path(folder) / f"{name}.ply"
        path.parent.mkdir(parents=True, exist_ok=True)
        write_ply(path, v, f)
        return path
    if name in ("josie", "paul"):
        return FACE / "cyberheads" / f"{name}.obj"
    if name == "mpface":
        return FACE / "canonical_face_model.obj"
    files = {"bunny": "bunny.obj", "bone": "bone.ply", "cow": "cow.obj", "airplane": "airplane.obj",
             "face000": "rangemaps/face000.ply"}
    if name not in files:
        raise UsageError(f"morph suite: unknown case {name!r} (have {', '.join(SUITE + UNSEEN)})")
    return pymeshlab_sample(files[name])
