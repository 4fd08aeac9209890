"""What another stage renders of a morph result: the coarse and the morphed mesh at every camera of a benchmark,
beside its photos, cached in the morph folder (the GAN's paired renders, the diffusion renderer's G-buffers)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Callable

import numpy as np

from foundation.errors import UsageError
from foundation.files import cached_arrays, file_digest

from .benchmark import MorphBenchmark


def morph_views(bench: MorphBenchmark, morph_dir: str | Path, cache: str, settings: dict,
                render: Callable[[dict[str, Path], list[int]], dict[str, np.ndarray]]) -> tuple[np.ndarray, dict]:
    """The benchmark's photos (N, H, W, 3) and ``render({"coarse": ply, "morphed": ply}, ids)`` at every camera,
    cached in ``morph_dir/cache`` under the two meshes' digests and ``settings`` (another mesh or setting renders
    again); a morph folder without ``morphed.ply`` is refused by name."""
    morph_dir = Path(morph_dir)
    morphed = morph_dir / "morphed.ply"
    if not morphed.is_file():
        raise UsageError(f"{morphed}: no morphed mesh (run `photoreal morph run` first)")
    n = len(bench.meta.cameras)
    key = json.dumps({"coarse": file_digest(bench.coarse), "morphed": file_digest(morphed), **settings},
                     sort_keys=True)
    arrays = cached_arrays(morph_dir / cache, key,
                           lambda: render({"coarse": bench.coarse, "morphed": morphed}, list(range(n))))
    photos = np.stack([bench.photo(i) for i in range(n)]).astype(np.float32)
    return photos, arrays
