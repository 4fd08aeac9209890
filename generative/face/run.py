"""`photoreal face train-models`: data, completion backbone, decomposition variants and super-resolution in one
resumable run folder.

::

    RUN/run.json                 the settings (a rerun with other settings is refused)
    RUN/data/                    the instances (face_data), built on the pool
    RUN/completion/              the completion/homogenisation diffusion model = the shared backbone
    RUN/completion_albedo.npz    its albedo for every training instance (the decomposition's input), keyed by the
                                 backbone's checkpoint digest
    RUN/decomposition_<variant>/ LoRA + cross-intrinsic attention (and the ablations, when asked for)
    RUN/superres/                the 2× upscaler

Kill it anywhere and run the same command again: finished parts are kept, a training stage resumes from its
checkpoint.
"""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

import numpy as np

from foundation.errors import UsageError
from foundation.files import holds_files, read_json, write_json

from .data import build_face_dataset, load_face_dataset
from .evaluate import LearnedModels
from .completion import complete, load_completion, train_completion
from .decomposition import DecompSettings, backbone_id, load_decomposer, train_decomposer
from .superres import load_superres, train_superres
from .settings import FaceModelsSettings

RUN_FORMAT = "photoreal face models v1"


def _claim(out: Path, s: FaceModelsSettings) -> None:
    from foundation.records import to_json

    want = {"format": RUN_FORMAT, "settings": json.loads(json.dumps(to_json(s)))}
    marker = out / "run.json"
    if marker.is_file():
        have = read_json(marker, "face models run")
        if have != want:
            diff = [k for k in want["settings"] if want["settings"][k] != have.get("settings", {}).get(k)]
            raise UsageError(f"{marker}: a run made with other settings ({', '.join(diff) or 'format'}); "
                             "use a fresh --out folder or the same settings")
    elif holds_files(out):
        raise UsageError(f"{out}: exists and is not a face models run; give an empty or new folder")
    out.mkdir(parents=True, exist_ok=True)
    write_json(marker, want)


def completion_albedo(run: Path, show_progress: bool = False) -> np.ndarray:
    """The backbone's albedo of every training instance, cached beside it (recomputed when the backbone changes)."""
    from foundation.files import atomic_path

    cache = run / "completion_albedo.npz"
    key = backbone_id(run / "completion")
    if cache.is_file():
        with np.load(cache) as z:
            if str(z["key"]) == key:
                return z["albedo"]
    model, cs = load_completion(run / "completion")
    train = load_face_dataset(run / "data", "train")
    albedo = complete(model, cs, train, seed=0, samples=1)
    with atomic_path(cache, suffix=".npz") as tmp:
        np.savez(tmp, albedo=albedo, key=np.array(key))
    return albedo


def train_face_models(out: str | Path, s: FaceModelsSettings | None = None, pool=None, progress: bool = True) -> dict:
    """Build the data and train every model of ``s`` in ``out`` (resumable). Returns the stages' summaries."""
    from foundation.records import to_json

    s = s or FaceModelsSettings()
    out = Path(out)
    _claim(out, s)
    build_face_dataset(out / "data", s.data, pool, progress)
    train = load_face_dataset(out / "data", "train")
    summary = {"completion": train_completion(train, out / "completion", s.completion, show_progress=progress)}
    albedo = completion_albedo(out, progress)
    for v in s.variants:
        ds = DecompSettings(**{**asdict(s.decomposition), "variant": v})
        summary[f"decomposition_{v}"] = train_decomposer(train, albedo, out / "completion", out / f"decomposition_{v}",
                                                         ds, show_progress=progress)
    if s.data.uv_res == 2 * s.completion.res:
        summary["superres"] = train_superres(train, out / "superres", s.superres, show_progress=progress)
    result = {k: json.loads(json.dumps(to_json(v))) for k, v in summary.items()}
    write_json(out / "metrics.json", result)
    return result


def load_face_models(run: str | Path, variant: str | None = None) -> LearnedModels:
    """The models of a finished run (``variant``: a decomposition variant trained there; default the run's first)."""
    run = Path(run)
    marker = run / "run.json"
    if not marker.is_file():
        raise UsageError(f"{run}: not a face models run (run.json missing; train one with `photoreal face train-models`)")
    settings = read_json(marker, "face models run").get("settings", {})
    variants = settings.get("variants") or ["cross_attention"]
    variant = variant or variants[0]
    if variant not in variants:
        raise UsageError(f"{run}: has no {variant!r} decomposition (it has {', '.join(variants)})")
    model, cs = load_completion(run / "completion")
    dec = load_decomposer(run / f"decomposition_{variant}", run / "completion")
    sr = load_superres(run / "superres") if (run / "superres" / "checkpoint.npz").is_file() else None
    # runs made before the template layout existed were in the scans' own layout
    return LearnedModels(model, cs, dec, sr, layout=settings.get("data", {}).get("layout", "scan"))


def photo_maps_fn(models: LearnedModels):
    """The learned stages as ``inverse.face.photo_to_face``'s ``maps_fn``: (lit texture, visibility weight, template
    geometry, the baseline's albedo) → maps at the texture's resolution. The template's frame is the photo's image
    space (side +x, up +y, front +z); the albedo is brought to the baseline's level on the seen texels (the level the
    fitted lights explain the photo with)."""
    from .data import FaceSet
    from .evaluate import learned_maps

    if models.layout != "template":
        # from-photo unwraps into the template's layout: maps learned in another read the wrong texels
        raise UsageError(f"these face models were trained in the {models.layout!r} UV layout; photos are unwrapped "
                         "into the face template's: train with `photoreal face train-models --layout template`")

    def fn(tex: np.ndarray, weight: np.ndarray, geo, baseline: np.ndarray) -> dict[str, np.ndarray]:
        mask = geo.mask.astype(bool)
        seen = (weight > 0.3) & mask
        p = geo.position[mask]
        centre = 0.5 * (p.min(0) + p.max(0))
        radius = 0.5 * float(np.linalg.norm(p.max(0) - p.min(0)))
        pos_f = np.where(mask[..., None], (geo.position - centre) / radius, 0.0).astype(np.float32)
        nrm_f = np.where(mask[..., None], geo.normal, 0.0).astype(np.float32)
        h, w = mask.shape
        zeros = lambda c: np.zeros((1, h, w, c), np.float32)  # noqa: E731
        d = FaceSet(["photo"], [{"name": "photo"}], tex[None].astype(np.float32), seen[None], mask[None], pos_f[None],
                    nrm_f[None], baseline[None].astype(np.float32),
                    {"albedo": zeros(3), "normal": zeros(3), "roughness": zeros(1), "specular": zeros(1),
                     "displacement": zeros(1)},
                    {"position": geo.position[None], "normal_geo": geo.normal[None], "tangent": geo.tangent[None],
                     "bitangent_sign": geo.bitangent_sign[None]})
        maps = {k: v[0] for k, v in learned_maps(d, models, "full").items()}
        ref = seen if seen.any() else mask
        maps["albedo"] = np.clip(maps["albedo"] * float(baseline[ref].mean()) / max(float(maps["albedo"][ref].mean()), 1e-6),
                                 0.0, 1.0)
        return maps

    return fn


__all__ = ["FaceModelsSettings", "completion_albedo", "load_face_models", "photo_maps_fn", "train_face_models"]
