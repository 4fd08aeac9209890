"""Geometry metrics against ground truth: Chamfer, normal consistency, spikes, inverted triangles."""

from __future__ import annotations

import numpy as np

from .mesh import edge_lengths, face_normals, sample_surface


def _samples(v, f, n, seed):
    pts, fid, _ = sample_surface(v, f, n, np.random.default_rng(seed))
    return pts, face_normals(v, f)[fid]


def chamfer(va, fa, vb, fb, n: int = 100_000, n_ref: int = 1_000_000, seed: int = 0) -> dict:
    """Two-sided Chamfer distance (mean of both directions' mean nearest distances) and normal consistency.

    Each direction queries ``n`` points of one surface against ``n_ref`` points
    of the other: the denser reference keeps the estimator's floor (the
    distance between two samplings of the *same* surface) an order of
    magnitude below the artifacts being measured (see test_mesh_metrics).
    Normal consistency is the mean |n_a · n_b| over nearest pairs (orientation-free).
    """
    from scipy.spatial import cKDTree

    pa, na = _samples(va, fa, n, seed)
    pb, nb = _samples(vb, fb, n, seed + 1)
    ra, rna = _samples(va, fa, n_ref, seed + 2)
    rb, rnb = _samples(vb, fb, n_ref, seed + 3)
    da, ia = cKDTree(rb).query(pa)
    db, ib = cKDTree(ra).query(pb)
    na_ref, nb_ref = rna, rnb
    nc = 0.5 * (np.abs(np.sum(na * nb_ref[ia], axis=1)).mean() + np.abs(np.sum(nb * na_ref[ib], axis=1)).mean())
    return {"chamfer": float(0.5 * (da.mean() + db.mean())), "normal_consistency": float(nc)}


def inverted_triangles(v: np.ndarray, f: np.ndarray, gv: np.ndarray, gf: np.ndarray) -> int:
    """Triangles facing against the ground-truth surface at their nearest ground-truth triangle.

    Orientation is judged against the truth, not against the starting mesh: a
    morph that *unfolds* a fold of the coarse input must not count as flipping.
    """
    from scipy.spatial import cKDTree

    gc = gv[gf].mean(axis=1)
    idx = cKDTree(gc).query(v[f].mean(axis=1))[1]
    return int((np.sum(face_normals(v, f) * face_normals(gv, gf)[idx], axis=1) < 0).sum())


def spikes(v0: np.ndarray, v1: np.ndarray, f: np.ndarray, gv: np.ndarray, gf: np.ndarray, k: float = 3.0) -> dict:
    """Spike vertices (moved more than k× their local edge length) and inverted triangles (normal
    flipped relative to the start: folds the optimisation made); ``spikes`` = both.

    ``facing_against_truth`` is also reported but is only meaningful for a closed,
    non-overlapping ground truth (the village's overlapping parts confuse it).
    """
    moved = np.linalg.norm(v1 - v0, axis=1) > k * edge_lengths(v0, f)
    flipped = int((np.sum(face_normals(v0, f) * face_normals(v1, f), axis=1) < 0).sum())
    return {"spike_vertices": int(moved.sum()), "inverted_triangles": flipped,
            "facing_against_truth": inverted_triangles(v1, f, gv, gf), "spikes": int(moved.sum() + flipped)}
