"""Intrinsic decomposition network (seed 000 §3.1): an image → its layers A, I, S (and normal N).

The seed's key idea for data: a network that splits *photos* into intrinsic layers turns images that
have no 3D model into more (intrinsics → photo) pairs for the diffusion renderer. Here it is trained on
procedurally varied Mitsuba scenes whose ground-truth layers come from the ``intrinsic`` integrator
(its RGB output is the full render D + S = A·I + S, so every training image has exact layers):

* shapes — Mitsuba's sphere, cube and cylinder and meshes shipped inside pymeshlab's wheel (cow,
  airplane, the vertex-coloured airplane, bone), never the benchmark meshes (village, armadillo, bunny),
  so the network has not seen the objects whose photos it is later applied to;
* materials — ``diffuse`` and ``principled`` (random roughness, metallic, specular) with a plain
  colour, a vertex colour, or a scikit-image photograph as texture (tinted, scaled);
* a textured ground plane half the time, one of the bundled HDRIs at a random rotation, a random
  orbit camera.

Model: a ``diffusers`` ``UNet2DModel`` (no attention, timestep fixed at 0: a plain regression UNet)
from the image (sRGB in [−1, 1]) to the 12 channels of :func:`renderer.local_condition` (A in sRGB,
I and S through x/(1+x), N), L1 loss, trained on the shared loop. Held-out scenes give per-layer PSNR
(in those [0, 1] spaces) and the PSNR of the recomposition A·I + S against the image (linear).
"""

from __future__ import annotations

import functools
import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

import mi_plugins  # noqa: F401
import mitsuba as mi

from foundation.assets import bundled_hdris, envmap, pymeshlab_sample
from foundation.errors import UsageError
from foundation.files import cached_arrays
from foundation.loop import RunState, Stage, StepResult, TrainingSummary
from foundation.metrics import psnr
from foundation.progress import progress_bar
from foundation.scene import recompose
from foundation.threads import torch_threads

from generative.diffusion import OptimizerStage, load_trained, train_stage
from .renderer import LAYERS, condition_to_layers, intrinsic_layers, local_condition, photo_to_model
from .settings import DecompDataSettings, DecompSettings

TEXTURES = ("brick", "grass", "gravel", "astronaut", "rocket", "hubble_deep_field", "color", "coffee")
#: meshes inside pymeshlab's wheel (tests/sample_meshes); bunny is left out: it is the unseen-mesh benchmark
MESHES = ("cow.obj", "airplane.obj", "colored_airplane.ply", "bone.ply")
BUILTIN = ("sphere", "cube", "cylinder")
DECOMP_CHANNELS = 12


@functools.lru_cache(maxsize=None)
def _photo(name: str) -> np.ndarray:
    """A photograph shipped inside scikit-image's wheel (``skimage/data/NAME.png|.jpg``) as linear RGB float32."""
    import skimage.data
    from PIL import Image

    folder = Path(skimage.data.__file__).parent
    path = next((p for p in (folder / f"{name}.png", folder / f"{name}.jpg") if p.is_file()), None)
    if path is None:
        raise UsageError(f"{folder}: scikit-image's photograph {name!r} is missing (reinstall scikit-image)")
    img = np.asarray(Image.open(path).convert("RGB"), np.float32) / 255.0
    return np.where(img <= 0.04045, img / 12.92, ((img + 0.055) / 1.055) ** 2.4).astype(np.float32)


def _mesh_path(name: str) -> Path:
    return pymeshlab_sample(name)


@functools.lru_cache(maxsize=None)
def _mesh_bounds(name: str) -> tuple[tuple[float, ...], float]:
    """Centre and radius of a sample mesh's bounding box (to place it at the origin with radius 1)."""
    shape = mi.load_dict({"type": Path(name).suffix[1:], "filename": str(_mesh_path(name))})
    bb = shape.bbox()
    lo, hi = np.array(bb.min), np.array(bb.max)
    return tuple(float(x) for x in (lo + hi) / 2), float(np.linalg.norm(hi - lo) / 2)


def _texture(rng: np.random.Generator) -> dict:
    img = _photo(TEXTURES[int(rng.integers(len(TEXTURES)))])
    h, w = img.shape[:2]
    side = int(rng.integers(min(h, w) // 4, min(h, w) + 1))
    y, x = int(rng.integers(0, h - side + 1)), int(rng.integers(0, w - side + 1))
    tint = rng.uniform(0.35, 1.0, 3)
    tex = np.ascontiguousarray(img[y:y + side, x:x + side] * tint * rng.uniform(0.5, 1.0), np.float32)
    return {"type": "bitmap", "bitmap": mi.Bitmap(tex), "raw": True,
            "to_uv": mi.ScalarTransform4f().scale([float(rng.uniform(1, 4))] * 2 + [1])}


def _colour(rng: np.random.Generator, vertex_colours: bool) -> dict:
    r = rng.random()
    if vertex_colours and r < 0.5:
        return {"type": "mesh_attribute", "name": "vertex_color"}
    if r < 0.55:
        return {"type": "rgb", "value": [float(c) for c in rng.uniform(0.03, 0.9, 3)]}
    return _texture(rng)


def _material(rng: np.random.Generator, vertex_colours: bool) -> dict:
    base = _colour(rng, vertex_colours)
    if rng.random() < 0.55:
        bsdf = {"type": "diffuse", "reflectance": base}
    else:
        bsdf = {"type": "principled", "base_color": base, "roughness": float(rng.uniform(0.08, 0.9)),
                "metallic": float(rng.choice([0.0, 0.0, rng.uniform(0.0, 1.0)])),
                "specular": float(rng.uniform(0.2, 0.8))}
    return {"type": "twosided", "bsdf": bsdf}


def procedural_scene(index: int, s: DecompDataSettings) -> tuple[dict, dict]:
    """Scene ``index`` (its own seed): (scene dict, sensor dict); deterministic in (index, s.seed)."""
    rng = np.random.default_rng([s.seed, index])
    kind = rng.integers(len(BUILTIN) + len(MESHES))
    rot = mi.ScalarTransform4f().rotate([0, 1, 0], float(rng.uniform(0, 360))).rotate([1, 0, 0], float(rng.uniform(-30, 30)))
    if kind < len(BUILTIN):
        shape = {"type": BUILTIN[kind], "to_world": rot.scale(0.6 if BUILTIN[kind] == "cube" else 0.8)}
        vc = False
    else:
        name = MESHES[kind - len(BUILTIN)]
        centre, radius = _mesh_bounds(name)
        shape = {"type": Path(name).suffix[1:], "filename": str(_mesh_path(name)),
                 "to_world": rot.scale(1.0 / radius).translate([-c for c in centre])}
        vc = name.endswith(".ply") and "colored" in name
    shape["bsdf"] = _material(rng, vc)
    scene = {"type": "scene", "integrator": {"type": "intrinsic", "max_depth": s.max_depth},
             "env": envmap(bundled_hdris()[int(rng.integers(len(bundled_hdris())))],
                           to_world=mi.ScalarTransform4f().rotate([0, 1, 0], float(rng.uniform(0, 360)))),
             "object": shape}
    if rng.random() < 0.5:
        scene["ground"] = {"type": "rectangle", "to_world": mi.ScalarTransform4f().translate([0, -1.0, 0])
                           .rotate([1, 0, 0], -90).scale(4.0),
                           "bsdf": {"type": "diffuse", "reflectance": _colour(rng, False)}}
    theta, elev = rng.uniform(0, 2 * np.pi), rng.uniform(-0.1, 0.9)
    dist = rng.uniform(2.6, 3.6)
    eye = dist * np.array([np.cos(elev) * np.sin(theta), np.sin(elev), np.cos(elev) * np.cos(theta)])
    target = rng.normal(0, 0.1, 3)
    sensor = {"type": "perspective", "fov": float(rng.uniform(35, 50)),
              "to_world": mi.ScalarTransform4f().look_at(origin=[float(x) for x in eye],
                                                        target=[float(x) for x in target], up=[0, 1, 0]),
              "film": {"type": "hdrfilm", "width": s.resolution, "height": s.resolution, "rfilter": {"type": "box"}},
              "sampler": {"type": "independent"}}
    return scene, sensor


def render_decomp_data(s: DecompDataSettings, show_progress: bool = True) -> dict[str, np.ndarray]:
    """Every procedural scene → ``image`` (full render, linear) and its layers, (N, H, W, 3) each."""
    from foundation.scene import mitsuba_log_level

    out = {k: np.empty((s.count, s.resolution, s.resolution, 3), np.float32) for k in ("image", *LAYERS)}
    with progress_bar(total=s.count, desc="decomposition data", unit="scene", disable=not show_progress) as bar:
        for i in range(s.count):
            scene_d, sensor_d = procedural_scene(i, s)
            with mitsuba_log_level(mi.LogLevel.Error):
                scene = mi.load_dict(scene_d)
            img = np.array(mi.render(scene, sensor=mi.load_dict(sensor_d), spp=s.spp, seed=i), np.float32)
            rgb, layers = intrinsic_layers(img)
            out["image"][i] = rgb
            for k in LAYERS:
                out[k][i] = layers[k]
            bar.update(1)
    for k, a in out.items():
        if not np.isfinite(a).all():
            raise FloatingPointError(f"decomposition data: the {k} layer has non-finite values")
    return out


def load_decomp_data(path: str | Path, s: DecompDataSettings, show_progress: bool = True) -> dict[str, np.ndarray]:
    """:func:`render_decomp_data`, cached in ``path`` (an .npz keyed by the settings)."""
    return cached_arrays(Path(path), json.dumps(asdict(s), sort_keys=True),
                         lambda: render_decomp_data(s, show_progress))


# -- the network -----------------------------------------------------------------------------------------------------


class Decomposer(torch.nn.Module):
    """Image (B, 3, H, W) in [−1, 1] → (B, 12, H, W) condition-space layers [A ‖ I ‖ S ‖ N]."""

    def __init__(self, s: DecompSettings):
        super().__init__()
        from diffusers import UNet2DModel

        torch.manual_seed(s.seed)
        n = len(s.widths)
        self.multiple = s.multiple
        self.unet = UNet2DModel(in_channels=3, out_channels=DECOMP_CHANNELS, block_out_channels=s.widths,
                                down_block_types=("DownBlock2D",) * n, up_block_types=("UpBlock2D",) * n,
                                layers_per_block=1, norm_num_groups=8, add_attention=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.shape[-2] % self.multiple or x.shape[-1] % self.multiple:
            raise UsageError(f"image size {x.shape[-2]}×{x.shape[-1]} must divide by {self.multiple}")
        t = torch.zeros(x.shape[0], dtype=torch.long)
        return torch.tanh(self.unet(x, t, return_dict=False)[0])  # every condition channel lies in [−1, 1]


@dataclass
class DecompResult:
    settings: DecompSettings
    data: DecompDataSettings
    parameters: int
    training: TrainingSummary
    heldout_psnr: dict = field(default_factory=dict)  #: layer → PSNR on the held-out scenes, and "R"


class DecompStage(OptimizerStage, Stage):
    """Seeded crops of the procedural (image → layers) pairs; one Adam step on the L1 loss per step."""

    unit = "step"

    def __init__(self, data: dict[str, np.ndarray], ds: DecompDataSettings, s: DecompSettings):
        self.s, self.ds = s, ds
        self.name = "train decomposition network"
        n_train = ds.count - ds.n_test
        self.x = photo_to_model(data["image"][:n_train])
        self.y = local_condition({k: data[k][:n_train] for k in LAYERS})
        self.data_digest = _digest(data)
        self.rng = np.random.default_rng(s.seed)
        self.model = Decomposer(s)
        self.opt = torch.optim.AdamW(self.model.parameters(), lr=s.lr, weight_decay=0.0)

    def fingerprint(self) -> dict:
        return {"settings": self.s, "data_settings": self.ds, "data": self.data_digest}

    def step(self, it: int) -> StepResult:
        n, h, w = self.x.shape[:3]
        c = min(self.s.crop, h, w)
        xs, ys = [], []
        for i in self.rng.integers(0, n, self.s.batch):
            y0, x0 = int(self.rng.integers(0, h - c + 1)), int(self.rng.integers(0, w - c + 1))
            xs.append(self.x[i, y0:y0 + c, x0:x0 + c])
            ys.append(self.y[i, y0:y0 + c, x0:x0 + c])
        x = torch.from_numpy(np.ascontiguousarray(np.stack(xs).transpose(0, 3, 1, 2)))
        y = torch.from_numpy(np.ascontiguousarray(np.stack(ys).transpose(0, 3, 1, 2)))
        return self.backward(torch.mean(torch.abs(self.model(x) - y)))

    def finish(self, run: RunState) -> DecompResult:
        return DecompResult(self.s, self.ds, sum(p.numel() for p in self.model.parameters()), run.summary())


def _digest(data: dict[str, np.ndarray]) -> str:
    import hashlib

    h = hashlib.sha256()
    for k in sorted(data):
        h.update(k.encode())
        h.update(np.ascontiguousarray(data[k], np.float32).tobytes())
    return h.hexdigest()[:16]


@torch.no_grad()
def decompose(model: Decomposer, images: np.ndarray, batch: int = 8) -> dict[str, np.ndarray]:
    """Linear images (N, H, W, 3) → predicted layers (linear A, I, S; N), each (N, H, W, 3)."""
    images = np.asarray(images, np.float32)
    if images.ndim != 4 or images.shape[-1] != 3:
        raise UsageError(f"images must be (N, H, W, 3), got {images.shape}")
    if not np.isfinite(images).all():
        raise UsageError(f"images to decompose have {int((~np.isfinite(images)).sum())} NaN/Inf values")
    model.eval()
    outs = []
    for k in range(0, len(images), batch):
        x = torch.from_numpy(np.ascontiguousarray(photo_to_model(images[k:k + batch]).transpose(0, 3, 1, 2)))
        outs.append(model(x).permute(0, 2, 3, 1).numpy())
    return condition_to_layers(np.concatenate(outs))


def heldout_psnr(model: Decomposer | None, data: dict[str, np.ndarray], ds: DecompDataSettings) -> dict:
    """Mean PSNR over the held-out scenes per layer (A sRGB, I and S as x/(1+x), N as (n+1)/2: the [0, 1]
    spaces the network predicts) and of the recomposition A·I + S against the image (linear, clipped).

    ``model=None`` scores the trivial decomposition (A = the image, I = 1, S = 0, N = 0: "everything is
    albedo"), the floor a network has to clear."""
    test = slice(ds.count - ds.n_test, ds.count)
    if model is None:
        img = np.asarray(data["image"][test], np.float32)
        pred = {"albedo": np.clip(img, 0, 1), "irradiance": np.ones_like(img), "specular": np.zeros_like(img),
                "normal": np.zeros_like(img)}
    else:
        pred = decompose(model, data["image"][test])
    gt_c = local_condition({k: data[k][test] for k in LAYERS})
    pr_c = local_condition(pred)
    out = {}
    for j, (key, name) in enumerate(zip(("A", "I", "S", "N"), LAYERS)):
        out[key] = float(np.mean([psnr((p[..., 3 * j:3 * j + 3] + 1) / 2, (g[..., 3 * j:3 * j + 3] + 1) / 2)
                                  for p, g in zip(pr_c, gt_c)]))
    rec = recompose(pred)
    out["R"] = float(np.mean([psnr(r, im) for r, im in zip(rec, data["image"][test])]))
    return out


def train_decomposer(data: dict[str, np.ndarray], ds: DecompDataSettings, out: str | Path,
                     s: DecompSettings | None = None, show_progress: bool = True,
                     budget_steps: int | None = None) -> DecompResult | None:
    """Train on the procedural scenes but the held-out ones; ``OUT/checkpoint.npz`` (resumable), ``OUT/metrics.json``
    with the held-out PSNRs when done."""
    from foundation.files import write_json
    from foundation.records import to_json

    s = s or DecompSettings()
    stage, result = train_stage(lambda: DecompStage(data, ds, s), out, s, budget_steps, show_progress, metrics=False)
    if result is not None:
        with torch_threads(s.threads):
            result.heldout_psnr = heldout_psnr(stage.model, data, ds)
        write_json(Path(out) / "metrics.json", to_json(result))
    return result


def load_decomposer(run: str | Path) -> Decomposer:
    """The trained decomposition network of a run folder, eval mode."""
    return load_trained(run, DecompStage.__name__, "decomposition network", "", DecompSettings, Decomposer)[0]


def photographs(names: tuple[str, ...] = ("coffee", "chelsea", "motorcycle_left", "astronaut", "rocket"),
                size: int = 128, crops: int = 2, seed: int = 0) -> np.ndarray:
    """Square crops of scikit-image photographs (images with no 3D model), resized to ``size``², linear."""
    from PIL import Image

    rng = np.random.default_rng(seed)
    out = []
    for name in names:
        img = _photo(name)
        h, w = img.shape[:2]
        for _ in range(crops):
            side = int(rng.integers(min(h, w) // 2, min(h, w) + 1))
            y, x = int(rng.integers(0, h - side + 1)), int(rng.integers(0, w - side + 1))
            crop = img[y:y + side, x:x + side]
            out.append(np.stack([np.asarray(Image.fromarray(crop[..., k]).resize((size, size), Image.BOX))
                                 for k in range(3)], -1))
    return np.stack(out).astype(np.float32)


__all__ = ["DecompDataSettings", "DecompResult", "DecompSettings", "Decomposer", "decompose", "heldout_psnr",
           "load_decomp_data", "load_decomposer", "photographs", "procedural_scene", "render_decomp_data",
           "train_decomposer"]
