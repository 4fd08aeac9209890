"""Geometry metrics against ground truth: Chamfer, normal consistency, spikes, inverted triangles."""

from __future__ import annotations

import numpy as np

from .files import Memo, array_key
from .mesh import edge_lengths, face_normals, sample_surface, unique_edges


#: sample counts (queries per direction, reference samples) of :func:`chamfer` and :func:`truth_surface` where a
#: caller names none. At these the estimator's floor (two samplings of one surface) is an order of magnitude below
#: the artifacts the benches measure; the test suite lowers them (tests/conftest.py: 20k / 200k, the morph trace's
#: own counts), where only orderings and thresholds far above that floor are checked
DEFAULT_SAMPLES = (100_000, 1_000_000)


def _samples(v, f, n, seed):
    pts, fid, _ = sample_surface(v, f, n, np.random.default_rng(seed))
    return pts, face_normals(v, f)[fid]


#: the reference side of the last few :func:`chamfer` calls (a morph compares many meshes with one ground truth:
#: its samplings and k-d tree are built once): (query points, their normals, reference normals, tree)
_REFERENCES = Memo(2)
#: results of the last few calls, and dense truth samplings for :func:`truth_surface`: every run on a benchmark
#: evaluates the same input mesh against the same truth (a test module's dozen runs, the λ candidates, the suite)
_RESULTS = Memo(32)
_TRUTHS = Memo(2)


def _reference_side(vb, fb, n: int, n_ref: int, seed: int) -> tuple:
    """Surface b's ``n`` query samples (seed + 1), its ``n_ref`` reference samples (seed + 3) and their k-d tree,
    cached by the mesh's bytes: the same arrays as sampling anew, so results do not depend on the cache."""
    from scipy.spatial import cKDTree

    def make():
        pb, nb = _samples(vb, fb, n, seed + 1)
        rb, rnb = _samples(vb, fb, n_ref, seed + 3)
        return pb, nb, rnb, cKDTree(rb, balanced_tree=False, compact_nodes=False)
    return _REFERENCES.get((array_key(vb, fb), n, n_ref, seed), make)


def chamfer(va, fa, vb, fb, n: int | None = None, n_ref: int | None = None, seed: int = 0) -> dict:
    """Two-sided Chamfer distance (mean of both directions' mean nearest distances) and normal consistency.

    Each direction queries ``n`` points of one surface against ``n_ref`` points
    of the other: the denser reference keeps the estimator's floor (the
    distance between two samplings of the *same* surface) an order of
    magnitude below the artifacts being measured (see test_mesh_metrics).
    Normal consistency is the mean |n_a · n_b| over nearest pairs (orientation-free).
    Surface b (the ground truth, in every use here) has its samplings and k-d tree cached between calls, and
    a call repeated with equal arrays returns its earlier result. ``n`` / ``n_ref`` None: :data:`DEFAULT_SAMPLES`.
    """
    from scipy.spatial import cKDTree

    n = DEFAULT_SAMPLES[0] if n is None else n
    n_ref = DEFAULT_SAMPLES[1] if n_ref is None else n_ref

    def make():
        pa, na = _samples(va, fa, n, seed)
        pb, nb, nb_ref, tree_b = _reference_side(vb, fb, n, n_ref, seed)
        ra, na_ref = _samples(va, fa, n_ref, seed + 2)
        da, ia = tree_b.query(pa)
        db, ib = cKDTree(ra, balanced_tree=False, compact_nodes=False).query(pb)
        nc = 0.5 * (np.abs(np.sum(na * nb_ref[ia], axis=1)).mean() + np.abs(np.sum(nb * na_ref[ib], axis=1)).mean())
        return {"chamfer": float(0.5 * (da.mean() + db.mean())), "normal_consistency": float(nc)}
    # the estimator is deterministic in its inputs: a repeat returns the same figures (a copy: callers may edit it)
    return dict(_RESULTS.get((array_key(va, fa), array_key(vb, fb), n, n_ref, seed), make))


def triangle_areas(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    return 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)


class TruthSurface:
    """A dense area-uniform sampling of a ground-truth surface (``n`` points), their normals and a k-d tree:
    built once, queried for every mesh compared with that truth."""

    def __init__(self, gv: np.ndarray, gf: np.ndarray, n: int = 1_000_000, seed: int = 0):
        from scipy.spatial import cKDTree

        pts, fid, _ = sample_surface(gv, gf, n, np.random.default_rng(seed))
        self.normals = face_normals(gv, gf)[fid]
        self.tree = cKDTree(pts, balanced_tree=False, compact_nodes=False)


def truth_surface(gv: np.ndarray, gf: np.ndarray, n: int | None = None, seed: int = 0) -> TruthSurface:
    """:class:`TruthSurface` of a mesh, built once for the last few meshes asked for (keyed by content); ``n`` None:
    the reference count of :data:`DEFAULT_SAMPLES`."""
    n = DEFAULT_SAMPLES[1] if n is None else n
    return _TRUTHS.get((array_key(gv, gf), n, seed), lambda: TruthSurface(gv, gf, n, seed))


def signed_distance(x: np.ndarray, truth: TruthSurface) -> np.ndarray:
    """Signed distance of points to the truth: the offset from the nearest sample of its dense sampling along that
    sample's normal (positive on the side it points to). Along the normal, not to the sample itself: the distance
    to the nearest sample also holds the sampling's lateral spacing (about 0.003 on a unit sphere at 200k samples),
    which would make every point on the surface look off it by that much, with a random sign."""
    x = np.asarray(x, np.float64)
    i = truth.tree.query(x)[1]
    return np.sum((x - truth.tree.data[i]) * truth.normals[i], axis=1)


def facing_against_truth(v: np.ndarray, f: np.ndarray, truth: TruthSurface) -> dict:
    """Triangles facing against the ground truth at the truth's surface point nearest their centroid.

    ``count`` and ``area_fraction`` (share of the mesh's area): meshes with different triangle counts (a
    coarse input and its remeshed morph) compare by the fraction. The nearest point comes from a dense
    sampling of the truth (:class:`TruthSurface`), not from the truth's triangle centroids: a large
    truth triangle's centroid can be far from the part of it a small triangle lies on (a house wall is two
    triangles), and the nearest centroid then belongs to another wall. Orientation is judged against the
    truth, not against the starting mesh: a morph that *unfolds* a fold of its input does not count as flipping.
    """
    against = facing_mask(v, f, truth)
    area = triangle_areas(v, f)
    return {"count": int(against.sum()), "area_fraction": float(area[against].sum() / max(area.sum(), 1e-30))}


def facing_mask(v: np.ndarray, f: np.ndarray, truth: TruthSurface) -> np.ndarray:
    """Per triangle: whether it faces against the truth (:func:`facing_against_truth`)."""
    idx = truth.tree.query(v[f].mean(axis=1))[1]
    return np.sum(face_normals(v, f) * truth.normals[idx], axis=1) < 0


def vertex_neighbours_mean(x: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Mean of ``x`` over each vertex's 1-ring (edge neighbours, each counted once)."""
    import scipy.sparse as sp

    e = unique_edges(f)
    n = len(x)
    a = sp.coo_matrix((np.ones(2 * len(e)), (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])), shape=(n, n)).tocsr()
    deg = np.asarray(a.sum(axis=1)).ravel()
    return (a @ x) / np.maximum(deg, 1)[:, None]


def spike_mask(v0: np.ndarray, v1: np.ndarray, f: np.ndarray, k: float = 3.0,
               ell: np.ndarray | None = None) -> np.ndarray:
    """Vertices whose displacement ``v1 − v0`` departs from their 1-ring's mean displacement by more than ``k`` ×
    their local edge length in ``v0`` (``ell``, computed when not given): the spikes of :func:`spikes`."""
    d = v1 - v0
    ell = edge_lengths(v0, f) if ell is None else ell
    return np.linalg.norm(d - vertex_neighbours_mean(d, f), axis=1) > k * ell


def spikes(v0: np.ndarray, v1: np.ndarray, f: np.ndarray, k: float = 3.0) -> dict:
    """Spikes and folds a morph made, judged against its start ``v0`` (same topology ``f``).

    * ``spike_vertices``: vertices whose displacement departs from the mean displacement of their 1-ring
      by more than ``k`` × their local edge length — a vertex that left its neighbours (a spike or a pit).
      A region moving together (an eroded chimney growing back, a bulge pushed in) is not a spike.
    * ``far_moved_vertices``: vertices that moved more than ``k`` × their local edge length at all (the
      earlier definition of a spike; coherent large moves count, reported beside).
    * ``inverted_triangles``: triangles whose normal flipped relative to the start (folds).
    * ``spikes`` = spike vertices + inverted triangles.
    """
    ell = edge_lengths(v0, f)
    spike = spike_mask(v0, v1, f, k, ell)
    far = np.linalg.norm(v1 - v0, axis=1) > k * ell
    flipped = int((np.sum(face_normals(v0, f) * face_normals(v1, f), axis=1) < 0).sum())
    return {"spike_vertices": int(spike.sum()), "far_moved_vertices": int(far.sum()), "inverted_triangles": flipped,
            "spikes": int(spike.sum() + flipped)}
