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

from foundation.errors import UsageError
from foundation.files import array_key, file_digest
from foundation.loop import (DrJitStage, LoopSettings, RunState, StepResult, rng_state, run_loop,
                             set_rng_state)
from foundation.mesh import face_normals, load_mesh_any, read_ply_colours, unique_edges, write_ply
from foundation.mesh_metrics import chamfer
from foundation.records import from_json, to_json
from foundation.optim_state import load_optimizer_state, optimizer_state
from foundation.quantile_adam import QuantileAdam
from foundation.scene import mitsuba_log_level

from .benchmark import MorphBenchmark, sensor_dict
from .evaluate import evaluate_morph
from .prior import colour_prior, dihedral_pairs, dominant_plane_fraction, planarity_prior
from .mesh_edit import (iron_border_turns, iron_spikes, remesh,
                        repair_flips, undo_flips, unfold_pleats)
from .scene import (inward_thickness, mask_integrator, mask_scene, morph_scene, photo_l1, photo_masks,
                    photo_saturation, photo_tensors, projective_integrator, render_views, upsample_bilinear, views_seeing)

from .results import (ColourPriorDecision, MorphResult,
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
                    for i, m in photo_masks(bench, self.mask_res, self.train_ids).items()} if s.mask_weight > 0 else {}
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
        self.scene = morph_scene(self.work_ply, s.mode, self.bench.meta.hdri,
                                 integrator=None if self.shared_spp else projective_integrator(s.spp, s.boundary_spp))
        self.params = mi.traverse(self.scene)
        if s.mask_weight > 0:  # the same mesh file: both scenes get the step's positions
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
                   "step_select_quantile", "step_select_lr", "planarity_select_where")
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
            (("planarity_min_thickness",) if self.s.planarity_where != "thick" else ())
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
        return {"faces": self.faces, "v_ref": self.v_ref, "vertices": self.vertices(), "colours": self.colours(),
                "optimizer": optimizer_state(self.opt), "rng": rng_state(self.rng), "lambda": self.lam,
                "trace": [to_json(t) for t in self.trace], "snapshots": list(self.snapshots),
                "anneal": list(self.anneal) if self.anneal else None,
                "validation_seconds": self.validation_seconds,
                "indirect": {str(k): np.array(v) for k, v in self.indirect.items()}}

    def load_state(self, tree: dict) -> None:
        self.lam = float(tree["lambda"])
        self._build(tree["vertices"], tree["v_ref"], tree["faces"], tree["colours"])
        load_optimizer_state(self.opt, tree["optimizer"], "morph optimizer")
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
            imgs = render_views(self.scene, self.params, meta.cameras, self.val_ids, self.res, meta.fov,
                                max(self.s.spp, 8), 7_000_003)
            return float(np.mean([np.asarray(self._l1(img, i)).item() for img, i in zip(imgs, self.val_ids)]))

    def _l1(self, img, i):
        """L1 against photo ``i`` without its saturated pixels (:func:`~inverse.morph.scene.photo_l1`)."""
        return photo_l1(self._with_indirect(img, i), self.photos[int(i)], self.photo_hot.get(int(i)),
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
                silhouettes += dr.mean(dr.abs(img[..., :3] - self.sky[int(i)]), axis=None)
            loss += s.mask_weight * s.mask_every * silhouettes / len(views)
        if self.planarity.weight > 0:
            loss += self.planarity.weight * planarity_prior(dr.unravel(mi.Point3f, flat), self.f_mi, self.pairs,
                                                            self.sigma)
        if self.colour_prior.weight > 0:
            loss += self.colour_prior.weight * colour_prior(colours, self.edges)
        dr.backward(loss)
        return self.result(loss)

    def apply(self, it: int) -> None:
        s = self.s
        v_before = self.vertices() if s.forbid_flips else None
        self.opt.step()
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
        self.close()
        ev = evaluate_morph(self.bench, self.v_in, self.f_in, self.c_in, v_out, self.faces, c_out, s.mode, self.res,
                            self.out, start=(self.v_start, self.f_start) if not s.remesh_at else None)
        trace_in = None
        if self.snapshots:  # the convergence curve in Chamfer (coarser estimator than the headline figure)
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
                           trace_chamfer_input=trace_in, saturation_level=self.saturation_level)

    def close(self) -> None:
        """Free the scene (Mitsuba traces every live plugin instance in every render) and the work file."""
        self.scene = self.params = self.opt = self.ls = self.ls_c = None
        self.work_ply.unlink(missing_ok=True)


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
    return array_key(*(bench.photo(i) for i in range(len(meta.cameras))),
                     np.array([[*c.eye, *c.target] for c in meta.cameras], np.float64))[0][:16]


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
