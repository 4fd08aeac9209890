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
#: how a tied prior choice goes (:attr:`MorphSettings.prior_ties`)
PRIOR_TIES = ("keep", "drop")
#: the light estimate's render seeds are 9_000_011 + view (+ this × the draw, for :func:`light_choice_draws`)
ESTIMATE_DRAW_STRIDE = 1_000_003


@dataclass
class MorphSettings:
    #: the cap; with ``early_stop`` a run anneals and ends once its validation loss stops improving (cow of the
    #: suite: 300 fixed −36 % Chamfer; cap 600, stopped at 375: −45 %)
    iterations: int = 600
    views_per_step: int = 3
    mode: Literal["unlit", "lit"] = "lit"
    parameterisation: Literal["large_steps", "plain"] = "large_steps"
    lambda_: float = 2.0  #: large-steps λ
    lr: float = 0.05  #: × scene size / 10, for positions (uniform Adam on u); 0 = positions frozen (colour-only fit)
    lr_colour: float = 0.02  #: village 300 it: −51.6 % / +3.3 dB (0.01: −50.3 % / +3.0 dB); armadillo unchanged (−57 %)
    lr_final: float = 0.1  #: learning rates decay linearly to this fraction (fewer late flips)
    #: large steps: the quantile of Adam's second moments that sets the one step scale of u
    #: (:class:`foundation.quantile_adam.QuantileAdam`); 1 = their maximum, the uniform Adam of Nicolet et al. The
    #: silhouettes' large, noisy gradient sets the maximum, and the shading gradient elsewhere then moves the
    #: surface by a tiny fraction of ``lr`` (the cow at seed 1 stalls at −15 % after 25 iterations)
    adam_quantile: float = 1.0
    spp: int = 4
    #: samples per pixel of the silhouettes' gradient (the projective integrator's primarily visible
    #: discontinuities); None = ``spp``. They cost more than the image's own samples (village, 2 threads: the
    #: backward pass 0.51 s at 4, 0.43 s at 2, 0.30 s at 1); an unbiased estimate at any count (tested), but the
    #: suite's fits were worse at 2 (josie −24.9 % Chamfer, village −49.9 %, against −32.4 / −55.8 % at 4: docs/results/morph.md)
    #: without the silhouette loss below. With it (the default since 2026-11-29) the masks carry the outlines and 1
    #: is enough: the default (docs/results/morph.md: "A cheaper mask, and the default").
    boundary_spp: int | None = 1
    resolution: int | None = None  #: None = the benchmark's photo resolution
    remesh_input: bool = True  #: isotropic remesh of the input first (decimators leave slivers that flip)
    target_vertices: int | None = None  #: remesh the input to about this many vertices (None: see min_vertices)
    #: without a target, a coarser input is remeshed up to about this many vertices: coarse reconstructions lack the
    #: vertices to take the shape (village −12% Chamfer at its 4k, −23% at 10k; armadillo −46% / −54%)
    min_vertices: int | None = 10_000
    remesh_at: tuple[int, ...] = ()  #: iterations after which to remesh isotropically (pymeshlab)
    checkpoint_every: int = 20
    forbid_flips: bool = False  #: undo a step at vertices of triangles it flips w.r.t. the start
    #: after the run, unfold triangles flipped w.r.t. the start, then iron out pleats (local smoothing; reported)
    repair_flips: bool = True
    #: with ``repair_flips``: then the open border's triangles (border and 1-ring) turned more than this many degrees
    #: from the start are ironed back into line with their neighbours' move (:func:`iron_border_turns`: a curl that
    #: is no flip; face000@0's facing area 0.571 → 0.279 %, docs/results/morph.md). 0 = off (runs before 2026-11-29, morning). Read
    #: only after the last step: a finished run's checkpoint takes a new value.
    border_turn_deg: float = 60.0
    #: weight of the edge-preserving planarity prior (mean over interior edges of ρ(1 − n_a·n_b), ρ(d) = d/(d+σ));
    #: 0 = image loss only (the thesis). Dihedrals well above ``planarity_angle`` (house corners, ridges) are left
    #: alone. None = auto: ``planarity_auto_weight`` for man-made scenes (the input's largest plane holds at least
    #: ``planarity_auto_threshold`` of its area, e.g. a ground plane), else 0 — on organic shapes the prior flattens
    #: real curvature (armadillo, 150 it: weight 0.1 / 0.3 / 1 → Chamfer −47 / −31 / −24 % vs −51 % without).
    planarity_weight: float | None = None
    planarity_angle: float = 20.0  #: degrees; σ = 1 − cos(angle), where the prior's pull starts to fade
    planarity_auto_weight: float = 1.0
    #: the largest plane's share of the remeshed input over the suite's draws at seeds 0–2 (3 for face000): village
    #: 0.47–0.48, table 0.34, pedestal 0.32–0.33; the organic and CAD meshes 0.03–0.21 (face000@3 0.207, bracket@2
    #: 0.199, airplane@1 0.195). Until 2026-11-28 0.2, which put the plane prior (weight 1) on face000@3 (−33.7 %
    #: Chamfer); now the middle of the gap
    planarity_auto_threshold: float = 0.26
    #: training photos kept out of the fit (evenly spread over the orbit) to watch convergence: their L1 every
    #: ``check_every`` iterations is the validation curve; 0 = fit every training photo, no validation
    validation_views: int = 3
    #: at most this share of the training photos goes to validation (few photos: all are fitted, no early stop)
    validation_fraction: float = 0.125
    check_every: int = 25
    #: once the validation L1 has not improved by ``min_improvement`` (relative) for ``patience`` checks (never
    #: before ``min_iterations``), the learning rates anneal linearly to ``lr_final`` over ``anneal_fraction`` × the
    #: iterations made so far (at least ``check_every``), and the run ends. Without it, or until then, they decay
    #: linearly over ``iterations``. Stopping without the anneal left the thin airplane wings noisy (−5 % Chamfer
    #: at 325 of 600 vs −25 % for 300 iterations decayed to the end).
    early_stop: bool = True
    patience: int = 2
    min_improvement: float = 0.005
    min_iterations: int = 150
    anneal_fraction: float = 0.33
    #: large-steps λ schedule: start at ``lambda_start`` (stiffer: smooth early steps while the silhouettes are
    #: far off) and fall geometrically to ``lambda_`` over the first ``lambda_warmup`` of the iterations (the
    #: operator is refactored at each check); None = constant λ. The suite's airplane settled into a bumpy state
    #: within its first 25 iterations at constant λ = 2 (−5 % Chamfer); with 25 → 2 it kept improving (−27 %).
    #: As the one default for the whole suite it helped the table and airplane but broke the village (docs/results/morph.md), so
    #: by default ``lambda_select`` tries both and keeps what the validation photos prefer.
    lambda_start: float | None = None
    lambda_warmup: float = 0.3
    #: λ decided from the input: each start value (≤ ``lambda_``: constant λ) runs to the end of the warm-up
    #: (``lambda_warmup`` × the cap, rounded up to a validation check), and the one whose validation L1 is lowest
    #: there continues (:class:`LambdaSelection`). Used when ``lambda_start`` is None; () = constant λ. Neither
    #: choice suits every mesh: 25 → 2 took the airplane from −5 % to −27 % Chamfer and the table from −24 % to
    #: −41 %, but broke the village.
    lambda_select: tuple[float, ...] = (2.0, 25.0)
    #: the planarity prior decided from the photos too: where the automatic rule leaves it off (no dominant plane),
    #: each of these weights is one more candidate of the selection above (at constant λ), kept only when the
    #: validation photos prefer it by ``prior_margin``. On organic shapes the prior can flatten real curvature (the
    #: armadillo) or remove bumps whose shading the vertex colours absorb (josie, bunny, bone, cow); at iteration
    #: 200 of the suite's candidates the validation L1 ranked them as their Chamfer did on all six meshes with the
    #: choice (docs/results/morph.md).
    #: () = the rule alone.
    planarity_select: tuple[float, ...] = (0.1,)
    #: the edges the planarity prior acts on: "all"; "seen" — only edges beside a triangle that a fitted training
    #: photo sees at the start (:func:`~.scene.views_seeing`); elsewhere no photo tells the prior's flattening from
    #: real shape; "thick" — only edges between two triangles of the start whose part is at least
    #: ``planarity_min_thickness`` thick (:func:`~.scene.inward_thickness`): on a thin part (a leg, an ear, a horn)
    #: a small dihedral angle is the part's own cross-section as often as a bump
    planarity_where: Literal["all", "seen", "thick"] = "all"
    #: ``planarity_where`` of the weights in ``planarity_select`` (the plane rule's prior keeps ``planarity_where``).
    #: "seen" (the photos that prefer such a weight vouch only for what they see), measured over six suite draws
    #: (docs/results/morph.md "The prior only where the photos see"), moved the failing ones within their noise and cost the bunny@0
    #: and bracket@0 4 and 7 points of Chamfer. "thick", the default since 2026-11-29 (docs/results/morph.md "The prior off thin
    #: parts"): two thirds of cow@1's facing area lay on parts thinner than 5 % of its extent, where the prior made it
    #: worse; off them cow@1's facing ended below its input's at each of four render seeds
    planarity_select_where: Literal["all", "seen", "thick"] = "thick"
    #: where ``planarity_where`` is "thick": the least thickness of a part the prior acts on, × the start's largest
    #: extent (the cow's legs, ears and horns lie below 0.05; its body above)
    planarity_min_thickness: float = 0.05
    #: weight of the colour prior (mean over edges of the colour step, :func:`~.prior.colour_prior`): under one fixed
    #: lighting a diffuse point looks the same from every view, so per-vertex colour can absorb the shading of bumps
    #: the photos show, and the photos then pull weakly on the geometry; a piecewise-smooth albedo (Retinex) leaves
    #: that shading to the geometry. None = auto: ``colour_prior_auto_weight`` where the input's own colours are
    #: smooth (mean colour step per edge below ``colour_prior_auto_threshold``), else 0 — textured inputs (the
    #: village's 0.030) hold real albedo steps. Airplane (25 → 2): −27 % Chamfer without, −38 / −43 % at 0.03 /
    #: 0.1.
    #: Where the rule switches it on and the λ selection runs, the winner also runs without it to the selection
    #: point and the validation photos decide by ``prior_margin`` (:class:`ColourSelection`; josie: −24 % with,
    #: −27 % without, and its validation L1 prefers without). A given weight skips both.
    colour_prior_weight: float | None = None
    colour_prior_auto_weight: float = 0.1
    colour_prior_auto_threshold: float = 0.015  #: the suite's smooth-albedo inputs: 0.004–0.006; the village 0.030
    #: a prior the photos are asked about (a planarity candidate, the colour prior) is kept only where its validation
    #: L1 at the selection point is below (1 − ``prior_margin``) × the best run without it: model no more than the
    #: photos ask for. The comparison's own noise, measured over render/view seeds 0, 1, 2 at iteration 200: the
    #: cow's planarity advantage 0.80, 0.37, −0.65 % (SD 0.74 %; a 2-thread run of the bench: 1.01 %), the bunny's
    #: colour-prior advantage 1.07, 0.70, 1.46 % (SD 0.38 %); 0.015 ≈ 2 × the cow's SD. 0 = the lower L1 wins.
    prior_margin: float = 0.015
    #: where the two sides of a prior's choice lie within ``prior_margin`` of each other (a tie): "keep" — the run
    #: with the prior continues (the one without must beat it by the margin); "drop" — the run without it continues
    #: (the prior must win by the margin; the rule before 2026-11-28). The planarity and colour-prior choices; the
    #: light choice always needs its margin (it models more). Over the suite at seeds 0, 1, 2 "keep" changed 13 of
    #: 36 runs, Chamfer +3.9 points on those (10 better, 3 worse), held-out PSNR −0.3 dB, every target met on the
    #: same 28 of 36 (docs/results/morph.md: "Priors kept on ties")
    prior_ties: Literal["keep", "drop"] = "keep"
    #: the light the morph's direct-only renders miss (interreflections; the photos are path traced) is estimated
    #: per photo at iteration 0 and every ``indirect_every`` iterations — a path-traced render at the photos' depth
    #: minus direct light (``indirect_reference``), ``indirect_spp`` each, no gradients — and added to that view's
    #: renders until the next estimate ('lit' mode; 0 = off). Off by default and asked of the photos instead
    #: (``light_select_every``): on for every mesh, with ``colour_lambda`` 10, the suite gained on josie (−27 → −32 %
    #: Chamfer), the village (−50 → −56 %), bunny and cow, and lost the airplane (−43 → −37 %) and the table
    #: (−41 → −37 %) below the −40 % target (docs/results/morph.md)
    indirect_every: int = 0
    indirect_spp: int = 16
    #: what the estimate subtracts from the path-traced render: "direct" (the ``direct`` integrator, its own random
    #: numbers) or "depth2" (the path tracer at depth 2 with the same seed: the first bounce cancels sample for
    #: sample). "depth2" at 16 spp has less noise than "direct" at 64 (RMSE 0.0031 against 0.0050) at a quarter of
    #: the cost (village: 0.024–0.028 against 0.087–0.094 s per iteration); over the suite at seeds 0, 1, 2 it
    #: fitted as the other did (docs/results/morph.md: "A cheaper light estimate"), where one draw had made josie look worse
    indirect_reference: Literal["direct", "depth2"] = "depth2"
    #: the estimate's renders at 1/``indirect_downsample`` of the fitting resolution, upsampled bilinearly: the
    #: indirect light varies slowly across the image, and the upsampling averages the estimate's noise with its
    #: neighbours'. Against a 1024-spp full-resolution reference, 6 training views at 128², 16 spp each: village RMSE
    #: 0.0037 at 2 against 0.0053 at 1 (josie 0.0025 against 0.0034), 3 × cheaper (35 against 108 ms per view);
    #: what the coarser grid cannot hold (1024 spp at 2: RMSE 0.0016, where two full-resolution references differ by
    #: 0.0009) is below the full-resolution estimate's noise; the mean is kept (within 2·10⁻⁵ of 0.0039).
    #: 1 = the fitting resolution (the estimate before 2026-11-28)
    indirect_downsample: int = 2
    #: large-steps λ for the vertex colours (0: plain per-vertex steps): their steps are diffused over the surface
    #: like the positions' (the same operator, Nicolet et al. 2021), so the colours take the smooth part of what the
    #: photos show quickly and the bump-sized part slowly, leaving the bumps' shading to the geometry; the fixed
    #: point is unchanged (a preconditioner, not a prior). Off by default, asked of the photos (``indirect_every``)
    colour_lambda: float = 0.0
    #: the two above decided from the photos, where both are off: the winner of the choices above also runs with
    #: ``indirect_every`` = ``light_select_every`` and ``colour_lambda`` = ``light_select_colour_lambda`` to the
    #: selection point and continues only where its validation L1 there is below (1 − ``prior_margin``) × the
    #: winner's, both measured the same way, after a fresh estimate of the missing light on each run's own mesh
    #: (each run's own validation L1 would compare renders with an estimate against renders without one;
    #: :class:`LightSelection`). 0 = no such candidate.
    light_select_every: int = 100
    light_select_colour_lambda: float = 10.0
    #: the step size asked of the photos too, where ``adam_quantile`` is 1: the winner of the λ and colour choices
    #: also runs with ``adam_quantile`` = ``step_select_quantile`` and ``lr`` = ``step_select_lr`` to the selection
    #: point and continues only where its validation L1 there is below (1 − ``prior_margin``) × the winner's
    #: (:class:`StepSelection`; before the light choice, which then runs with the step kept). No single step serves
    #: the suite: at quantile 0.9 and lr 0.0125 the cow at seed 1 went from −21 to −56 % Chamfer and josie at seed 0
    #: from −31 to −16 % (docs/results/morph.md: "The silhouettes set the size of every step"); at iteration 200 of those probes
    #: the validation L1 was 10 % lower for the cow and 11 % higher for josie. 1 = no such candidate.
    step_select_quantile: float = 0.9
    step_select_lr: float = 0.0125
    #: pixels brighter than ``saturation`` × the training photos' 99th percentile, in the photo or the render, and
    #: their neighbours stay out of the loss (a camera clips there: :func:`~inverse.morph.scene.unsaturated_mask`).
    #: A silhouette against the sun otherwise froze uniform Adam (paul at seed 1: one view's largest gradient
    #: 3,000 times the others'). 0 = every pixel counts (runs before 2026-11-28, evening).
    saturation: float = 4.0
    #: weight of a silhouette L1 beside the photos' (eq. 4.3): the mesh's coverage of each pixel against the photos'
    #: masks (:func:`~inverse.morph.scene.mask_scene`, :func:`~inverse.morph.scene.photo_masks`), the same views
    #: and seeds as the step. Every silhouette then pulls with contrast 1, where the photos' own contrast can be
    #: small (a head's skin against the sky): josie@0's silhouettes moved from 0.37 to only 0.26 px off the truth's
    #: without it (the bunny's 0.58 → 0.15), and its fixed candidate went from −27.4 % to −42.9 % Chamfer with it at 1
    #: (docs/results/morph.md: "The silhouettes on their own"). The default 2, with one boundary sample, met every target on
    #: the draws it was run on where the photos alone failed (josie@0–2, face000@0) (docs/results/morph.md: "A cheaper mask,
    #: and the default"). 0 = photos only (every run before 2026-11-29, evening).
    mask_weight: float = 2.0
    #: the silhouette L1 every ``mask_every``-th step only, at ``mask_every`` × the weight (the same mean gradient),
    #: its renders and the photos' masks at resolution // ``mask_downsample`` (coverage is an area: a coarser mask
    #: still places a silhouette to a fraction of its pixel). Each mask render costs about as much as the photo's
    #: (its silhouettes' boundary samples dominate both); these make it cheaper. The default is full resolution
    #: since 2026-11-29: at 2, mpface@0 left more area facing against the truth than its input, and
    #: full resolution gained Chamfer and PSNR on every draw compared; with the mask render's continuous samples
    #: gone (:func:`~inverse.morph.scene.mask_integrator`) an iteration costs 0.86–0.90 × the issue's recipe
    #: (docs/results/morph.md: "Full-resolution masks, the default").
    mask_every: int = 1
    mask_downsample: int = 1
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


