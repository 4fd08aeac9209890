"""A capture (:mod:`inverse.capture`) as the morph's input: its photos, pinhole cameras and coarse mesh behind the
interface the morph reads of a benchmark (``meta.cameras``, ``photo(i)``, ``coarse``, ``ground_truth``), so that one
stage fits both. What a capture does not give is left unknown: the light (fitted, :mod:`.photo_model`), the exposure of
each photo (fitted), the cameras' last bit of accuracy (refined), and a ground truth (metrics needing one are left
out unless the capture carries one)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from foundation.errors import UsageError

#: the width the morph fits a capture's photos at unless ``--resolution`` says otherwise (the photos' own when smaller)
CAPTURE_FIT_WIDTH = 128


@dataclass
class CaptureBenchSettings:
    photo_max_depth: int = 2  #: the photos are not renders: no path depth to match (the light estimate stays off)


@dataclass
class CaptureMorphMeta:
    """What the morph reads of a benchmark's record, for a capture."""

    kind: str
    resolution: int  #: the fitting width
    scene_size: float  #: the coarse mesh's largest extent (SfM units are arbitrary: every length follows it)
    cameras: list  #: :class:`inverse.capture.CaptureCamera`, in the capture's order
    train: list[int]
    test: list[int]
    names: list[str]
    fov: None = None  #: each camera has its own intrinsics
    hdri: None = None  #: the light is not known: it is fitted
    settings: CaptureBenchSettings = field(default_factory=CaptureBenchSettings)
    #: the cameras came from structure from motion or another tool, not from the renderer: refinement's "auto" is on
    estimated_cameras: bool = True


class CaptureBenchmark:
    """A capture folder as the morph's input. ``work``: a folder of this run for what the morph derives (the coarse
    mesh coloured from the training photos, the stored start); the capture folder itself is only read."""

    def __init__(self, capture, work: str | Path):
        from foundation.mesh import load_mesh_any, write_ply
        from inverse.capture import colour_from_photos

        self.capture = capture
        cm = capture.meta
        if capture.mesh is None:
            raise UsageError(f"{capture.path}: the capture has no coarse mesh to morph (import one with "
                             "`photoreal capture import --mesh`, or run `photoreal capture sfm`)")
        names = [c.name for c in cm.cameras]
        self.path = Path(work)
        self.path.mkdir(parents=True, exist_ok=True)
        v, f = load_mesh_any(capture.mesh)
        size = float(np.ptp(v, axis=0).max())
        width = min(CAPTURE_FIT_WIDTH, max(c.width for c in cm.cameras))
        self.meta = CaptureMorphMeta("capture", width, size, list(cm.cameras), [names.index(n) for n in cm.train],
                                     [names.index(n) for n in cm.test], names,
                                     estimated_cameras=not cm.source.get("exact_cameras", False))
        # the input's colours: the training photos projected onto it (the photogrammetry texture), the held-out never
        self.coarse = self.path / "coarse.ply"
        from foundation.files import file_digest

        key = self.path / "coarse.source"
        from foundation.files import array_key

        want = f"{file_digest(capture.mesh)} {array_key(*(capture.photo(n) for n in cm.train))[0][:16]}"
        if not (self.coarse.is_file() and key.is_file() and key.read_text() == want):
            write_ply(self.coarse, v, f, colour_from_photos(capture, v, f))
            key.write_text(want)
        self._photos: dict[tuple[int, int], np.ndarray] = {}
        #: where the masks come from: "capture" (its own), "backdrop" (:meth:`derive_backdrop`), "none"
        self.mask_source = "capture" if cm.masks else "none"
        self.backdrop = None  #: the :class:`~inverse.capture.backdrop.BackdropDecision`, once asked
        self._backdrop: dict[int, np.ndarray] = {}

    @property
    def ground_truth(self) -> Path | None:
        return self.capture.truth

    @property
    def has_masks(self) -> bool:
        return self.mask_source != "none"

    def derive_backdrop(self, folder: Path | None = None):
        """For a capture without masks: masks from a uniform backdrop where the training photos show one
        (:mod:`inverse.capture.backdrop`), written as ``folder/NAME.png`` to look at. Returns the decision."""
        from inverse.capture import backdrop_mask, decide_backdrop

        if self.mask_source == "capture":
            return None
        if self.backdrop is None:  # once per input: the selection's trials ask again
            self.backdrop = decide_backdrop(self.photo(i) for i in self.meta.train)
            if self.backdrop.uniform:
                self.mask_source = "backdrop"
                self._backdrop = {i: backdrop_mask(self.photo(i)) for i in range(len(self.meta.names))}
        if folder is not None and self._backdrop:
            from foundation import imageio

            folder.mkdir(parents=True, exist_ok=True)
            for i, (m, unsure) in self._backdrop.items():  # white: object, grey: unsure, black: backdrop
                imageio.write_png(folder / f"{self.meta.names[i]}.png",
                                  np.repeat(np.where(unsure, 0.5, m)[..., None], 3, -1).astype(np.float32),
                                  linear=False)
        return self.backdrop

    def mask(self, i: int) -> np.ndarray:
        """(H, W) bool mask of photo ``i`` (the capture's or the backdrop's)."""
        return self._backdrop[int(i)][0] if self.mask_source == "backdrop" else \
            self.capture.mask(self.meta.names[int(i)])

    def mask_weights_at(self, res: int, views) -> dict[int, np.ndarray]:
        """Where derived masks are unsure (:func:`~inverse.capture.backdrop.backdrop_mask`): per view at ``res``
        across, the share of each pixel they are sure of (float32 in [0, 1]); empty where every pixel counts."""
        if self.mask_source != "backdrop":
            return {}
        return {int(i): self._share_at(~self._backdrop[int(i)][1], i, res) for i in views}

    def _share_at(self, m: np.ndarray, i: int, res: int) -> np.ndarray:
        """Bool image ``m`` of photo ``i`` area-resampled to ``res`` across: the share of each pixel that is True."""
        from inverse.capture import area_resize

        cam = self.meta.cameras[int(i)].scaled(res)
        return np.clip(area_resize(m.astype(np.float32)[..., None], cam.width, cam.height)[..., 0], 0.0, 1.0)

    def photo(self, i: int) -> np.ndarray:
        """Photo ``i`` at the capture's resolution, linear RGB (H, W, 3)."""
        return self.capture.photo(self.meta.names[int(i)])

    def photo_at(self, i: int, res: int) -> np.ndarray:
        """Photo ``i`` area-resampled to ``res`` pixels across (its camera :meth:`CaptureCamera.scaled` to match)."""
        from inverse.capture import area_resize

        if (i, res) not in self._photos:
            cam = self.meta.cameras[int(i)].scaled(res)
            self._photos[(i, res)] = np.ascontiguousarray(area_resize(self.photo(i), cam.width, cam.height))
        return self._photos[(i, res)]

    def masks_at(self, res: int, views) -> dict[int, np.ndarray]:
        """The capture's masks of ``views`` at ``res`` pixels across, float32 coverage in [0, 1] (empty without)."""
        if not self.has_masks:
            return {}
        return {int(i): self._share_at(self.mask(i), i, res) for i in views}


def is_capture(bench) -> bool:
    return isinstance(bench, CaptureBenchmark)


def load_morph_input(path: str | Path, work: str | Path):
    """A morph benchmark folder (``morph_benchmark.json``) or a capture folder (``capture.json``) as the morph's
    input; anything else is named."""
    from inverse.capture import MARKER as CAPTURE_MARKER, load_capture

    from .benchmark import MARKER, load_morph_benchmark

    path = Path(path)
    if (path / CAPTURE_MARKER).is_file():
        return CaptureBenchmark(load_capture(path), work)
    if (path / MARKER).is_file() or not path.exists():
        return load_morph_benchmark(path)
    raise UsageError(f"{path}: neither a morph benchmark ({MARKER}) nor a capture ({CAPTURE_MARKER})")


def evaluate_capture_morph(stage, v_in, f_in, c_in, v_out, f_out, c_out, start=None):
    """Held-out photos of a capture against renders of the input and the morphed mesh (no truth: no Chamfer).

    Both are rendered at the held-out photos' imported cameras, at the fitting width, with the fitted exposure (a
    held-out photo's gain from its two nearest fitted cameras) and the fitted environment as the background (and, for
    a 'lit' result, the light, with the fitted flash at the camera where the photo's EXIF says it fired). The input
    is scored as photogrammetry gives it: its colours from the training photos, unlit. Renders: ``path`` at depth 2,
    32 spp, seed = view index. The scores are over the whole photo, and again over the object's region: the pixels
    either mesh covers at least half of (:func:`object_region`), where the two differ at all (the background is the
    same environment for both). Spikes and inverted triangles compare the result with the mesh the optimisation
    started from (``start``), as for a benchmark."""
    from foundation.features import perceptual_distance
    from foundation.metrics import ImageMetrics, flip, image_metrics, masked_psnr

    from . import photo_model as pm
    from .evaluate import MorphEvaluation, heldout_renders, start_spikes

    meta = stage.bench.meta
    light = pm.fitted_envmap(stage.env_values) if stage.env_values is not None else meta.hdri
    meshes = {"input": (v_in, f_in, np.clip(c_in, 0, None), "unlit"),
              "morphed": (v_out, f_out, np.clip(c_out, 0, None), stage.s.mode)}
    renders = heldout_renders(stage.bench, meshes, light, stage.res, stage.out, max_depth=2, gain=stage.gain_of,
                              flash=stage.flash_intensity if stage.flash else None,
                              flash_weight=stage.flash_weight_now())
    mean = {n: ImageMetrics.mean([image_metrics(img, ref) for img, ref in pairs]) for n, pairs in renders.items()}
    perceptual = {n: [float(perceptual_distance(img[None], ref[None])[0]) for img, ref in pairs]
                  for n, pairs in renders.items()}
    region = object_region(stage.bench, [(v_in, f_in), (v_out, f_out)], stage.res, stage.out)
    seen = [k for k, m in enumerate(region) if m.any()]  # a view neither mesh reaches has no region to score
    obj = {n: {"psnr": float(np.mean([masked_psnr(*pairs[k], region[k]) for k in seen])) if seen else float("nan"),
               "flip": float(np.mean([flip(np.clip(pairs[k][0], 0, 1), np.clip(pairs[k][1], 0, 1), mask=region[k])
                                      for k in seen])) if seen else float("nan")}
           for n, pairs in renders.items()}
    v0, f0 = start if start is not None else (v_in, f_in)
    sp = start_spikes(v0, f0, v_out, f_out)
    nan = float("nan")
    return MorphEvaluation(
        chamfer_input=nan, chamfer_morphed=nan, chamfer_reduction=nan, normal_consistency_input=nan,
        normal_consistency_morphed=nan, psnr_heldout_input=mean["input"].psnr, psnr_heldout_morphed=mean["morphed"].psnr,
        heldout_input=mean["input"], heldout_morphed=mean["morphed"], spike_vertices=sp["spike_vertices"],
        inverted_triangles=sp["inverted_triangles"], spikes=sp["spikes"], far_moved_vertices=sp["far_moved_vertices"],
        facing_against_truth=-1, facing_against_truth_input=-1, scene_size=meta.scene_size,
        perceptual_heldout_input=float(np.mean(perceptual["input"])),
        perceptual_heldout_morphed=float(np.mean(perceptual["morphed"])),
        object_share=float(np.mean([m.mean() for m in region])),
        psnr_object_input=obj["input"]["psnr"], psnr_object_morphed=obj["morphed"]["psnr"],
        flip_object_input=obj["input"]["flip"], flip_object_morphed=obj["morphed"]["flip"])


def object_region(bench, meshes: list[tuple], res: int, work: Path, spp: int = 16) -> list[np.ndarray]:
    """Per held-out photo, the pixels (bool, its camera at ``res`` across) at least half covered by any of ``meshes``
    ((v, f) each): the mesh black under a white sky (:func:`~inverse.morph.scene.mask_scene`), ``spp`` samples."""
    import mitsuba as mi

    from foundation.mesh import write_ply

    from .cameras import sensor_dict
    from .scene import mask_scene

    meta = bench.meta
    cover = None
    for k, (v, f) in enumerate(meshes):
        ply = work / f".region_{k}.ply"
        write_ply(ply, v, f)
        scene = mask_scene(ply, integrator={"type": "direct"})
        got = [1.0 - np.array(mi.render(scene, sensor=mi.load_dict(sensor_dict(meta.cameras[i], res, meta.fov)),
                                        spp=spp, seed=int(i)))[..., 0] for i in meta.test]
        cover = got if cover is None else [np.maximum(a, b) for a, b in zip(cover, got)]
        del scene
        ply.unlink(missing_ok=True)
    return [c >= 0.5 for c in cover]
