"""Paired image data for the GAN stages (REAL-DIBS §3.3, §5.1) from a morph benchmark and a morph run.

For every camera of the benchmark (train and held-out):

* ``photos``   i_j — the benchmark's photos (target images);
* ``rendered`` r_j — the coarse input mesh rendered by Mitsuba (I_render);
* ``morphed``  m_j — the morphed mesh rendered the same way (I_morphed, eq. 5.1).

Both renders use the scene of :func:`inverse.morph.evaluate_morph` (lit vertex
colours under the benchmark's HDRI, ``path`` with max depth 3, 32 spp, seed = view
index), so the "input" and "morphed" rows of the GAN bench equal that evaluation.
Renders are cached in the morph run folder (``gan_renders.npz``), keyed by the
meshes' digests and the settings. Batches are seeded random crops with random
horizontal flips (the thesis' augmentation).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

import mi_plugins  # noqa: F401
import mitsuba as mi

from foundation.progress import progress_bar
from inverse.morph import MorphBenchmark, morph_scene, sensor_dict, morph_views
from .settings import GanDataSettings


@dataclass
class PairedViews:
    """All views of one case as float32 (V, H, W, 3) linear RGB arrays, with the split."""

    photos: np.ndarray
    rendered: np.ndarray
    morphed: np.ndarray
    train: list[int]
    test: list[int]
    case: str = ""

    @property
    def resolution(self) -> int:
        return int(self.photos.shape[1])

    def digest(self) -> str:
        """SHA-256 (16 hex digits) of the images and the split: what a checkpoint trained on them must match."""
        import hashlib

        h = hashlib.sha256()
        for a in (self.photos, self.rendered, self.morphed):
            h.update(np.ascontiguousarray(a, np.float32).tobytes())
        h.update(json.dumps([list(map(int, self.train)), list(map(int, self.test))]).encode())
        return h.hexdigest()[:16]


def render_mesh_views(mesh_ply: Path, bench: MorphBenchmark, ids: list[int], s: GanDataSettings,
                      desc: str = "render", show_progress: bool = True) -> np.ndarray:
    """Render a coloured PLY at the benchmark's cameras ``ids`` → (len(ids), H, W, 3) float32."""
    meta = bench.meta
    res = meta.resolution
    scene = morph_scene(Path(mesh_ply), s.mode, meta.hdri, integrator={"type": "path", "max_depth": s.max_depth})
    out = np.empty((len(ids), res, res, 3), np.float32)
    with progress_bar(total=len(ids), desc=desc, unit="view", disable=not show_progress) as bar:
        for k, i in enumerate(ids):
            sensor = mi.load_dict(sensor_dict(meta.cameras[i], res, meta.fov))
            out[k] = np.array(mi.render(scene, sensor=sensor, spp=s.spp, seed=int(i)))[..., :3]
            bar.update(1)
    del scene
    return out


def load_paired_views(bench: MorphBenchmark, morph_dir: str | Path, s: GanDataSettings | None = None,
                      show_progress: bool = True) -> PairedViews:
    """Photos, coarse renders and morphed renders of every view; renders cached in ``morph_dir``."""
    s = s or GanDataSettings()

    def render(meshes: dict, ids: list[int]) -> dict:
        return {"rendered": render_mesh_views(meshes["coarse"], bench, ids, s, "render coarse", show_progress),
                "morphed": render_mesh_views(meshes["morphed"], bench, ids, s, "render morphed", show_progress)}

    photos, cached = morph_views(bench, morph_dir, "gan_renders.npz", asdict(s), render)
    rendered, morphed = cached["rendered"], cached["morphed"]
    meta = bench.meta
    if photos.shape != rendered.shape:
        raise ValueError(f"{bench.path}: photos {photos.shape} and renders {rendered.shape} differ in shape")
    return PairedViews(photos, rendered, morphed, list(meta.train), list(meta.test), meta.kind)


def to_nchw(images: np.ndarray) -> torch.Tensor:
    """(N, H, W, 3) or (H, W, 3) numpy → (N, 3, H, W) float32 torch tensor."""
    a = np.asarray(images, np.float32)
    if a.ndim == 3:
        a = a[None]
    return torch.from_numpy(np.ascontiguousarray(a.transpose(0, 3, 1, 2)))


def random_crops(stacks: list[np.ndarray], ids: np.ndarray, crop: int, rng: np.random.Generator,
                 flip: bool = True) -> list[torch.Tensor]:
    """The same random ``crop``² window (and flip) of view ``ids[k]`` from every stack → [(B, 3, crop, crop)].

    Whole images when ``crop`` ≥ the image side.
    """
    h, w = stacks[0].shape[1:3]
    out = [[] for _ in stacks]
    for i in ids:
        if crop >= min(h, w):
            y0 = x0 = 0
            ch, cw = h, w
        else:
            y0, x0 = int(rng.integers(0, h - crop + 1)), int(rng.integers(0, w - crop + 1))
            ch = cw = crop
        f = flip and bool(rng.random() < 0.5)
        for k, st in enumerate(stacks):
            patch = st[int(i), y0:y0 + ch, x0:x0 + cw]
            out[k].append(patch[:, ::-1] if f else patch)
    return [to_nchw(np.stack(p)) for p in out]
