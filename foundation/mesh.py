"""Mesh I/O and basic mesh operations (numpy; Mitsuba only where it parses a file for us).

* OBJ with texture coordinates (:func:`load_obj`, :func:`write_obj`) for UV-space work;
* binary PLY with per-vertex float colours (:func:`write_ply`, :func:`read_ply`), the format
  Mitsuba's ``mesh_attribute`` texture reads as ``vertex_color``;
* any OBJ/PLY/OFF through pymeshlab (:func:`load_mesh_any`), refusing what pymeshlab would
  repair silently (NaN vertices) and degenerate meshes;
* normals, edge lengths, area-uniform surface samples, the graph Laplacian.

Errors are :class:`MeshError` and name the file.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import UsageError
from .files import atomic_path


class MeshError(UsageError):
    """A mesh file is missing, malformed or unusable (no UVs, NaN vertices, degenerate)."""


# -- basic operations ---------------------------------------------------------------------------------------------


def face_normals(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Unit face normals (zero-area faces give ~0)."""
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-20)


def vertex_normals(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals."""
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    vn = np.zeros_like(np.asarray(v, np.float64))
    for k in range(3):
        np.add.at(vn, f[:, k], fn)
    return vn / np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-20)


def edge_lengths(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Mean incident edge length per vertex."""
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    ln = np.linalg.norm(v[e[:, 0]] - v[e[:, 1]], axis=1)
    s = np.zeros(len(v))
    c = np.zeros(len(v))
    for k in range(2):
        np.add.at(s, e[:, k], ln)
        np.add.at(c, e[:, k], 1)
    return s / np.maximum(c, 1)


def sample_surface(v: np.ndarray, f: np.ndarray, n: int,
                   rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Area-uniform points, their face ids and barycentric weights."""
    a = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    fid = rng.choice(len(f), size=n, p=a / a.sum())
    r1, r2 = rng.random(n), rng.random(n)
    s1 = np.sqrt(r1)
    w = np.stack([1 - s1, s1 * (1 - r2), s1 * r2], axis=1)
    fi = f[fid]  # the weighted sum in einsum's order (bit-identical), without its (n, 3, 3) gather: 2× faster
    return w[:, 0:1] * v[fi[:, 0]] + w[:, 1:2] * v[fi[:, 1]] + w[:, 2:3] * v[fi[:, 2]], fid, w


def unique_edges(f: np.ndarray) -> np.ndarray:
    """The mesh's edges as (i, j) vertex pairs, i < j, each once (sorted)."""
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    return np.unique(np.sort(e, axis=1), axis=0)


def boundary_edges(f: np.ndarray) -> np.ndarray:
    """Edges that belong to one triangle only (an open mesh's border), as sorted (i, j) pairs."""
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    u, count = np.unique(e, axis=0, return_counts=True)
    return u[count == 1]


def graph_laplacian(n: int, faces: np.ndarray):
    """Combinatorial Laplacian D − A of the mesh's edge graph (binary adjacency), scipy CSR."""
    import scipy.sparse as sp

    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    e = np.concatenate([e, e[:, ::-1]])
    adj = sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n)).tocsr()
    adj.data[:] = 1.0
    deg = np.asarray(adj.sum(1)).ravel()
    return sp.diags(deg) - adj


def check_mesh(v: np.ndarray, f: np.ndarray, path: str | os.PathLike = "mesh") -> None:
    """Refuse what no later stage can use: no faces, bad indices, NaN/Inf, zero extent or zero area."""
    v, f = np.asarray(v), np.asarray(f)
    if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
        raise MeshError(f"{path}: no triangles")
    if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
        raise MeshError(f"{path}: no vertices")
    if f.min() < 0 or f.max() >= len(v):
        raise MeshError(f"{path}: face indices outside the {len(v)} vertices")
    if not np.isfinite(v).all():
        raise MeshError(f"{path}: {int((~np.isfinite(v).all(1)).sum())} vertices are NaN/Inf")
    if float(np.linalg.norm(np.ptp(v, axis=0))) <= 0:
        raise MeshError(f"{path}: degenerate mesh (all vertices at one point)")
    area = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1).sum()
    if not area > 0:
        raise MeshError(f"{path}: degenerate mesh (zero surface area)")


# -- any mesh (pymeshlab) -----------------------------------------------------------------------------------------


def _declared_vertices(path: Path) -> int | None:
    """The vertex count a file declares (PLY/OFF header, OBJ ``v`` lines); None if unknown."""
    suffix = path.suffix.lower()
    try:
        if suffix == ".obj":
            with open(path, "rb") as fh:
                return sum(1 for line in fh if line.startswith(b"v ") or line.startswith(b"v\t"))
        with open(path, "rb") as fh:
            head = fh.read(4096)
        if suffix == ".ply":
            m = re.search(rb"element\s+vertex\s+(\d+)", head)
            return int(m.group(1)) if m else None
        if suffix == ".off":
            tokens = [t for line in head.split(b"\n") if not line.lstrip().startswith(b"#") for t in line.split()]
            if tokens and tokens[0].upper().endswith(b"OFF"):
                tokens = tokens[1:] if tokens[0].upper() == b"OFF" else [tokens[0][:-3]] + tokens[1:]
            return int(tokens[0]) if tokens and tokens[0].isdigit() else None
    except (OSError, ValueError):
        return None
    return None


def load_mesh_any(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (float64) and triangles (int64) of an OBJ/PLY/OFF file (pymeshlab reads all three).

    pymeshlab drops NaN vertices (and their faces) without a word; that is refused here, as are
    meshes without faces and degenerate ones. A failed load no longer moves the working folder.
    """
    ms = _load_meshset(Path(path))  # kept alive: its current mesh is a view into it
    m = ms.current_mesh()
    v, f = m.vertex_matrix().astype(np.float64), m.face_matrix().astype(np.int64)
    check_mesh(v, f, path)
    return v, f


def _load_meshset(path: Path):
    """A pymeshlab MeshSet holding the file as one mesh (a glTF scene's meshes merged), NaN vertices refused."""
    import pymeshlab

    if not path.is_file():
        raise MeshError(f"{path}: no such mesh file")
    ms = pymeshlab.MeshSet()
    cwd = os.getcwd()
    try:
        ms.load_new_mesh(str(path))
    except Exception as exc:  # pymeshlab raises its own PyMeshLabException, several lines long
        detail = " ".join(str(exc).split())
        raise MeshError(f"{path}: cannot read mesh ({detail})") from None
    finally:
        os.chdir(cwd)  # pymeshlab changes into the file's folder and stays there when loading fails
    if ms.mesh_number() > 1:
        ms.generate_by_merging_visible_meshes()
    declared = _declared_vertices(path)
    if declared is not None and declared > ms.current_mesh().vertex_number():
        raise MeshError(f"{path}: {declared - ms.current_mesh().vertex_number()} of {declared} vertices are NaN/Inf "
                        "or unreadable (refusing to drop them silently; repair the file)")
    return ms


def load_mesh_colours(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """:func:`load_mesh_any` (also GLB/glTF, STL) with linear vertex colours: its texture (an OBJ's MTL, a glTF's)
    sampled at the vertices, else its own vertex colours, sRGB-decoded; None when it has neither."""
    from .imageio import srgb_to_linear

    path = Path(path)
    ms = _load_meshset(path)
    m = ms.current_mesh()
    colours = None
    if m.has_wedge_tex_coord() or m.has_vertex_tex_coord():
        try:
            if m.has_wedge_tex_coord() and not m.has_vertex_tex_coord():
                ms.compute_texcoord_transfer_wedge_to_vertex()
            ms.compute_color_from_texture_per_vertex()
            colours = ms.current_mesh().vertex_color_matrix()[:, :3]
        except Exception:  # pymeshlab's error for a texture it cannot read: the geometry stands without colours
            colours = None
    m = ms.current_mesh()
    if colours is None and m.has_vertex_color():
        c = m.vertex_color_matrix()[:, :3]
        colours = None if np.allclose(c, c[:1]) else c  # meshlab fills a colourless mesh with one grey
    v, f = m.vertex_matrix().astype(np.float64), m.face_matrix().astype(np.int64)
    check_mesh(v, f, path)
    return v, f, None if colours is None else np.asarray(srgb_to_linear(colours), np.float32)


def normalise_mesh(v: np.ndarray) -> np.ndarray:
    """Centre on the floor (min y = 0) and scale to a 2-unit bounding diagonal."""
    lo, hi = v.min(0), v.max(0)
    s = 2.0 / np.linalg.norm(hi - lo)
    out = (v - 0.5 * (lo + hi)) * s
    out[:, 1] -= out[:, 1].min()
    return out


# -- PLY with vertex colours --------------------------------------------------------------------------------------

_PLY_HEAD = ("ply", "format binary_little_endian 1.0")


def write_ply(path: str | os.PathLike, v: np.ndarray, f: np.ndarray, colours: np.ndarray | None = None) -> Path:
    """Binary PLY with optional per-vertex colours (float r, g, b in [0, 1]; Mitsuba reads them)."""
    header = [*_PLY_HEAD, f"element vertex {len(v)}", "property float x", "property float y", "property float z"]
    if colours is not None:
        header += ["property float r", "property float g", "property float b"]
    header += [f"element face {len(f)}", "property list uchar int vertex_indices", "end_header"]
    vert = np.asarray(v, np.float32)
    if colours is not None:
        vert = np.concatenate([vert, np.asarray(colours, np.float32)], axis=1)
    faces = np.empty(len(f), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    faces["n"] = 3
    faces["i"] = f
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(("\n".join(header) + "\n").encode())
            fh.write(vert.astype("<f4").tobytes())
            fh.write(faces.tobytes())
    return Path(path)


def _read_own_ply(path: Path, data: bytes) -> tuple[np.ndarray, np.ndarray, np.ndarray | None] | None:
    """Parse the exact layout :func:`write_ply` writes; None for any other PLY."""
    end = data.find(b"end_header\n")
    if end < 0:
        raise MeshError(f"{path}: not a PLY file (no end_header)")
    head = data[:end].decode("ascii", "replace").splitlines()
    if tuple(head[:2]) != _PLY_HEAD:
        return None
    props = [h for h in head if h.startswith("property")]
    xyz = ["property float x", "property float y", "property float z"]
    rgb = ["property float r", "property float g", "property float b"]
    tail = ["property list uchar int vertex_indices"]
    if props not in (xyz + tail, xyz + rgb + tail):
        return None
    nv = int(next(h for h in head if h.startswith("element vertex")).split()[-1])
    nf = int(next(h for h in head if h.startswith("element face")).split()[-1])
    ncol = len(props) - 1
    body = data[end + len(b"end_header\n"):]
    need = nv * ncol * 4 + nf * 13
    if len(body) != need:
        raise MeshError(f"{path}: truncated or damaged PLY ({len(body)} bytes of data, expected {need})")
    vert = np.frombuffer(body[:nv * ncol * 4], "<f4").reshape(nv, ncol)
    faces = np.frombuffer(body[nv * ncol * 4:], dtype=[("n", "u1"), ("i", "<i4", (3,))])
    if nf and (faces["n"] != 3).any():
        raise MeshError(f"{path}: damaged PLY (a face without 3 corners)")
    v, f = vert[:, :3].astype(np.float64), faces["i"].astype(np.int64)
    return v, f, (vert[:, 3:6].astype(np.float32) if ncol == 6 else None)


def read_ply(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Vertices, triangles and per-vertex colours (None if the file has none) of a PLY file.

    Files written by :func:`write_ply` are parsed here (a truncated file is named, not dumped by
    Mitsuba's parser); other PLYs go through Mitsuba's loader.
    """
    path = Path(path)
    if not path.is_file():
        raise MeshError(f"{path}: no such mesh file")
    data = path.read_bytes()
    own = _read_own_ply(path, data)
    if own is None:
        import mitsuba as mi

        try:
            p = mi.traverse(mi.load_dict({"type": "ply", "filename": str(path)}))
        except Exception as exc:
            raise MeshError(f"{path}: cannot read PLY ({str(exc).splitlines()[0] if str(exc) else exc})") from None
        v = np.array(p["vertex_positions"], np.float64).reshape(-1, 3)
        f = np.array(p["faces"], np.int64).reshape(-1, 3)
        c = np.array(p["vertex_color"], np.float32).reshape(-1, 3) if "vertex_color" in p else None
        own = (v, f, c)
    check_mesh(own[0], own[1], path)
    return own


def read_ply_colours(path: str | os.PathLike, default: float = 0.5) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`read_ply` with colours filled with ``default`` grey where the file has none."""
    v, f, c = read_ply(path)
    return v, f, c if c is not None else np.full((len(v), 3), default, np.float32)


# -- OBJ with texture coordinates ---------------------------------------------------------------------------------


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
        return vertex_normals(self.vertices, self.faces)


def _index(token: str, count: int, what: str, path: Path, line_no: int) -> int:
    i = int(token)
    i = i - 1 if i > 0 else count + i  # OBJ is 1-based; negative = relative to the end
    if not (0 <= i < count):
        raise MeshError(f"{path}:{line_no}: {what} index {token} out of range (have {count})")
    return i


def load_obj(path: str | os.PathLike) -> UVMesh:
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
    f = np.asarray(faces, np.int64)
    check_mesh(v, f, path)
    texture = None
    if mtllib is not None and mtllib.is_file():
        for line in mtllib.read_text().splitlines():
            p = line.split()
            if p and p[0] == "map_Kd":
                texture = mtllib.parent / " ".join(p[1:])
                break
    return UVMesh(v, f, np.asarray(uvs, np.float64), np.asarray(fuvs, np.int64), texture, path)


def write_obj(path: str | os.PathLike, vertices: np.ndarray, like: UVMesh) -> Path:
    """OBJ with new ``vertices`` and the faces and texture coordinates of ``like`` (atomic write)."""
    lines = [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in vertices]
    lines += [f"vt {u:.6f} {w:.6f}" for u, w in like.uvs]
    lines += [f"f {a + 1}/{ta + 1} {b + 1}/{tb + 1} {c + 1}/{tc + 1}"
              for (a, b, c), (ta, tb, tc) in zip(like.faces, like.face_uvs)]
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(lines) + "\n")
    return Path(path)
