"""The settings of a morph run (:class:`MorphSettings`) and the constants its checks and records use."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal


import mi_plugins  # noqa: F401

from foundation import validate
from foundation.errors import UsageError

from .scene import (MODES)



#: largest run seed: render seeds are seed·7919 + step·101 + view and must stay below 2³¹
MORPH_SEED_MAX = 200_000


#: the ``indirect_spp`` a run without the light estimate records in its checkpoint's fingerprint (the default when
#: those runs were first made): it never reads it, and a changed default must not make its checkpoints "other settings"
PLAIN_RUN_INDIRECT_SPP = 64
#: the edges the planarity prior acts on (:attr:`MorphSettings.planarity_where`)
PLANARITY_WHERE = ("all", "seen", "thick")
#: the values of the real-photo switches (:attr:`MorphSettings.refine_cameras`, ``exposure``)
AUTO_ON_OFF = ("auto", "on", "off")
#: how a tied prior choice goes (:attr:`MorphSettings.prior_ties`)
PRIOR_TIES = ("keep", "drop")
#: the light estimate's render seeds are 9_000_011 + view (+ this × the draw, for :func:`light_choice_draws`)
ESTIMATE_DRAW_STRIDE = 1_000_003


@dataclass
class MorphSettings:
    """The settings of a morph run. Each default's history — what it was before, what was measured, why it
    changed — is in docs/results/morph.md ("The settings and why")."""

    #: the cap; with ``early_stop`` a run anneals and ends once its validation loss stops improving
    iterations: int = 600
    views_per_step: int = 3
    mode: Literal["unlit", "lit"] = "lit"
    parameterisation: Literal["large_steps", "plain"] = "large_steps"
    lambda_: float = 2.0  #: large-steps λ
    lr: float = 0.05  #: × scene size / 10, for positions (Adam on u); 0 = positions frozen (a colour-only fit)
    lr_colour: float = 0.02  #: Adam's learning rate of the vertex colours
    lr_final: float = 0.1  #: learning rates decay linearly to this fraction (fewer late flips)
    #: large steps: the quantile of Adam's second moments that sets the step of u (1: their maximum, Nicolet et al.'s
    #: uniform Adam; :class:`foundation.quantile_adam.QuantileAdam`)
    adam_quantile: float = 1.0
    spp: int = 4
    #: samples per pixel of the silhouettes' gradient (projective integrator); None = ``spp``
    boundary_spp: int | None = 1
    resolution: int | None = None  #: None = the benchmark's photo resolution
    remesh_input: bool = True  #: isotropic remesh of the input first (decimators leave slivers that flip)
    target_vertices: int | None = None  #: remesh the input to about this many vertices (None: see min_vertices)
    min_vertices: int | None = 10_000  #: without a target, a coarser input is remeshed up to about this many vertices
    remesh_at: tuple[int, ...] = ()  #: iterations after which to remesh isotropically (pymeshlab)
    checkpoint_every: int = 20
    forbid_flips: bool = False  #: undo a step at vertices of triangles it flips w.r.t. the start
    #: after the run, unfold triangles flipped w.r.t. the start, then iron out pleats (reported)
    repair_flips: bool = True
    #: with ``repair_flips``: open-border triangles turned more than this from the start are ironed back
    #: (:func:`iron_border_turns`); 0 = off
    border_turn_deg: float = 60.0
    #: weight of the edge-preserving planarity prior (mean of ρ(1 − n_a·n_b), ρ(d) = d/(d+σ), over interior edges); 0 =
    #: off; None = the plane rule (``planarity_auto_*``)
    planarity_weight: float | None = None
    planarity_angle: float = 20.0  #: degrees; σ = 1 − cos(angle), where the prior's pull starts to fade
    planarity_auto_weight: float = 1.0
    #: the plane rule: the prior is on where the input's largest plane holds at least this share of its area
    planarity_auto_threshold: float = 0.26
    #: training photos kept out of the fit to watch convergence (their L1 every ``check_every`` iterations); 0 = none
    validation_views: int = 3
    validation_fraction: float = 0.125  #: at most this share of the training photos goes to validation
    check_every: int = 25
    #: after ``patience`` checks without a ``min_improvement`` gain (not before ``min_iterations``), anneal the learning
    #: rates over ``anneal_fraction`` × the iterations so far, then stop
    early_stop: bool = True
    patience: int = 2
    min_improvement: float = 0.005
    min_iterations: int = 150
    anneal_fraction: float = 0.33
    #: large-steps λ starts here and falls geometrically to ``lambda_`` over ``lambda_warmup`` of the iterations; None =
    #: constant λ
    lambda_start: float | None = None
    lambda_warmup: float = 0.15  #: its end is where the photos' choices are made (iteration 100 of 600)
    #: λ decided from the photos: each start value runs to the selection point, the lowest validation L1 continues
    #: (:class:`LambdaSelection`); () = constant λ
    lambda_select: tuple[float, ...] = (2.0, 25.0)
    #: where the plane rule leaves the prior off, each weight is one more candidate of the λ choice; () = the rule alone
    planarity_select: tuple[float, ...] = (0.1,)
    #: the edges the prior acts on: "all", "seen" (beside a triangle a training photo sees) or "thick" (parts at least
    #: ``planarity_min_thickness`` thick)
    planarity_where: Literal["all", "seen", "thick"] = "all"
    #: ``planarity_where`` of the ``planarity_select`` candidates
    planarity_select_where: Literal["all", "seen", "thick"] = "thick"
    #: "thick": the least thickness of a part the prior acts on, × the start's largest extent
    planarity_min_thickness: float = 0.05
    #: weight of the colour prior (mean colour step over edges); None = on at ``colour_prior_auto_weight`` where the
    #: input's colours are smooth, then asked of the photos (:class:`ColourSelection`)
    colour_prior_weight: float | None = None
    colour_prior_auto_weight: float = 0.1
    #: the colour rule: on where the input's mean colour step per edge is below this
    colour_prior_auto_threshold: float = 0.015
    #: a choice that models more continues only where its validation L1 is below (1 − margin) × the other's
    prior_margin: float = 0.015
    #: within the margin, "keep": the run with the prior continues; "drop": the run without it
    prior_ties: Literal["keep", "drop"] = "keep"
    #: estimate the light direct renders miss (path traced minus direct) every this many iterations and add it ('lit'
    #: mode); 0 = off, asked of the photos instead (``light_select_every``)
    indirect_every: int = 0
    indirect_spp: int = 16
    #: what the estimate subtracts from the path-traced render: "direct" or "depth2" (the same seed: the first bounce
    #: cancels sample for sample)
    indirect_reference: Literal["direct", "depth2"] = "depth2"
    indirect_downsample: int = 2  #: the estimate rendered at 1/this of the fitting resolution, upsampled bilinearly
    colour_lambda: float = 0.0  #: large-steps λ of the vertex colours (0: plain per-vertex steps)
    #: the light estimate and colour large steps asked of the photos: the winner's twin with ``indirect_every`` = this
    #: (:class:`LightSelection`); 0 = no such choice
    light_select_every: int = 100
    light_select_colour_lambda: float = 10.0
    #: the step asked of the photos: the winner's twin with ``adam_quantile`` = this and ``lr`` = ``step_select_lr``
    #: (:class:`StepSelection`); 1 = no such choice
    step_select_quantile: float = 0.9
    step_select_lr: float = 0.0125
    #: pixels brighter than this × the training photos' 99th percentile (photo or render) and their neighbours leave the
    #: loss; 0 = every pixel counts
    saturation: float = 4.0
    #: weight of the silhouette L1: the mesh's coverage of each pixel against the photos' masks; 0 = photos only
    mask_weight: float = 2.0
    mask_every: int = 1  #: the silhouette L1 every this many steps, at this × the weight
    mask_downsample: int = 1  #: the masks at the photos' resolution // this
    #: a capture without masks: "auto" derives them where its photos show a uniform backdrop
    #: (:mod:`inverse.capture.backdrop`; a scene's photos do not, and keep none); "off": none
    backdrop: Literal["auto", "off"] = "auto"
    #: refine each training photo's camera pose with the mesh (a rotation and a shift, pulled toward the imported pose by
    #: ``camera_weight``): "auto" where the cameras were estimated (captures), not a benchmark's exact ones. Off by
    #: default: on both vendored captures the held-out photos came out worse with it (docs/results/capture.md)
    refine_cameras: Literal["auto", "on", "off"] = "off"
    #: with refined cameras, also one focal length shared by all photos (a capture's pinhole cameras), pulled toward
    #: the imported one (5 % costs as much as 0.5° of rotation)
    refine_focal: bool = False
    lr_camera: float = 0.0005  #: Adam's step of the corrections: radians, and × scene size for the shifts
    #: weight of the camera prior (mean over photos of |ω|²/(0.5°)² + |t|²/(1 % of the scene)²)
    camera_weight: float = 0.001
    #: a colour gain per photo (exposure and white balance): "auto" on for captures (photos of a camera), off for a
    #: benchmark's renders; held-out photos take their two nearest fitted cameras' mean gain
    exposure: Literal["auto", "on", "off"] = "auto"
    lr_exposure: float = 0.03  #: Adam's step of the log-gains (at 0.005 they had not converged in a run)
    #: where the light is not known (captures): the fitted environment map's height (its width is twice that)
    env_resolution: int = 8
    lr_env: float = 0.01  #: Adam's step of the fitted environment's texels
    #: a light at the camera ('lit' mode, where the light is fitted): a point light at each photo's centre, one RGB
    #: intensity fitted for all. "auto": on for the photos whose EXIF says the flash fired; "on": every photo
    flash: Literal["auto", "on", "off"] = "auto"
    lr_flash: float = 0.01  #: Adam's step of the flash's log-intensity
    #: where the light is fitted, 'lit' runs' twin in 'unlit' mode is asked of the photos (:class:`ModeSelection`)
    mode_select: bool = True
    seed: int = 0

    def __post_init__(self):
        validate.integer("iterations", self.iterations, 0)
        validate.integer("views_per_step", self.views_per_step, 1)
        validate.one_of("mode", self.mode, MODES)
        validate.one_of("parameterisation", self.parameterisation, ("large_steps", "plain"))
        validate.positive("lambda_", self.lambda_)  # λ ≤ 0 makes I + λL indefinite (Cholesky fails)
        validate.non_negative("lr", self.lr)
        validate.non_negative("lr_colour", self.lr_colour)
        validate.non_negative("mask_weight", self.mask_weight)
        validate.integer("mask_every", self.mask_every, 1)
        validate.integer("mask_downsample", self.mask_downsample, 1, 16)
        validate.one_of("backdrop", self.backdrop, ("auto", "off"))
        validate.in_range("adam_quantile", self.adam_quantile, 0.0, 1.0, lo_open=True)
        validate.non_negative("saturation", self.saturation)
        validate.in_range("lr_final", self.lr_final, 0.0, 1.0)
        validate.integer("spp", self.spp, 1)
        validate.optional(validate.integer, "boundary_spp", self.boundary_spp, 1, 1 << 16)
        validate.optional(validate.integer, "resolution", self.resolution, 8, 4096)
        validate.optional(validate.integer, "target_vertices", self.target_vertices, 100, 2_000_000)
        validate.optional(validate.integer, "min_vertices", self.min_vertices, 1)
        for it in self.remesh_at:
            validate.integer("remesh_at", it, 1)
        validate.integer("checkpoint_every", self.checkpoint_every, 1)
        validate.optional(validate.non_negative, "planarity_weight", self.planarity_weight)
        validate.in_range("border_turn_deg", self.border_turn_deg, 0.0, 180.0, hi_open=True)
        validate.in_range("planarity_angle", self.planarity_angle, 0.0, 180.0, lo_open=True, hi_open=True)
        validate.one_of("planarity_where", self.planarity_where, PLANARITY_WHERE)
        validate.one_of("planarity_select_where", self.planarity_select_where, PLANARITY_WHERE)
        validate.in_range("planarity_min_thickness", self.planarity_min_thickness, 0.0, 1.0, lo_open=True)
        validate.non_negative("planarity_auto_weight", self.planarity_auto_weight)
        validate.in_range("planarity_auto_threshold", self.planarity_auto_threshold, 0.0, 1.0)
        validate.optional(validate.non_negative, "colour_prior_weight", self.colour_prior_weight)
        validate.non_negative("colour_prior_auto_weight", self.colour_prior_auto_weight)
        validate.non_negative("colour_prior_auto_threshold", self.colour_prior_auto_threshold)
        validate.in_range("prior_margin", self.prior_margin, 0.0, 0.5)
        validate.one_of("prior_ties", self.prior_ties, PRIOR_TIES)
        validate.integer("indirect_every", self.indirect_every, 0)
        validate.integer("indirect_spp", self.indirect_spp, 1, 1 << 16)
        validate.one_of("indirect_reference", self.indirect_reference, ("direct", "depth2"))
        validate.integer("indirect_downsample", self.indirect_downsample, 1, 8)
        validate.non_negative("colour_lambda", self.colour_lambda)
        validate.integer("light_select_every", self.light_select_every, 0)
        validate.positive("light_select_colour_lambda", self.light_select_colour_lambda)
        validate.in_range("step_select_quantile", self.step_select_quantile, 0.0, 1.0, lo_open=True)
        validate.positive("step_select_lr", self.step_select_lr)
        validate.seed("seed", self.seed, MORPH_SEED_MAX)
        validate.one_of("refine_cameras", self.refine_cameras, AUTO_ON_OFF)
        validate.one_of("exposure", self.exposure, AUTO_ON_OFF)
        validate.non_negative("lr_camera", self.lr_camera)
        validate.non_negative("camera_weight", self.camera_weight)
        validate.non_negative("lr_exposure", self.lr_exposure)
        validate.integer("env_resolution", self.env_resolution, 2, 256)
        validate.non_negative("lr_env", self.lr_env)
        validate.one_of("flash", self.flash, AUTO_ON_OFF)
        validate.non_negative("lr_flash", self.lr_flash)
        validate.integer("validation_views", self.validation_views, 0)
        validate.in_range("validation_fraction", self.validation_fraction, 0.0, 0.5)
        validate.integer("check_every", self.check_every, 1)
        validate.integer("patience", self.patience, 1)
        validate.non_negative("min_improvement", self.min_improvement)
        validate.integer("min_iterations", self.min_iterations, 0)
        validate.in_range("anneal_fraction", self.anneal_fraction, 0.0, 1.0)
        validate.optional(validate.positive, "lambda_start", self.lambda_start)
        validate.in_range("lambda_warmup", self.lambda_warmup, 0.0, 1.0)
        self.lambda_select = tuple(float(x) for x in self.lambda_select)
        for x in self.lambda_select:
            validate.positive("lambda_select", x)
        if len(set(self.lambda_select)) != len(self.lambda_select):
            raise UsageError(f"lambda_select: repeated candidate in {self.lambda_select}")
        self.planarity_select = tuple(float(x) for x in self.planarity_select)
        for x in self.planarity_select:
            validate.positive("planarity_select", x)
        if len(set(self.planarity_select)) != len(self.planarity_select):
            raise UsageError(f"planarity_select: repeated candidate in {self.planarity_select}")
        if len(self.lambda_select) == 1 and self.lambda_start is None:  # one candidate: nothing to choose
            start = self.lambda_select[0]
            self.lambda_start, self.lambda_select = (start if start > self.lambda_ else None), ()
        if self.early_stop and not self.validation_views:
            raise UsageError("early_stop needs validation_views ≥ 1 (the stopping rule watches their loss)")


