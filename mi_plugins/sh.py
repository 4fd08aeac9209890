"""Real spherical harmonics for low-frequency environment light (Ramamoorthi & Hanrahan 2001).

An environment L(ω) band-limited to order ``n`` (bands l = 0…n, (n + 1)² coefficients L_lm) is

    L(ω) = Σ_lm L_lm Y_lm(ω)                      (orthonormal real SH, ∫ Y_lm Y_l'm' dω = δ)
    E(n) = Σ_lm Â_l L_lm Y_lm(n)                  (irradiance of a surface with normal n, unoccluded)

with the clamped-cosine convolution constants Â_0 = π, Â_1 = 2π/3, Â_2 = π/4, Â_3 = 0, Â_4 = −π/24 (R&H eq. 8–9).
For band-limited light these are exact; for any light, E from L's first bands is within 1–3 % (R&H §3).
A point's occluded irradiance Σ L_lm T_lm uses its *transfer* T_lm = ∫ V(ω) (n·ω)⁺ Y_lm(ω) dω (precomputed
radiance transfer, Sloan et al. 2002), exact for band-limited L whatever V is.

Glossy reflection: a GGX lobe of width α about the mirror direction r is treated as a zonal lobe with SH
coefficients g_l = exp(−α² l (l + 1)) (a spherical Gaussian of sharpness 1 / (2α²) in reflected directions, the
half-vector lobe's 2/α² widened by the reflection), times the lobe's directional albedo — an approximation whose
error against Mitsuba is tested (``tests/plugins/test_uv_shader_environment.py``).

Directions follow Mitsuba's ``envmap``: pixel (u, v) looks along (sin θ sin φ, cos θ, −sin θ cos φ), φ = 2πu,
θ = πv, in the emitter's frame. Everything is plain arithmetic, so it runs on numpy arrays and on Dr.Jit arrays.
"""

from __future__ import annotations

import math

import numpy as np


def n_coeffs(order: int) -> int:
    """(order + 1)² coefficients for bands 0…order."""
    return (order + 1) ** 2


def band(j: int) -> int:
    """The band l of flat index j = l² + l + m."""
    return int(math.isqrt(j))


def cosine_lobe(l: int) -> float:
    """Â_l: SH coefficient of the clamped cosine (n·ω)⁺, so that E = Σ Â_l L_lm Y_lm(n) (R&H eq. 8)."""
    if l == 0:
        return math.pi
    if l == 1:
        return 2.0 * math.pi / 3.0
    if l % 2:
        return 0.0
    return (2.0 * math.pi * (-1) ** (l // 2 - 1) / ((l + 2) * (l - 1))
            * math.factorial(l) / (2 ** l * math.factorial(l // 2) ** 2))


def glossy_lobe(l: int, alpha):
    """g_l(α) = exp(−α² l (l + 1)): the zonal SH coefficient (normalised: g_0 = 1) of a GGX reflection lobe."""
    import drjit as dr

    e = -(alpha * alpha) * float(l * (l + 1))
    return dr.exp(e) if dr.is_array_v(alpha) else np.exp(e)


def basis(x, y, z, order: int) -> list:
    """[Y_j(x, y, z)] for j = l² + l + m, l ≤ order: real orthonormal SH of unit directions.

    Associated Legendre recurrence on z with the azimuthal factors sin^m θ cos mφ, sin^m θ sin mφ built from (x, y)
    as polynomials (no trigonometry), Condon–Shortley phase included.
    """
    out = [None] * n_coeffs(order)
    # c_m + i s_m = (x + i y)^m
    c, s = [1.0 + 0.0 * x], [0.0 * x]
    for m in range(1, order + 1):
        c.append(x * c[m - 1] - y * s[m - 1])
        s.append(x * s[m - 1] + y * c[m - 1])
    for m in range(order + 1):
        # P̄_mm = (−1)^m (2m − 1)!!, P̄_{m+1,m} = z (2m + 1) P̄_mm, then the three-term recurrence in l
        p_mm = (-1) ** m * float(np.prod(np.arange(1, 2 * m, 2))) if m else 1.0
        prev2, prev = None, p_mm + 0.0 * z
        for l in range(m, order + 1):
            if l == m:
                p = prev
            elif l == m + 1:
                p = z * (2 * m + 1) * p_mm
            else:
                p = ((2 * l - 1) * z * prev - (l + m - 1) * prev2) / (l - m)
            if l > m:
                prev2, prev = prev, p
            k = math.sqrt((2 * l + 1) / (4 * math.pi) * math.factorial(l - m) / math.factorial(l + m))
            if m == 0:
                out[l * l + l] = k * p
            else:
                out[l * l + l + m] = math.sqrt(2.0) * k * p * c[m]
                out[l * l + l - m] = math.sqrt(2.0) * k * p * s[m]
    return out


# -- environment maps (numpy) ---------------------------------------------------------------------


def envmap_directions(h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit directions (H, W, 3) of a latitude–longitude map's pixel centres (Mitsuba's envmap) and their solid
    angles (H, W)."""
    theta = (np.arange(h) + 0.5) / h * np.pi
    phi = (np.arange(w) + 0.5) / w * 2 * np.pi
    th, ph = np.meshgrid(theta, phi, indexing="ij")
    dirs = np.stack([np.sin(th) * np.sin(ph), np.cos(th), -np.sin(th) * np.cos(ph)], -1)
    return dirs, np.sin(th) * (np.pi / h) * (2 * np.pi / w)


def project_envmap(pixels: np.ndarray, order: int, rotation: np.ndarray | None = None) -> np.ndarray:
    """SH coefficients (n_coeffs, 3) of a latitude–longitude radiance map; ``rotation`` (3×3) takes the map's
    frame to the world's (an envmap's ``to_world``)."""
    h, w = pixels.shape[:2]
    dirs, dw = envmap_directions(h, w)
    if rotation is not None:
        dirs = dirs @ np.asarray(rotation, float).T
    y = np.stack(basis(dirs[..., 0], dirs[..., 1], dirs[..., 2], order), -1)  # (H, W, J)
    return np.einsum("hwj,hwc,hw->jc", y, pixels[..., :3].astype(np.float64), dw)


def envmap_from_coeffs(coeffs: np.ndarray, h: int, w: int) -> np.ndarray:
    """The band-limited radiance map (H, W, 3) of SH coefficients (n_coeffs, 3) (negative lobes kept)."""
    order = math.isqrt(len(coeffs)) - 1
    dirs, _ = envmap_directions(h, w)
    y = np.stack(basis(dirs[..., 0], dirs[..., 1], dirs[..., 2], order), -1)
    return (y @ np.asarray(coeffs, np.float64)).astype(np.float32)
