"""Per-vertex morphing of a coarse mesh against multi-view photos (REAL-DIBS §4.3, eqs. 4.1–4.3).

Notation (thesis §4.3):

=============  ===========  ===============================================
code           thesis       meaning
=============  ===========  ===============================================
``v``          V            vertex positions (N×3)
``c``          C            vertex colours (N×3)
``views``      B            the batch of camera views of one step (≥ 3)
``loss``       L (eq. 4.3)  Σ_{b∈B} mean |R(V, C; cam_b) − I_b|  (L1)
``u``          —            large-steps variable u = (I + λL)V (Nicolet et al. 2021)
=============  ===========  ===============================================

Gradients of silhouettes come from Mitsuba's projective integrator
(``direct_projective``). Two appearance modes: ``unlit`` (the mesh emits its
vertex colour, as in the thesis) and ``lit`` (diffuse vertex colour under
the benchmark's HDR environment). Stability: large steps (``mi.ad.LargeSteps``
with cholespy; plain per-vertex Adam is available for comparison), optional
remeshing between stages (pymeshlab). Checkpoints, resume, budgets and the NaN/Inf policy are
the shared loop's (:mod:`foundation.loop`).

Beyond the thesis: an edge-preserving planarity prior (``planarity_prior``, a
Geman–McClure penalty on dihedral angles) for man-made scenes, switched on when
the input has a dominant plane (``dominant_plane_fraction``). At 128² with
vertex colours the image loss alone does not pin the bumps of large flat areas
(started at the village's ground truth it drifts from Chamfer 0.013 to 0.037).
Where no plane switches it on, a mild weight is one more candidate of the λ
selection (``planarity_select``): the validation photos decide. A colour prior (``colour_prior``, mean colour
step over edges) keeps the albedo piecewise smooth where the input's colours are smooth, so that the photos'
shading moves the geometry instead of being painted into the vertex colours.
"""

from __future__ import annotations

import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

import mi_plugins  # noqa: F401
import drjit as dr
import mitsuba as mi
from mi_plugins.arrays import aligned

from foundation import imageio
from foundation.errors import UsageError
from foundation.files import array_key, file_digest
from foundation.loop import (DrJitStage, LoopSettings, RunState, StepResult, all_finite, rng_state, run_loop,
                             set_rng_state)
from foundation.mesh import face_normals, load_mesh_any, read_ply_colours, unique_edges, write_ply
from foundation.mesh_metrics import chamfer
from foundation.records import from_json, to_json
from foundation.optim_state import load_optimizer_state, optimizer_state
from foundation.quantile_adam import QuantileAdam
from foundation.scene import mitsuba_log_level

from . import photo_model as pm
from .benchmark import MorphBenchmark, sensor_dict
from .capture_input import evaluate_capture_morph, is_capture
from .evaluate import evaluate_morph
from .prior import colour_prior, dihedral_pairs, dominant_plane_fraction, planarity_prior
from .mesh_edit import (iron_border_turns, iron_spikes, remesh,
                        repair_flips, undo_flips, unfold_pleats)
from .scene import (camera_centre, flash_distance, flash_sampling_weight, inward_thickness, mask_integrator,
                    mask_scene, morph_scene, photo_l1, photo_masks, photo_saturation, photo_tensors,
                    projective_integrator, render_views, set_flash, upsample_bilinear, views_seeing)

from .results import (ColourPriorDecision, MorphResult, PhotoFit,
                      PlanarityDecision, TracePoint)
from .settings import (ESTIMATE_DRAW_STRIDE, PLAIN_RUN_INDIRECT_SPP, MorphSettings)


def start_mesh(bench: MorphBenchmark, s: MorphSettings) -> tuple[tuple, tuple]:
    """The coarse input (v, f, c) and the mesh the optimisation starts from (remeshed unless disabled)."""
    v_in, f_in, c_in = read_ply_colours(bench.coarse)
    target = s.target_vertices or (s.min_vertices if s.min_vertices and len(v_in) < s.min_vertices else None)
    if s.remesh_input or target:
        return (v_in, f_in, c_in), stored_remesh(bench, (v_in, f_in, c_in), target)
    return (v_in, f_in, c_in), (v_in, f_in, c_in)


def stored_remesh_path(bench: MorphBenchmark, target: int | None) -> Path:
    """Where :func:`stored_remesh` keeps the start: named by the target and the coarse input's content."""
    return bench.path / f"start_remesh_{target or 'same'}_{file_digest(bench.coarse, 12)}.ply"


def stored_remesh(bench: MorphBenchmark, mesh: tuple, target: int | None) -> tuple:
    """The isotropic remesh of the benchmark's coarse input (``mesh``), made once and kept in the benchmark folder.

    pymeshlab's remesh of byte-identical input has differed between processes (docs/results/morph.md, "run-to-run
    differences"), so the first run on a benchmark stores its start and every later one — λ candidates,
    resumes, suite workers, later invocations — reads that file. The first writer wins (a hard link, which fails
    when the name exists), and the writer too reads the file back: float32 on disk, the same values for all. A
    damaged file is replaced; a read-only benchmark folder remeshes in every process, as before.
    """
    import os
    import tempfile

    from foundation.mesh import MeshError

    path = stored_remesh_path(bench, target)
    try:
        return read_ply_colours(path)
    except MeshError:
        pass  # absent or damaged
    v, f, c = remesh(*mesh, target)
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".ply", dir=path.parent)
        os.close(fd)
        try:
            write_ply(tmp, v, f, c)
            if path.exists():  # damaged (it did not read): replace it
                os.replace(tmp, path)
            else:
                try:
                    os.link(tmp, path)
                except FileExistsError:  # another process stored its start first: use that one
                    pass
        finally:
            if os.path.exists(tmp):
                os.unlink(tmp)
    except OSError:
        return v, f, c
    return read_ply_colours(path)


def decide_planarity(v: np.ndarray, f: np.ndarray, s: MorphSettings) -> PlanarityDecision:
    if s.planarity_weight is not None:
        return PlanarityDecision(float(s.planarity_weight), False, None)
    frac = dominant_plane_fraction(v, f, seed=s.seed)
    return PlanarityDecision(s.planarity_auto_weight if frac >= s.planarity_auto_threshold else 0.0, True, frac)


def decide_colour_prior(c: np.ndarray, f: np.ndarray, s: MorphSettings) -> ColourPriorDecision:
    """The colour prior's weight: fixed, or from the coarse input's colours (``c`` per vertex, triangles ``f``)."""
    if s.colour_prior_weight is not None:
        return ColourPriorDecision(float(s.colour_prior_weight), False, None)
    e = unique_edges(f)
    step = float(np.mean(np.linalg.norm(np.asarray(c, np.float64)[e[:, 0]] - c[e[:, 1]], axis=1))) if len(e) else 0.0
    return ColourPriorDecision(s.colour_prior_auto_weight if step < s.colour_prior_auto_threshold else 0.0, True, step)


class MorphStage(DrJitStage):
    """Eq. 4.3 (L1 over a batch of views) + the planarity prior, large-steps Adam on (u, C)."""

    unit = "it"

    def __init__(self, bench: MorphBenchmark, out: Path, s: MorphSettings):
        t0 = time.perf_counter()
        self.bench, self.out, self.s = bench, out, s
        self.name = f"morph {bench.meta.kind}"
        meta = bench.meta
        self.res = s.resolution or meta.resolution
        self.mask_res = self.res // s.mask_downsample
        if s.mask_weight > 0 and self.mask_res < 8:
            raise UsageError(f"mask_downsample: {s.mask_downsample} leaves {self.mask_res}² masks of the {self.res}² "
                             "photos (at least 8² are needed)")
        self.size = meta.scene_size
        self.capture = is_capture(bench)
        #: what a real photo adds (:mod:`.photo_model`): refined cameras, a gain per photo, a fitted environment
        self.refine = s.refine_cameras == "on" or (s.refine_cameras == "auto" and
                                                   bool(getattr(meta, "estimated_cameras", False)))
        self.exposure = s.exposure == "on" or (s.exposure == "auto" and self.capture)
        self.env_fit = meta.hdri is None
        #: the photos lit by a flash (a light at the camera, :attr:`MorphSettings.flash`): 'lit' runs whose light is
        #: fitted; the flash is modelled where a training photo is among them
        self.flash_photos = flash_photos(meta.cameras, s.flash) if s.mode == "lit" and self.env_fit else set()
        self.flash = any(i in self.flash_photos for i in meta.train)
        self.per_view = self.refine or self.exposure or self.env_fit
        if self.env_fit and s.indirect_every:
            raise UsageError("indirect_every: the light estimate needs a known light (a benchmark's HDRI); a "
                             "capture's light is fitted")
        #: a capture without masks of its own: masks from a uniform backdrop, where its photos show one
        self.backdrop = bench.derive_backdrop(out / "backdrop_masks") \
            if self.capture and s.mask_weight > 0 and s.backdrop == "auto" else None
        self.mask_weight = s.mask_weight if not self.capture or bench.has_masks else 0.0
        self.photos = photo_tensors(bench, self.res)
        self.saturation_level, self.photo_hot = photo_saturation(self.photos, meta.train, s.saturation)
        (self.v_in, self.f_in, self.c_in), (v0, f0, c0) = start_mesh(bench, s)
        self.v_start, self.f_start = v0, f0
        self.digest = file_digest(bench.coarse)
        self.photos_digest = photos_digest(bench)
        self.rng = np.random.default_rng(s.seed)
        self.planarity = decide_planarity(v0, f0, s)
        self.colour_prior = decide_colour_prior(self.c_in, self.f_in, s)
        self.sigma = 1.0 - float(np.cos(np.radians(s.planarity_angle)))
        self.lr_pos = s.lr * self.size / 10.0 if s.parameterisation == "large_steps" else s.lr * self.size / 100.0
        self.work_ply = out / ".morph_work.ply"
        self.val_ids = validation_split(meta.train, min(s.validation_views,
                                                        int(s.validation_fraction * len(meta.train))))
        self.train_ids = [i for i in meta.train if i not in self.val_ids]
        self.train_index = {int(i): k for k, i in enumerate(self.train_ids)}
        self.centres = np.array([camera_centre(c) for c in meta.cameras], np.float64)
        #: a photo not fitted takes the mean gain of these fitted neighbours (never its own pixels)
        self.gain_from = pm.nearest_fitted(self.centres, self.train_ids)
        #: the photos' EXIF exposures (log; NaN: not known): a held-out photo's gain follows its own exposure
        self.log_exposure = np.array([np.log(e) if (e := getattr(c, "exposure", None)) else np.nan
                                      for c in meta.cameras], np.float64)
        n = len(self.train_ids)
        self.cam_rot, self.cam_shift = np.zeros((n, 3)), np.zeros((n, 3))
        self.log_gain = np.zeros((n, 3))
        #: the shared focal length's log-scale, where refined (capture cameras: their axes are known)
        self.focal = self.refine and s.refine_focal and all(hasattr(c, "matrix") for c in meta.cameras)
        self.log_focal = 0.0
        self.env_values = self._initial_env() if self.env_fit else None
        #: the flash's RGB log-intensity (W/sr in the capture's length unit)
        self.flash_r = flash_distance(self.centres[self.train_ids], v0) if self.flash else 1.0
        self.log_flash = np.full(3, np.log(initial_flash(self.flash_r))) if self.flash else np.zeros(3)
        #: the flash's sampling weight (the environment's is 1), set from the fitted lights at every check
        self.flash_weight = flash_sampling_weight(np.exp(self.log_flash), self.env_values, self.flash_r) \
            if self.flash else 1.0
        self.trace: list[TracePoint] = []
        self.snapshots: list[np.ndarray] = []  #: vertices at the trace points (same topology only)
        self.validation_seconds = 0.0
        self.anneal: tuple[int, int, float] | None = None  #: (start step, length, lr factor then) once on a plateau
        self.lam = s.lambda_start if s.lambda_start and s.parameterisation == "large_steps" else s.lambda_
        self.indirect: dict[int, mi.TensorXf] = {}
        #: one count for every part of the gradient: the renders are those of runs before ``boundary_spp`` existed
        self.shared_spp = s.boundary_spp is None or s.boundary_spp == s.spp
        #: the photos' masks as the mask scene renders them (1 − coverage, RGB), training views only
        self.sky = {i: mi.TensorXf(aligned(np.repeat((1.0 - m)[..., None], 3, axis=-1)))
                    for i, m in photo_masks(bench, self.mask_res, self.train_ids).items()} if self.mask_weight > 0 else {}
        #: where derived masks are unsure of a pixel, the silhouette loss's weight there (none: every pixel counts)
        self.sky_weight = {i: mi.TensorXf(aligned(np.repeat(w[..., None], 3, axis=-1)))
                           for i, w in bench.mask_weights_at(self.mask_res, self.train_ids).items()} \
            if self.mask_weight > 0 and hasattr(bench, "mask_weights_at") else {}
        self._build(v0, v0, f0, c0)
        if self.planarity.weight and dr.width(self.pairs) == 0:  # no manifold edge (an unwelded soup)
            self.planarity.weight = 0.0
        self.setup_seconds = time.perf_counter() - t0

    # -- set-up -------------------------------------------------------------------------------------------------

    def _build(self, v: np.ndarray, v_ref: np.ndarray, f: np.ndarray, c: np.ndarray) -> None:
        """Scene, large-steps operator (from ``v_ref``: the same on resume) and optimiser for topology ``f``."""
        s = self.s
        self.faces, self.v_ref = f, v_ref
        write_ply(self.work_ply, v, f, c)
        light = pm.fitted_envmap(self.env_values) if self.env_fit else self.bench.meta.hdri
        self.scene = morph_scene(self.work_ply, s.mode, light,
                                 integrator=None if self.shared_spp else projective_integrator(s.spp, s.boundary_spp),
                                 flash=self.flash)
        self.params = mi.traverse(self.scene)
        if self.mask_weight > 0:  # the same mesh file: both scenes get the step's positions
            self.mask_scene = mask_scene(self.work_ply, integrator=mask_integrator(None if self.shared_spp else
                                                                                   s.boundary_spp))
            self.mask_params = mi.traverse(self.mask_scene)
        self.f_mi = mi.UInt32(aligned(f, np.uint32).ravel())
        self.pairs = mi.UInt32(aligned(self._prior_pairs(v_ref, f), np.uint32).ravel())
        self.edges = mi.UInt32(aligned(unique_edges(f), np.uint32).ravel())
        self.n_start = face_normals(v_ref, f) if s.forbid_flips else None
        if s.parameterisation == "large_steps":
            self.ls = mi.ad.LargeSteps(mi.Float(aligned(v_ref).ravel()), self.f_mi, self.lam)
            self.opt = QuantileAdam(lr=self.lr_pos, quantile=s.adam_quantile)  # 1: mi.ad.Adam(uniform=True)
            self.key = "u"
            self.opt["u"] = self.ls.to_differential(mi.Float(aligned(v).ravel()))
        else:
            self.ls = None
            self.opt = mi.ad.Adam(lr=self.lr_pos)
            self.key = "v"
            self.opt["v"] = mi.Float(aligned(v).ravel())
        self.ls_c = mi.ad.LargeSteps(mi.Float(aligned(v_ref).ravel()), self.f_mi, s.colour_lambda) \
            if s.colour_lambda > 0 else None
        self.opt["c"] = self._to_colour_key(mi.Float(aligned(c).ravel()))
        self.opt.set_learning_rate({"c": s.lr_colour})
        # the photo model's own Adam, per entry: one photo's large residual must not set every other photo's step
        # (the mesh's uniform Adam would)
        self.popt = mi.ad.Adam(lr=s.lr_exposure) if self.per_view else None
        if self.refine:
            self.popt["cam_rot"] = mi.Float(aligned(self.cam_rot).ravel())
            self.popt["cam_shift"] = mi.Float(aligned(self.cam_shift / self.size).ravel())  # × scene size
        if self.focal:
            self.popt["focal"] = mi.Float([self.log_focal])
        if self.exposure:
            self.popt["gain"] = mi.Float(aligned(self.log_gain).ravel())
        if self.env_fit:
            self.popt["env"] = mi.Float(aligned(self.env_values).ravel())
            self.env_index = mi.UInt32(pm.envmap_index(*self.env_values.shape[:2]))
            self.env_shape = tuple(self.params["env.data"].shape)
        if self.flash:
            self.popt["flash"] = mi.Float(aligned(self.log_flash))
        self._extra_rates(1.0)

    def _prior_pairs(self, v_ref: np.ndarray, f: np.ndarray) -> np.ndarray:
        """The planarity prior's face pairs: every interior edge, or (``planarity_where`` "seen") those beside a
        triangle that a fitted training photo sees on ``v_ref``, or ("thick") those between two triangles of ``v_ref``
        whose part is at least ``planarity_min_thickness`` × its largest extent thick."""
        pairs = dihedral_pairs(f)
        self.planarity.where, self.planarity.edges_all = self.s.planarity_where, len(pairs)
        if self.s.planarity_where == "seen" and self.planarity.weight > 0 and len(pairs):
            meta = self.bench.meta
            seen = views_seeing(v_ref, f, [meta.cameras[i] for i in self.train_ids], meta.fov) > 0
            pairs = pairs[seen[pairs[:, 0]] | seen[pairs[:, 1]]]
        elif self.s.planarity_where == "thick" and self.planarity.weight > 0 and len(pairs):
            thick = inward_thickness(v_ref, f) >= self.s.planarity_min_thickness * np.ptp(v_ref, axis=0).max()
            pairs = pairs[thick[pairs[:, 0]] & thick[pairs[:, 1]]]
        self.planarity.edges = len(pairs)
        return pairs

    def _initial_env(self) -> np.ndarray:
        """The fitted environment's start: the training photos' pixels that miss the start mesh, where their rays end
        (:func:`~inverse.morph.photo_model.env_from_photos`): the background, and the light a far scene gives."""
        meta = self.bench.meta
        return pm.env_from_photos([meta.cameras[i] for i in self.train_ids],
                                  [np.asarray(self.photos[i]) for i in self.train_ids],
                                  self.v_start, self.f_start, self.s.env_resolution)

    def _extra_rates(self, decay: float) -> None:
        s = self.s
        rates = {}
        if self.refine:
            rates.update(cam_rot=s.lr_camera * decay, cam_shift=s.lr_camera * decay)
        if self.focal:
            rates["focal"] = s.lr_camera * decay
        if self.exposure:
            rates["gain"] = s.lr_exposure * decay
        if self.env_fit:
            rates["env"] = s.lr_env * decay
        if self.flash:
            rates["flash"] = s.lr_flash * decay
        if rates:
            self.popt.set_learning_rate(rates)

    def _sync_extras(self) -> None:
        """The fitted cameras, gains and environment from the optimiser into numpy (for checkpoints and rebuilds)."""
        if self.popt is None:
            return
        n = len(self.train_ids)
        if self.refine:
            self.cam_rot = np.array(self.popt["cam_rot"], np.float64).reshape(n, 3)
            self.cam_shift = np.array(self.popt["cam_shift"], np.float64).reshape(n, 3) * self.size
        if self.focal:
            self.log_focal = float(np.array(self.popt["focal"])[0])
        if self.exposure:
            self.log_gain = np.array(self.popt["gain"], np.float64).reshape(n, 3)
        if self.env_fit:
            self.env_values = np.array(self.popt["env"], np.float32).reshape(self.env_values.shape)
        if self.flash:
            self.log_flash = np.array(self.popt["flash"], np.float64)

    def gain_of(self, i: int) -> np.ndarray:
        """Photo ``i``'s RGB gain: its own where fitted, else its fitted neighbours' mean moved by the ratio of the
        EXIF exposures (:func:`~inverse.morph.photo_model.neighbour_log_gain`; 1 without exposure)."""
        if not self.exposure:
            return np.ones(3)
        self._sync_extras()
        k = self.train_index
        if int(i) in k:
            return np.exp(self.log_gain[k[int(i)]])
        return np.exp(pm.neighbour_log_gain(self.log_gain, [k[j] for j in self.gain_from[int(i)]],
                                            self.log_exposure[int(i)], self.log_exposure[self.gain_from[int(i)]],
                                            self.exposure_slope()))

    def exposure_slope(self) -> float:
        """How the fitted gains follow the EXIF exposures (:func:`~inverse.morph.photo_model.exposure_slope`)."""
        self._sync_extras()
        return pm.exposure_slope(self.log_exposure[self.train_ids], self.log_gain)

    def _set_env(self) -> None:
        if self.env_fit:
            data = dr.gather(mi.Float, dr.maximum(self.popt["env"], 0.0), self.env_index)
            self.params["env.data"] = mi.TensorXf(data, self.env_shape)

    def _to_colour_key(self, c):
        return self.ls_c.to_differential(c) if self.ls_c is not None else c

    def colour_values(self):
        """The vertex colours, flat (r, g, b per vertex), from the optimiser's variable."""
        return dr.ravel(self.ls_c.from_differential(self.opt["c"])) if self.ls_c is not None else self.opt["c"]

    def positions(self):
        return self.ls.from_differential(self.opt["u"]) if self.ls is not None else self.opt["v"]

    def vertices(self) -> np.ndarray:
        return np.array(dr.detach(self.positions()), np.float64).reshape(-1, 3)

    def colours(self) -> np.ndarray:
        return np.array(dr.detach(self.colour_values()), np.float32).reshape(-1, 3)

    # -- the loop's interface -----------------------------------------------------------------------------------

    def fingerprint(self) -> dict:
        # these only decide between runs (the decision files record them); a run's own steps do not read them
        between = ("prior_margin", "prior_ties", "light_select_every", "light_select_colour_lambda",
                   "step_select_quantile", "step_select_lr", "planarity_select_where", "mode_select")
        finish_only = ("border_turn_deg",)  # acts in :meth:`finish`, on the state the checkpoint holds
        # fields added later, at the value that computes what runs made before them did (bit for bit): those runs'
        # checkpoints still match
        same = (("boundary_spp",) if self.shared_spp else ()) + \
            (("indirect_reference",) if self.s.indirect_reference == "direct" else ()) + \
            (("indirect_downsample",) if self.s.indirect_downsample == 1 else ()) + \
            (("adam_quantile",) if self.s.adam_quantile == 1.0 else ()) + \
            (("saturation",) if self.s.saturation == 0 else ()) + \
            (("mask_weight",) if self.s.mask_weight == 0 else ()) + \
            (("mask_every",) if self.s.mask_every == 1 or self.s.mask_weight == 0 else ()) + \
            (("mask_downsample",) if self.s.mask_downsample == 1 or self.s.mask_weight == 0 else ()) + \
            (("planarity_where",) if self.s.planarity_where == "all" else ()) + \
            (("planarity_min_thickness",) if self.s.planarity_where != "thick" else ()) + \
            (() if self.per_view else ("refine_cameras", "lr_camera", "camera_weight", "exposure", "lr_exposure",
                                       "env_resolution", "lr_env")) + \
            (("refine_focal",) if not self.focal else ()) + \
            (("flash", "lr_flash") if not self.flash else ())
        settings = {k: v for k, v in asdict(self.s).items() if k not in between + finish_only + same}
        if not self.s.indirect_every:  # no estimate: its settings unread, kept as runs before their defaults changed
            settings["indirect_spp"] = PLAIN_RUN_INDIRECT_SPP
            settings.pop("indirect_reference", None)
            settings.pop("indirect_downsample", None)
        return {"settings": settings, "input": self.digest, "photos": self.photos_digest}

    def fingerprint_against(self, saved: dict) -> dict:
        # the plane rule's threshold acts only through the weight it decides for this input (and not at all under a
        # given weight): a checkpoint made under another threshold on the same side of the input's plane share (the
        # suite's stored trials at 0.2) resumes
        fp = self.fingerprint()
        was = (saved.get("settings") or {}).get("planarity_auto_threshold")
        share = self.planarity.dominant_plane_fraction
        unread = self.s.planarity_weight is not None
        if isinstance(was, (int, float)) and (unread or share is not None and
                                              (share >= was) == (share >= self.s.planarity_auto_threshold)):
            fp["settings"]["planarity_auto_threshold"] = was
        return fp

    def state(self) -> dict:
        self._sync_extras()
        extras = {"cam_rot": self.cam_rot, "cam_shift": self.cam_shift, "log_gain": self.log_gain,
                  "log_focal": np.array([self.log_focal]), "log_flash": self.log_flash,
                  "flash_weight": np.array([self.flash_weight])}
        if self.env_fit:
            extras["env"] = self.env_values
        return {**extras, "faces": self.faces, "v_ref": self.v_ref, "vertices": self.vertices(), "colours": self.colours(),
                "optimizer": optimizer_state(self.opt),
                **({"photo_optimizer": optimizer_state(self.popt)} if self.popt is not None else {}), "rng": rng_state(self.rng), "lambda": self.lam,
                "trace": [to_json(t) for t in self.trace], "snapshots": list(self.snapshots),
                "anneal": list(self.anneal) if self.anneal else None,
                "validation_seconds": self.validation_seconds,
                "indirect": {str(k): np.array(v) for k, v in self.indirect.items()}}

    def load_state(self, tree: dict) -> None:
        self.lam = float(tree["lambda"])
        for k in ("cam_rot", "cam_shift", "log_gain", "log_flash"):
            if k in tree:
                setattr(self, k, np.asarray(tree[k], np.float64))
        if "log_focal" in tree:
            self.log_focal = float(np.asarray(tree["log_focal"]).ravel()[0])
        if "flash_weight" in tree:
            self.flash_weight = float(np.asarray(tree["flash_weight"]).ravel()[0])
        if self.env_fit and "env" in tree:
            self.env_values = np.asarray(tree["env"], np.float32)
        self._build(tree["vertices"], tree["v_ref"], tree["faces"], tree["colours"])
        load_optimizer_state(self.opt, tree["optimizer"], "morph optimizer")
        if self.popt is not None and "photo_optimizer" in tree:
            load_optimizer_state(self.popt, tree["photo_optimizer"], "morph photo optimizer")
        set_rng_state(self.rng, tree["rng"])
        self.trace = [from_json(TracePoint, t, "morph checkpoint: trace") for t in tree["trace"]]
        self.snapshots = [np.asarray(x) for x in tree["snapshots"]]
        a = tree["anneal"]
        self.anneal = (int(a[0]), int(a[1]), float(a[2])) if a is not None else None
        self.validation_seconds = float(tree["validation_seconds"])
        self.indirect = {int(k): mi.TensorXf(np.asarray(v, np.float32)) for k, v in (tree.get("indirect") or {}).items()}

    # -- validation, trace, λ schedule ----------------------------------------------------------------------------

    def validation_l1(self) -> float | None:
        """Mean L1 of the validation photos (fixed seeds: checks compare like with like); no gradients."""
        if not self.val_ids:
            return None
        meta = self.bench.meta
        with dr.suspend_grad():
            if self.flash:  # the flash moves with the camera: one view at a time
                imgs = []
                for i in self.val_ids:
                    self._set_mesh(dr.detach(self._flat()), dr.detach(self.colour_values()), i)
                    imgs += render_views(self.scene, self.params, meta.cameras, [i], self.res, meta.fov,
                                         max(self.s.spp, 8), 7_000_003)
                    dr.eval(imgs[-1])  # rendered with this view's flash before the next moves it
                return float(np.mean([np.asarray(self._l1(img, i)).item() for img, i in zip(imgs, self.val_ids)]))
            if self.per_view:  # the last step left the last view's pose in the scene
                self._set_mesh(dr.detach(self._flat()), dr.detach(self.colour_values()))
            imgs = render_views(self.scene, self.params, meta.cameras, self.val_ids, self.res, meta.fov,
                                max(self.s.spp, 8), 7_000_003)
            return float(np.mean([np.asarray(self._l1(img, i)).item() for img, i in zip(imgs, self.val_ids)]))

    def _l1(self, img, i):
        """L1 against photo ``i`` without its saturated pixels (:func:`~inverse.morph.scene.photo_l1`)."""
        return photo_l1(self._exposed(img, i), self.photos[int(i)], self.photo_hot.get(int(i)),
                        self.saturation_level)

    def _with_indirect(self, img, i):
        extra = self.indirect.get(int(i))
        return img[..., :3] if extra is None else img[..., :3] + extra

    def estimate_indirect(self, views: list[int] | None = None, draw: int = 0) -> None:
        """Per photo (of ``views``; None: every training photo): a path-traced render at the photos' depth minus
        direct light (``indirect_reference``), no gradients. With "depth2" the subtrahend is the path tracer at depth
        2 with the same seed: Mitsuba's path tracer draws the same random numbers for the same first bounce at
        either depth, so the first bounce cancels sample for sample and the difference carries the indirect light's
        own noise only (josie, 128²: RMSE 0.0031 at 16 spp against 0.0050 for "direct" at 64 spp); rendered in one
        pass by the ``indirect`` integrator (since 2026-11-28; before, two renders subtracted).
        Rendered at 1/``indirect_downsample`` of the fitting resolution (rounded up) and upsampled bilinearly.
        ``draw``: another draw of the estimate's random numbers (0: the one every run and choice uses)."""
        meta = self.bench.meta
        if not self.s.indirect_every or self.s.mode != "lit":
            return
        depth = meta.settings.photo_max_depth
        depth2 = self.s.indirect_reference == "depth2"
        with dr.suspend_grad(), mitsuba_log_level(mi.LogLevel.Error):
            # "depth2" in one render: the ``indirect`` integrator draws the path tracer's random numbers and keeps
            # only paths of 3 segments or more, i.e. the difference of the two renders to rounding (tested)
            path = mi.load_dict({"type": "indirect", "max_depth": depth, "min_depth": 3} if depth2
                                else {"type": "path", "max_depth": depth})
            direct = None if depth2 else mi.load_dict({"type": "direct"})
            res = -(-self.res // self.s.indirect_downsample)
            for i in (meta.train if views is None else views):
                sensor = mi.load_dict(sensor_dict(meta.cameras[int(i)], res, meta.fov))
                seed = 9_000_011 + int(i) + ESTIMATE_DRAW_STRIDE * int(draw)
                a = np.array(mi.render(self.scene, self.params, sensor=sensor, integrator=path,
                                       spp=self.s.indirect_spp, seed=seed))[..., :3]
                if direct is not None:
                    a = a - np.array(mi.render(self.scene, self.params, sensor=sensor, integrator=direct,
                                               spp=self.s.indirect_spp, seed=seed))[..., :3]
                diff = upsample_bilinear(a, self.res)
                self.indirect[int(i)] = mi.TensorXf(np.ascontiguousarray(diff, np.float32))

    def _check(self, run: RunState) -> None:
        s = self.s
        if self.flash:
            self._sync_extras()
            self.flash_weight = flash_sampling_weight(np.exp(self.log_flash), self.env_values, self.flash_r)
        t0 = time.perf_counter()
        val = self.validation_l1()
        self.validation_seconds += time.perf_counter() - t0
        self.trace.append(TracePoint(run.step, self.setup_seconds + run.train_seconds, val,
                                     lambda_=self.lam if s.parameterisation == "large_steps" else None))
        if not s.remesh_at:
            self.snapshots.append(self.vertices().astype(np.float32))
        if val is None:
            return
        if s.early_stop and self.anneal is None and self.checks_without_gain() >= s.patience \
                and run.step >= s.min_iterations:
            length = max(int(round(s.anneal_fraction * run.step)), s.check_every)
            if run.step + length < s.iterations:  # else the linear decay over the cap ends sooner anyway
                self.anneal = (run.step, length, self.lr_factor(run.step))

    def checks_without_gain(self) -> int:
        """Validation checks since the last one that improved on the best so far by ``min_improvement``."""
        best, since = float("inf"), 0
        for t in self.trace:
            if t.validation_l1 is None:
                continue
            if t.validation_l1 < best * (1.0 - self.s.min_improvement):
                best, since = t.validation_l1, 0
            else:
                since += 1
        return since

    def lr_factor(self, it: int) -> float:
        """Learning-rate factor at iteration ``it``: linear to lr_final over the cap, or the plateau's anneal."""
        s = self.s
        if self.anneal is None:
            return 1.0 - (1.0 - s.lr_final) * it / max(s.iterations - 1, 1)
        start, length, f0 = self.anneal
        return f0 + (s.lr_final - f0) * min(1.0, (it - start) / length)

    def _schedule_lambda(self, step: int) -> None:
        """Geometric fall from λ_start to λ over the warm-up; the operator is refactored, Adam's state on u reset."""
        s = self.s
        if not s.lambda_start or s.parameterisation != "large_steps":
            return
        t = min(1.0, step / max(s.lambda_warmup * s.iterations, 1.0))
        lam = float(s.lambda_start * (s.lambda_ / s.lambda_start) ** t)
        if abs(lam - self.lam) <= 1e-9 * lam:
            return
        v = self.positions()
        self.lam = lam
        self.ls = mi.ad.LargeSteps(mi.Float(aligned(self.v_ref).ravel()), self.f_mi, lam)
        self.opt["u"] = self.ls.to_differential(dr.detach(v))
        self.opt.reset("u")  # u = (I + λL)v changes scale with λ: old moments would mislead the steps

    def step(self, it: int) -> StepResult:
        s, meta = self.s, self.bench.meta
        decay = self.lr_factor(it)
        self.opt.set_learning_rate({self.key: self.lr_pos * decay, "c": s.lr_colour * decay})
        self._extra_rates(decay)
        if self.per_view:
            return self._step_per_view(it)
        flat = dr.ravel(self.positions()) if self.ls is not None else self.positions()
        self.params["mesh.vertex_positions"] = flat
        colours = self.colour_values()
        self.params["mesh.vertex_color"] = colours
        with mitsuba_log_level(mi.LogLevel.Error):  # non-manifold vertices of remeshed inputs: expected
            self.params.update()
        views = self.rng.choice(self.train_ids, size=min(s.views_per_step, len(self.train_ids)), replace=False)
        imgs = render_views(self.scene, self.params, meta.cameras, views, self.res, meta.fov, s.spp,
                            s.seed * 7919 + it * 101, integrator_spp=not self.shared_spp)
        loss = 0
        for img, i in zip(imgs, views):
            loss += self._l1(img, i)  # eq. 4.3, L1
        loss = loss / len(views)
        if s.mask_weight > 0 and it % s.mask_every == 0:
            self.mask_params["mesh.vertex_positions"] = flat
            with mitsuba_log_level(mi.LogLevel.Error):
                self.mask_params.update()
            skies = render_views(self.mask_scene, self.mask_params, meta.cameras, views, self.mask_res, meta.fov, s.spp,
                                 s.seed * 7919 + it * 101 + 1_000_003, integrator_spp=not self.shared_spp)
            silhouettes = 0
            for img, i in zip(skies, views):
                silhouettes += dr.mean(self._silhouette_l1(img, i), axis=None)
            loss += s.mask_weight * s.mask_every * silhouettes / len(views)
        if self.planarity.weight > 0:
            loss += self.planarity.weight * planarity_prior(dr.unravel(mi.Point3f, flat), self.f_mi, self.pairs,
                                                            self.sigma)
        if self.colour_prior.weight > 0:
            loss += self.colour_prior.weight * colour_prior(colours, self.edges)
        dr.backward(loss)
        return self.result(loss)

    def _flat(self):
        return dr.ravel(self.positions()) if self.ls is not None else self.positions()

    def _view_flat(self, flat, i: int):
        """The positions that view ``i`` renders: moved by its camera's correction where it is fitted."""
        if not self.refine or int(i) not in self.train_index:
            return flat
        k = self.train_index[int(i)]
        w = pm.pick3(self.popt["cam_rot"], k)
        t = pm.pick3(self.popt["cam_shift"], k) * self.size
        moved = pm.view_positions(flat, self.centres[int(i)], w, t)
        if self.focal:  # in the imported camera's axes: a correction of its pose's size leaves them to second order
            moved = pm.focal_positions(moved, self.bench.meta.cameras[int(i)].matrix, self.popt["focal"])
        return moved

    def _exposed(self, img, i: int):
        """The render's RGB times photo ``i``'s gain (its own, differentiable, where fitted)."""
        img = self._with_indirect(img, i)
        if not self.exposure:
            return img
        if int(i) in self.train_index:
            g = dr.exp(pm.pick3(self.popt["gain"], self.train_index[int(i)]))
            return img * mi.TensorXf(dr.ravel(g), (1, 1, 3))
        return img * mi.TensorXf(self.gain_of(i).astype(np.float32).reshape(1, 1, 3))

    def _set_mesh(self, flat, colours, view: int | None = None) -> None:
        """The step's mesh, the fitted light, and the flash at ``view``'s camera."""
        self.params["mesh.vertex_positions"] = flat
        self.params["mesh.vertex_color"] = colours
        self._set_env()
        if self.flash and view is not None:
            if int(view) in self.flash_photos:
                set_flash(self.params, self.centres[int(view)], mi.Color3f(dr.exp(pm.pick3(self.popt["flash"], 0))),
                          self.flash_weight)
            else:
                set_flash(self.params, self.centres[int(view)], np.zeros(3))
        with mitsuba_log_level(mi.LogLevel.Error):
            self.params.update()

    def _step_per_view(self, it: int) -> StepResult:
        """One step where each view renders its own mesh pose (refined cameras) or gain: every view's loss is
        differentiated right after its render (Mitsuba's backward pass renders the scene as it then is), the
        gradients adding up in the optimiser's variables."""
        s, meta = self.s, self.bench.meta
        views = self.rng.choice(self.train_ids, size=min(s.views_per_step, len(self.train_ids)), replace=False)
        total, n = 0.0, len(views)
        for k, i in enumerate(views):
            seed = s.seed * 7919 + it * 101
            flat = self._view_flat(self._flat(), i)
            self._set_mesh(flat, self.colour_values(), i)
            img, = render_views(self.scene, self.params, meta.cameras, [i], self.res, meta.fov, s.spp, seed + k,
                                integrator_spp=not self.shared_spp)
            loss = photo_l1(self._exposed(img, i), self.photos[int(i)], self.photo_hot.get(int(i)),
                            self.saturation_level) / n
            if self.mask_weight > 0 and it % s.mask_every == 0:
                self.mask_params["mesh.vertex_positions"] = flat
                with mitsuba_log_level(mi.LogLevel.Error):
                    self.mask_params.update()
                sky, = render_views(self.mask_scene, self.mask_params, meta.cameras, [i], self.mask_res, meta.fov,
                                    s.spp, seed + k + 1_000_003, integrator_spp=not self.shared_spp)
                loss += self.mask_weight * s.mask_every * dr.mean(self._silhouette_l1(sky, i), axis=None) / n
            dr.backward(loss)
            total += float(loss.array[0])
        extra = 0
        if self.planarity.weight > 0 or self.colour_prior.weight > 0:
            flat = self._flat()
            if self.planarity.weight > 0:
                extra += self.planarity.weight * planarity_prior(dr.unravel(mi.Point3f, flat), self.f_mi, self.pairs,
                                                                 self.sigma)
            if self.colour_prior.weight > 0:
                extra += self.colour_prior.weight * colour_prior(self.colour_values(), self.edges)
        if self.refine and s.camera_weight > 0:  # the prior toward the imported poses (photo_model's scales)
            r, t = self.popt["cam_rot"], self.popt["cam_shift"]
            extra += s.camera_weight * (dr.sum(r * r) / pm.CAMERA_PRIOR_ROT ** 2 +
                                        dr.sum(t * t) / pm.CAMERA_PRIOR_SHIFT ** 2) / len(self.train_ids)
            if self.focal:
                extra += s.camera_weight * dr.sum(self.popt["focal"] ** 2) / pm.CAMERA_PRIOR_FOCAL ** 2
        if not isinstance(extra, int):
            dr.backward(extra)
            total += float(extra.array[0])
        grads = [dr.grad(o[k]) for o in (self.opt, self.popt) for k in o.keys()]
        dr.eval(*grads)
        return StepResult(total, all_finite(*grads), log={})

    def discard(self, it: int) -> None:
        super().discard(it)
        for k in (self.popt.keys() if self.popt is not None else ()):
            dr.set_grad(self.popt[k], 0)

    def apply(self, it: int) -> None:
        s = self.s
        v_before = self.vertices() if s.forbid_flips else None
        self.opt.step()
        if self.popt is not None:
            self.popt.step()
        if self.refine:  # a motion of all cameras together is the mesh's: the corrections keep none of it
            n = len(self.train_ids)
            rot, shift = pm.remove_gauge(np.array(self.popt["cam_rot"], np.float64).reshape(n, 3),
                                         np.array(self.popt["cam_shift"], np.float64).reshape(n, 3) * self.size,
                                         self.centres[self.train_ids], self.size)
            self.popt["cam_rot"] = mi.Float(rot.astype(np.float32).ravel())
            self.popt["cam_shift"] = mi.Float((shift / self.size).astype(np.float32).ravel())
        if self.exposure:  # one overall gain is the colours' (and the light's): the gains' mean stays 0
            g = dr.unravel(mi.Vector3f, self.popt["gain"])
            self.popt["gain"] = dr.ravel(g - mi.Vector3f(*[dr.mean(g[k]) for k in range(3)]))
        if self.env_fit:
            self.popt["env"] = dr.maximum(dr.detach(self.popt["env"]), 0.0)
        c = dr.clip(dr.detach(self.colour_values()), 0.0, 1.0 if s.mode == "lit" else 10.0)
        self.opt["c"] = self._to_colour_key(c)
        if v_before is not None:
            undo_flips(self.opt, self.key, v_before, self.positions,
                       self.ls.to_differential if self.ls is not None else (lambda x: x), self.n_start, self.faces)

    def start(self, run: RunState) -> None:
        if run.step == 0 and not self.indirect:
            self.estimate_indirect()
        if run.step == 0 and not self.trace:
            self._check(run)

    def after_step(self, it: int, run: RunState) -> None:
        if self.s.indirect_every and run.step % self.s.indirect_every == 0 and not (run.done or run.stopped):
            self.estimate_indirect()
        if run.step in self.s.remesh_at and not run.done:
            self._sync_extras()
            v, f, c = remesh(self.vertices(), self.faces, self.colours())
            self._build(v, v, f, c)
        if self.anneal is not None and run.step >= self.anneal[0] + self.anneal[1]:
            run.stopped = True  # annealed after the plateau: done
        if run.step % self.s.check_every == 0 or run.done or run.stopped:
            self._check(run)
            if not run.stopped and not run.done:
                self._schedule_lambda(run.step)

    def finish(self, run: RunState) -> MorphResult:
        s = self.s
        v_out, c_out = self.vertices(), self.colours()
        repair = None
        pleat_report = spike_report = turn_report = None
        if s.repair_flips and not s.remesh_at:
            v_out, repair = repair_flips(v_out, self.faces, self.v_start)
            if s.border_turn_deg:
                v_out, turn_report = iron_border_turns(v_out, self.faces, self.v_start, s.border_turn_deg)
            # the pleats' smoothing brings back no flip w.r.t. the start (``v_ref``: unfold_pleats guarantees it)
            v_out, pleat_report = unfold_pleats(v_out, self.faces, v_ref=self.v_start)
            v_out, spike_report = iron_spikes(v_out, self.faces, self.v_start)
        write_ply(self.out / "morphed.ply", v_out, self.faces, np.clip(c_out, 0, 1))
        seconds = self.setup_seconds + run.train_seconds
        self._sync_extras()
        fit = self.photo_fit() if self.capture or self.per_view else None
        self.close()
        if self.capture:
            ev = evaluate_capture_morph(self, self.v_in, self.f_in, self.c_in, v_out, self.faces, c_out,
                                        start=(self.v_start, self.f_start) if not s.remesh_at else None)
        else:
            ev = evaluate_morph(self.bench, self.v_in, self.f_in, self.c_in, v_out, self.faces, c_out, s.mode, self.res,
                            self.out, start=(self.v_start, self.f_start) if not s.remesh_at else None)
        trace_in = None
        if self.snapshots and self.bench.ground_truth is not None and not self.capture:  # the convergence curve in Chamfer (coarser estimator than the headline figure)
            gv, gf = load_mesh_any(self.bench.ground_truth)

            def quick(v, f):
                return chamfer(np.asarray(v, np.float64), f, gv, gf, n=20_000, n_ref=200_000)["chamfer"]
            trace_in = quick(self.v_in, self.f_in)
            for t, v in zip(self.trace, self.snapshots):
                t.chamfer = quick(v, self.faces)
        return MorphResult(**vars(ev), seconds=seconds, iterations=run.step, vertices=int(len(v_out)),
                           method=s.parameterisation, settings=s, training=run.summary(),
                           planarity=self.planarity, colour_prior=self.colour_prior, repair=repair,
                           pleats=pleat_report, spike_ironing=spike_report, border_turns=turn_report,
                           trace=self.trace,
                           stopped_early=run.stopped,
                           validation_views=list(self.val_ids), validation_seconds=self.validation_seconds,
                           trace_chamfer_input=trace_in, saturation_level=self.saturation_level, photo_fit=fit)

    def _silhouette_l1(self, img, i):
        """Per pixel, the mask render's L1 against photo ``i``'s mask (weighted where the mask is unsure)."""
        d = dr.abs(img[..., :3] - self.sky[int(i)])
        return d * self.sky_weight[int(i)] if int(i) in self.sky_weight else d

    def photo_fit(self) -> PhotoFit:
        """What the fit made of the photos beside the mesh: cameras moved, gains, the fitted light (written as
        ``environment.exr`` in the run folder)."""
        meta = self.bench.meta
        env = None
        if self.env_fit:
            env = str(imageio.write_exr(self.out / "environment.exr", {"": self.env_values}, half=False).name)
        gains = {int(i): [float(x) for x in self.gain_of(i)] for i in range(len(meta.cameras))}
        return PhotoFit(mode=self.s.mode, refined_cameras=self.refine, exposure=self.exposure,
                        fitted_light=self.env_fit, train_views=list(map(int, self.train_ids)),
                        camera_movement=pm.camera_movement(self.cam_rot, self.cam_shift, self.size) if self.refine
                        else None, camera_rotation=self.cam_rot.tolist() if self.refine else None,
                        camera_shift=self.cam_shift.tolist() if self.refine else None,
                        gains=gains if self.exposure else None,
                        exposure_slope=self.exposure_slope() if self.exposure else None, environment=env,
                        focal_scale=float(np.exp(self.log_focal)) if self.focal else None,
                        flash=self.flash_intensity().tolist() if self.flash else None,
                        flash_photos=sorted(self.flash_photos) if self.flash else None,
                        masks=getattr(self.bench, "mask_source", None),
                        backdrop=self.backdrop.to_json() if self.backdrop is not None else None)

    def flash_weight_now(self) -> float:
        """The flash's sampling weight for the fitted lights as they are (the held-out renders')."""
        self._sync_extras()
        return flash_sampling_weight(np.exp(self.log_flash), self.env_values, self.flash_r) if self.flash else 1.0

    def flash_intensity(self, view: int | None = None) -> np.ndarray:
        """The fitted flash's RGB intensity (W/sr); for ``view``, 0 where its photo was taken without it."""
        self._sync_extras()
        on = self.flash and (view is None or int(view) in self.flash_photos)
        return np.exp(self.log_flash) if on else np.zeros(3)

    def close(self) -> None:
        """Free the scene (Mitsuba traces every live plugin instance in every render) and the work file."""
        self.scene = self.params = self.opt = self.popt = self.ls = self.ls_c = None
        self.work_ply.unlink(missing_ok=True)


def flash_photos(cameras: list, flash: str) -> set[int]:
    """The photos a flash lit (:attr:`MorphSettings.flash`): "on" every one, "auto" those whose camera records that
    the flash fired (a capture's EXIF), "off" none."""
    if flash == "on":
        return set(range(len(cameras)))
    if flash == "auto":
        return {i for i, c in enumerate(cameras) if getattr(c, "flash", None)}
    return set()


def initial_flash(distance: float) -> float:
    """The flash's starting intensity: the one that gives a diffuse surface its albedo as radiance (ρ·I·cos θ/(π r²) =
    ρ) at ``distance`` r, the median distance from the cameras to the mesh (:func:`flash_distance`), for the mean
    cos θ = 2/3 of a sphere's lit half; the photos fit the rest (SfM units are arbitrary: r sets the scale)."""
    return float(1.5 * np.pi * distance ** 2)


def validation_split(train: list[int], k: int) -> list[int]:
    """``k`` training views spread evenly over the orbit (never all of them: at least one stays to fit)."""
    k = min(k, len(train) - 1)
    if k <= 0:
        return []
    return sorted({train[int((j + 0.5) * len(train) / k)] for j in range(k)})


def photos_digest(bench: MorphBenchmark) -> str:
    """The photos a run fits and the cameras they were taken from, for its fingerprint: a benchmark made again over
    the same coarse mesh with other photos must not resume a run's optimiser as if nothing had changed."""
    meta = bench.meta
    poses = np.array([c.matrix.ravel().tolist() + [c.f, c.cx, c.cy, c.width, c.height] if hasattr(c, "matrix")
                      else [*c.eye, *c.target] for c in meta.cameras], np.float64)
    return array_key(*(bench.photo(i) for i in range(len(meta.cameras))), poses)[0][:16]


def run_stage(bench: MorphBenchmark, out: Path, s: MorphSettings, show_progress: bool = True,
              budget_iterations: int | None = None) -> MorphResult | None:
    """One run of the optimisation stage with settings ``s`` as they are (no choice made), in ``out``."""
    stage = MorphStage(bench, out, s)
    try:
        return run_loop(stage, LoopSettings(steps=s.iterations, checkpoint_every=s.checkpoint_every),
                        checkpoint=out / "checkpoint.npz", budget_steps=budget_iterations,
                        show_progress=show_progress, metrics_path=out / "metrics.json")
    finally:
        stage.close()
