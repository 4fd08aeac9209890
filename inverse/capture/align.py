"""Similarity alignment of recovered cameras to known ones (Umeyama 1991, eq. 40–42): the scale, rotation and
translation that structure from motion cannot know, fitted on camera centres by least squares."""

from __future__ import annotations

import numpy as np

from foundation.errors import UsageError


def similarity(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """(s, R, t) minimising Σ‖s·R·src_i + t − dst_i‖² over rotations R (no reflection), scales s > 0."""
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) < 3:
        raise UsageError(f"similarity: two (N ≥ 3, 3) point sets expected, got {src.shape} and {dst.shape}")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    var = (a ** 2).sum() / len(a)
    if var <= 0:
        raise UsageError("similarity: the source points coincide")
    u, d, vt = np.linalg.svd(b.T @ a / len(a))
    sign = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        sign[2, 2] = -1.0
    r = u @ sign @ vt
    s = float(np.trace(np.diag(d) @ sign) / var)
    return s, r, mu_d - s * r @ mu_s


def camera_errors(recovered: dict[str, np.ndarray], truth: dict[str, np.ndarray], radius: float) -> dict:
    """Recovered cam-to-world matrices against true ones (by name) after the similarity of their centres: centre
    error as a fraction of ``radius`` (the orbit's), rotation error in degrees; median and max of each."""
    names = sorted(set(recovered) & set(truth))
    if len(names) < 3:
        raise UsageError(f"camera_errors: {len(names)} cameras in common; need at least 3")
    cs = np.array([recovered[n][:3, 3] for n in names])
    ct = np.array([truth[n][:3, 3] for n in names])
    s, r, t = similarity(cs, ct)
    pos = np.linalg.norm((s * cs @ r.T + t) - ct, axis=1) / radius
    rot = []
    for n in names:
        d = (r @ recovered[n][:3, :3]).T @ truth[n][:3, :3]
        rot.append(np.degrees(np.arccos(np.clip((np.trace(d) - 1) / 2, -1.0, 1.0))))
    rot = np.array(rot)
    return {"cameras": len(names), "scale": s, "rotation": r.tolist(), "translation": t.tolist(),
            "centre_error_median": float(np.median(pos)), "centre_error_max": float(pos.max()),
            "rotation_error_median_deg": float(np.median(rot)), "rotation_error_max_deg": float(rot.max())}
