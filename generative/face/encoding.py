"""Learned UV-space face stages (seed 003 §2–§4) on one shared backbone: the encodings they share.

Notation (seed 003 → code):

=====================  ===================================================================================
T_inc, M               ``lit`` (the photo resampled into UV, zero where unseen) and ``seen``
T_hom ≈ T_alb          the completion model's output: a complete, delit albedo
f_inp, f_hom           one conditional diffusion model here (:class:`CompletionStage`): completion and light
                       homogenisation in a single step, since our target is the albedo itself
LoRA_i, i ∈ {alb, n,   one low-rank adapter per intrinsic (``peft``) on the *frozen* completion backbone
r, s}
h_i = Attn(q_i, K, V)  :class:`CrossIntrinsicAttention`: each branch's queries attend to the keys and values
                       of every branch (concatenated along the token axis)
=====================  ===================================================================================

**The backbone.** The seed adapts one large pretrained diffusion transformer to every task. None exists
offline, so the completion model *is* the backbone: a ``diffusers`` UNet (the shared
:class:`core.ConditionalDiffusion`) trained as a conditional diffusion model (v-prediction, DDIM) that maps the
partial lit texture, its mask and the template geometry to a complete delit albedo. The decomposition then
freezes it and adds one LoRA adapter per intrinsic (albedo, normal, roughness, specular), all four branches run
in one batch (branch-major), each with its own adapter (``peft``'s mixed-adapter batches), and the backbone's
self-attention layers become cross-intrinsic. The decomposition is used as a single-step deterministic
predictor (the backbone at t = 0, the completed albedo in its image slot): on two cores a stochastic multi-step
decomposition would cost ~10× more and, judged by per-texel errors, do worse than its own mean (measured for the
diffusion renderer, issue 13). Ablations: *shared* (the same adapters, plain self-attention) and *independent*
(four full copies of the backbone, each fine-tuned alone: no sharing, 4× the parameters).

**Super-resolution** (§4): a small residual CNN upsamples the model-resolution maps 2× (pixel shuffle), added to
bicubic; it is trained on the training scans' maps and judged against bicubic on the held-out scan.

Every stage trains on the shared loop (checkpoint, budget, resume, NaN policy, progress, metrics JSON).
"""

from __future__ import annotations


import numpy as np

from foundation.errors import UsageError

from .data import FaceSet, TARGETS

#: lit (3), seen (1), covered (1), the baseline's albedo (3), position (3) and normal (3) in the face frame

COND_CHANNELS = 14
GEO = slice(8, 14)  #: the geometry channels of the condition
ALBEDO_LEVEL = 0.35  #: albedos are compared up to a global scale: each is scaled to this mean over the seen texels
RESIDUAL = 2.0  #: the completion model generates RESIDUAL × (albedo − baseline) in the encoded space
BRANCHES = tuple(TARGETS)  #: albedo, normal, roughness, specular
VARIANTS = ("cross_attention", "shared", "independent")
MAP_CHANNELS = sum(TARGETS.values())  #: 8: the super-resolution model's channels


# -- encodings ---------------------------------------------------------------------------------------------------------


def _pool(a: np.ndarray, f: int) -> np.ndarray:
    """Box average by ``f`` over axes 1, 2 of (N, H, W, …)."""
    if f == 1:
        return a
    n, h, w = a.shape[:3]
    return a.reshape(n, h // f, f, w // f, f, *a.shape[3:]).mean(axis=(2, 4))


def at_resolution(d: FaceSet, res: int) -> FaceSet:
    """The set box-filtered to ``res``: a texel is seen (covered) when all its sub-texels are; lit is averaged over
    seen sub-texels; normals are renormalised."""
    if d.res % res:
        raise UsageError(f"the data's {d.res}² maps do not divide into {res}²")
    f = d.res // res
    if f == 1:
        return d
    seen = _pool(d.seen.astype(np.float32), f) > 0.999
    mask = _pool(d.mask.astype(np.float32), f) > 0.999
    unit = lambda a: a / np.maximum(np.linalg.norm(a, axis=-1, keepdims=True), 1e-8)  # noqa: E731
    lit = _pool(d.lit * d.seen[..., None], f) * seen[..., None]
    base = _pool(d.baseline, f)
    t = {k: _pool(v, f) for k, v in d.targets.items()}
    t["normal"] = unit(t["normal"])
    g = {k: _pool(v, f) for k, v in d.geometry.items()}
    g["normal_geo"], g["tangent"] = unit(g["normal_geo"]), unit(g["tangent"])
    g["bitangent_sign"] = np.sign(g["bitangent_sign"])
    return FaceSet(d.names, d.records, lit.astype(np.float32), seen & mask, mask,
                   (_pool(d.position_face, f) * mask[..., None]).astype(np.float32),
                   (unit(_pool(d.normal_face, f)) * mask[..., None]).astype(np.float32), base.astype(np.float32),
                   {k: v.astype(np.float32) for k, v in t.items()}, {k: v.astype(np.float32) for k, v in g.items()})


def encode_lit(lit: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """(N, H, W, 3) linear radiance → [−1, 1], exposure-free: divided by twice the mean seen luminance (lighting's
    absolute level is unknowable from one photo), gamma 1/2.2, 0 where unseen."""
    lum = lit.mean(-1)
    mean = np.array([lum[i][seen[i]].mean() if seen[i].any() else 1.0 for i in range(len(lit))], np.float32)
    e = np.clip(lit / (2.0 * mean[:, None, None, None] + 1e-8), 0.0, 2.0) ** (1 / 2.2)
    return np.where(seen[..., None], e * 2.0 / 2.0 ** (1 / 2.2) - 1.0, 0.0).astype(np.float32)


def normalise_albedo(albedo: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """(N, H, W, 3) albedos scaled to a mean of ALBEDO_LEVEL over each one's seen texels (a photo fixes albedo × light
    intensity only: the models work, and are judged, up to that scale), clipped to [0, 1]."""
    out = np.empty_like(albedo, dtype=np.float32)
    for i in range(len(albedo)):
        ref = seen[i] if seen[i].any() else np.ones(seen[i].shape, bool)
        out[i] = np.clip(albedo[i] * ALBEDO_LEVEL / max(float(albedo[i][ref].mean()), 1e-4), 0.0, 1.0)
    return out


def condition(d: FaceSet) -> np.ndarray:
    """(N, 14, H, W): the local condition of every face model."""
    c = np.concatenate([encode_lit(d.lit, d.seen), d.seen[..., None] * 2.0 - 1.0, d.mask[..., None] * 2.0 - 1.0,
                        encode_albedo(normalise_albedo(d.baseline, d.seen)), d.position_face, d.normal_face], -1)
    return np.ascontiguousarray(c.transpose(0, 3, 1, 2), np.float32)


def encode_albedo(albedo: np.ndarray) -> np.ndarray:
    """Linear albedo (…, 3) → sRGB in [−1, 1]."""
    from foundation.imageio import linear_to_srgb

    return (linear_to_srgb(np.clip(albedo, 0.0, 1.0)) * 2.0 - 1.0).astype(np.float32)


def decode_albedo(x: np.ndarray) -> np.ndarray:
    from foundation.imageio import srgb_to_linear

    return srgb_to_linear(np.clip((x + 1.0) * 0.5, 0.0, 1.0)).astype(np.float32)


def encode_maps(maps: dict[str, np.ndarray]) -> np.ndarray:
    """Maps (N, H, W, C) → (N, 8, H, W) in [−1, 1]: sRGB albedo, unit normal, roughness and specular ×2 − 1."""
    x = np.concatenate([encode_albedo(maps["albedo"]), maps["normal"], maps["roughness"] * 2 - 1,
                        maps["specular"] * 2 - 1], -1)
    return np.ascontiguousarray(x.transpose(0, 3, 1, 2), np.float32)


def decode_maps(x: np.ndarray) -> dict[str, np.ndarray]:
    """Inverse of :func:`encode_maps` (normals renormalised, ranges clipped)."""
    x = np.asarray(x, np.float32).transpose(0, 2, 3, 1)
    n = x[..., 3:6]
    n = n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-6)
    n[..., 2] = np.maximum(n[..., 2], 0.0)
    n = n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-6)
    return {"albedo": decode_albedo(x[..., :3]), "normal": n.astype(np.float32),
            "roughness": np.clip((x[..., 6:7] + 1) * 0.5, 0.05, 1.0), "specular": np.clip((x[..., 7:8] + 1) * 0.5, 0.0, 1.0)}


def mirror(cond: np.ndarray, maps: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None]:
    """The same face mirrored across its midline: u flipped, the side components of position and normal negated,
    and the tangent-space normal's x negated (the tangent ∂p/∂u reverses under the reflection)."""
    c = cond[..., ::-1].copy()
    c[:, GEO.start] *= -1  # side component of the position
    c[:, GEO.start + 3] *= -1  # ... and of the normal
    if maps is None:
        return c, None
    m = maps[..., ::-1].copy()
    m[:, 3] *= -1
    return c, m


