"""`photoreal diffrender render`: diffusion renders of a benchmark's views or of a scene's sensors. The model and
torch load when a render starts, so that the command's flags (these functions' parameters) come without them."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from foundation import validate

from .settings import LAYERS, SOURCES, SampleSettings

if TYPE_CHECKING:
    from inverse.morph import MorphBenchmark


@dataclass
class DiffRenderOutput:
    """What ``photoreal diffrender render`` wrote and, on a benchmark, how close it came to the photos."""

    files: list[str]
    seconds_per_image: float
    views: list[int] = field(default_factory=list)
    source: str = ""
    diffusion: dict | None = None  #: mean held-out metrics of the diffusion renders (benchmark only)
    pbr: dict | None = None  #: the same for the PBR recomposition R = A·I + S of the same G-buffers


def render_benchmark(run: str | Path, bench: MorphBenchmark, morph_dir: str | Path, out_dir: str | Path,
                     source: str = "morphed", views: str = "test", sample_s: SampleSettings | None = None,
                     show_progress: bool = True) -> DiffRenderOutput:
    """Diffusion renders of a benchmark's views from its ``source`` mesh's G-buffers, with metrics vs the photos."""
    from foundation.metrics import ImageMetrics, image_metrics
    from foundation.records import to_json

    from .renderer import load_diffrender, load_intrinsic_views, render_views, write_views

    validate.one_of("source", source, SOURCES)
    validate.one_of("views", views, ("test", "all"))
    model, s = load_diffrender(run)
    data = load_intrinsic_views(bench, morph_dir, show_progress=show_progress)
    ids = list(data.test) if views == "test" else list(range(len(data.photos)))
    layers = {k: a[ids] for k, a in data.layers[source].items()}
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    images, sec = render_views(model, s, layers, sample_s, show_progress)
    files = write_views(out_dir, [f"view{i:02d}" for i in ids], images, layers)

    def mean(pred):
        return to_json(ImageMetrics.mean([image_metrics(p, r) for p, r in zip(pred, data.photos[ids])]))

    return DiffRenderOutput(files, sec, ids, source, mean(images), mean(data.recomposed(source)[ids]))


def render_scene_file(run: str | Path, scene_path: str | Path, out_dir: str | Path, spp: int = 32,
                      sample_s: SampleSettings | None = None, show_progress: bool = True) -> DiffRenderOutput:
    """G-buffers of every sensor of a Mitsuba scene (``intrinsic`` integrator) → diffusion renders."""
    from foundation.scene import RenderSettings, load_scene, render_scene, sensor_count
    from generative.diffusion import check_size

    from .renderer import load_diffrender, render_views, write_views

    model, s = load_diffrender(run)
    n = sensor_count(scene_path)
    layers: dict[str, list] = {k: [] for k in LAYERS}
    for i in range(n):
        rs = RenderSettings(spp=spp, aovs=True, sensor=i)
        _, aovs = render_scene(load_scene(scene_path, rs), rs, show_progress, label=f"G-buffers sensor {i}")
        for k in LAYERS:
            layers[k].append(aovs[k])
    stacked = {k: np.stack(v) for k, v in layers.items()}
    check_size(s.model_config(), *stacked["albedo"].shape[1:3])
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    images, sec = render_views(model, s, stacked, sample_s, show_progress)
    stem = Path(scene_path).stem
    return DiffRenderOutput(write_views(out_dir, [f"{stem}_sensor{i}" for i in range(n)], images, stacked), sec,
                            list(range(n)))
