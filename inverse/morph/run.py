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
from dataclasses import KW_ONLY, asdict, dataclass, field, replace
from pathlib import Path
from typing import Literal

import numpy as np

import mi_plugins  # noqa: F401
import drjit as dr
import mitsuba as mi
from mi_plugins.arrays import aligned

from foundation import validate
from foundation.errors import UsageError
from foundation.files import array_key, file_digest
from foundation.loop import (DrJitStage, LoopSettings, RunState, StepResult, TrainingSummary, rng_state, run_loop,
                             set_rng_state)
from foundation.mesh import face_normals, load_mesh_any, read_ply_colours, unique_edges, write_ply
from foundation.mesh_metrics import chamfer
from foundation.records import from_json, to_json
from foundation.optim_state import load_optimizer_state, optimizer_state
from foundation.quantile_adam import QuantileAdam
from foundation.scene import mitsuba_log_level

from .benchmark import MorphBenchmark, sensor_dict
from .evaluate import MorphEvaluation, evaluate_morph
from .prior import colour_prior, dihedral_pairs, dominant_plane_fraction, planarity_prior
from .mesh_edit import (PleatReport, RepairReport, SpikeReport, TurnReport, iron_border_turns, iron_spikes, remesh,
                        repair_flips, undo_flips, unfold_pleats)
from .scene import (MODES, inward_thickness, mask_integrator, mask_scene, morph_scene, photo_l1, photo_masks,
                    photo_saturation, photo_tensors, projective_integrator, render_views, upsample_bilinear, views_seeing)

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
    #: suite's fits were worse at 2 (josie −24.9 % Chamfer, village −49.9 %, against −32.4 / −55.8 % at 4: docs/morph.md)
    #: without the silhouette loss below. With it (the default since 2026-11-29) the masks carry the outlines and 1
    #: is enough: the default (docs/morph.md: "A cheaper mask, and the default").
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
    #: is no flip; face000@0's facing area 0.571 → 0.279 %, docs/morph.md). 0 = off (runs before 2026-11-29, morning). Read
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
    #: As the one default for the whole suite it helped the table and airplane but broke the village (docs/morph.md), so
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
    #: choice (docs/morph.md).
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
    #: (docs/morph.md "The prior only where the photos see"), moved the failing ones within their noise and cost the bunny@0
    #: and bracket@0 4 and 7 points of Chamfer. "thick", the default since 2026-11-29 (docs/morph.md "The prior off thin
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
    #: same 28 of 36 (docs/morph.md: "Priors kept on ties")
    prior_ties: Literal["keep", "drop"] = "keep"
    #: the light the morph's direct-only renders miss (interreflections; the photos are path traced) is estimated
    #: per photo at iteration 0 and every ``indirect_every`` iterations — a path-traced render at the photos' depth
    #: minus direct light (``indirect_reference``), ``indirect_spp`` each, no gradients — and added to that view's
    #: renders until the next estimate ('lit' mode; 0 = off). Off by default and asked of the photos instead
    #: (``light_select_every``): on for every mesh, with ``colour_lambda`` 10, the suite gained on josie (−27 → −32 %
    #: Chamfer), the village (−50 → −56 %), bunny and cow, and lost the airplane (−43 → −37 %) and the table
    #: (−41 → −37 %) below the −40 % target (docs/morph.md)
    indirect_every: int = 0
    indirect_spp: int = 16
    #: what the estimate subtracts from the path-traced render: "direct" (the ``direct`` integrator, its own random
    #: numbers) or "depth2" (the path tracer at depth 2 with the same seed: the first bounce cancels sample for
    #: sample). "depth2" at 16 spp has less noise than "direct" at 64 (RMSE 0.0031 against 0.0050) at a quarter of
    #: the cost (village: 0.024–0.028 against 0.087–0.094 s per iteration); over the suite at seeds 0, 1, 2 it
    #: fitted as the other did (docs/morph.md: "A cheaper light estimate"), where one draw had made josie look worse
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
    #: from −31 to −16 % (docs/morph.md: "The silhouettes set the size of every step"); at iteration 200 of those probes
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
    #: (docs/morph.md: "The silhouettes on their own"). The default 2, with one boundary sample, met every target on
    #: the draws it was run on where the photos alone failed (josie@0–2, face000@0) (docs/morph.md: "A cheaper mask,
    #: and the default"). 0 = photos only (every run before 2026-11-29, evening).
    mask_weight: float = 2.0
    #: the silhouette L1 every ``mask_every``-th step only, at ``mask_every`` × the weight (the same mean gradient),
    #: its renders and the photos' masks at resolution // ``mask_downsample`` (coverage is an area: a coarser mask
    #: still places a silhouette to a fraction of its pixel). Each mask render costs about as much as the photo's
    #: (its silhouettes' boundary samples dominate both); these make it cheaper. The default is full resolution
    #: since 2026-11-29 (ninth session): at 2, mpface@0 left more area facing against the truth than its input, and
    #: full resolution gained Chamfer and PSNR on every draw compared; with the mask render's continuous samples
    #: gone (:func:`~inverse.morph.scene.mask_integrator`) an iteration costs 0.86–0.90 × the issue's recipe
    #: (docs/morph.md: "Full-resolution masks, the default").
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


@dataclass
class TracePoint:
    """One point of a run's convergence record (every ``check_every`` iterations and at the end)."""

    iteration: int
    seconds: float  #: set-up + optimisation time so far (validation renders not counted)
    validation_l1: float | None  #: mean L1 of the validation photos (None without validation views)
    chamfer: float | None = None  #: to the ground truth (20k/200k samples: for the curve, not the headline figure)
    lambda_: float | None = None  #: the large-steps λ in force


@dataclass
class PlanarityDecision:
    """The weight the planarity prior ran with and why."""

    weight: float
    auto: bool  #: decided from the input (``planarity_weight=None``)
    dominant_plane_fraction: float | None  #: share of the input's area on its largest plane (auto only)
    _: KW_ONLY  # added later: results written before them still load
    where: str = "all"  #: :attr:`MorphSettings.planarity_where`
    #: interior edges the prior acted on, of all (``where`` "seen": beside a triangle a fitted photo sees at the start;
    #: "thick": between triangles of parts at least ``planarity_min_thickness`` thick)
    edges: int | None = None
    edges_all: int | None = None


@dataclass
class ColourPriorDecision:
    """The weight the colour prior ran with and why."""

    weight: float
    auto: bool  #: decided from the input (``colour_prior_weight=None``)
    input_colour_step: float | None  #: mean colour step per edge of the coarse input (auto only)


@dataclass(frozen=True)
class Candidate:
    """One schedule of the selection: its λ start (≤ the run's λ: constant λ) and its planarity weight (None: the
    automatic rule's)."""

    lambda_start: float
    planarity: float | None = None
    colour: float | None = None  #: the colour prior's weight (None: the rule's)
    light: bool = False  #: with the light estimate and colour large steps (:attr:`MorphSettings.light_select_every`)
    step: bool = False  #: with the quantile step (:attr:`MorphSettings.step_select_quantile`, ``step_select_lr``)

    @property
    def folder(self) -> str:
        return (f"start_{self.lambda_start:g}" + ("" if self.planarity is None else f"_planarity_{self.planarity:g}")
                + ("" if self.colour is None else f"_colour_{self.colour:g}") + ("_step" if self.step else "")
                + ("_light" if self.light else ""))


@dataclass
class LambdaSelection:
    """How the large-steps λ schedule (and, on inputs without a dominant plane, the planarity prior) was chosen:
    every candidate ran to ``at_iteration`` from the same start."""

    candidates: list[float]  #: λ at the start of each candidate (≤ the run's λ: constant λ)
    at_iteration: int  #: where the validation L1 was compared (the end of the warm-up)
    validation_l1: list[float | None]  #: of each candidate there (its last check, if it stopped sooner)
    chosen: float  #: the λ start of the candidate that continued to the end
    trial_seconds: float  #: time of the candidates not chosen (included in the run's ``seconds``)
    _: KW_ONLY  # added later: decisions written before them still load
    planarity: list[float | None] = field(default_factory=list)  #: each candidate's weight (None: the rule's)
    chosen_planarity: float | None = None  #: the winner's planarity weight (None: the rule's)
    margin: float = 0.0  #: :attr:`MorphSettings.prior_margin` the choice was made with
    ties: str = "drop"  #: :attr:`MorphSettings.prior_ties` the choice was made with (decisions before it: "drop")

    def candidate_list(self) -> list[Candidate]:
        w = self.planarity or [None] * len(self.candidates)
        return [Candidate(x, p) for x, p in zip(self.candidates, w)]

    @property
    def winner(self) -> Candidate:
        return Candidate(self.chosen, self.chosen_planarity)


@dataclass
class ColourSelection:
    """Where the colour rule switched the prior on, the λ selection's winner also ran without it from the same
    start to the selection point; the prior stayed on only where its validation L1 there was below (1 − ``margin``) ×
    the run's without it (:func:`choose_with_margin`)."""

    candidate: str  #: folder of the λ selection's winner (with the prior)
    at_iteration: int
    validation_l1_with: float | None
    validation_l1_without: float | None
    kept: bool  #: the prior stayed on
    trial_seconds: float  #: time of the run not continued, to the selection point (included in ``seconds``)
    _: KW_ONLY
    margin: float = 0.0  #: :attr:`MorphSettings.prior_margin` the choice was made with
    ties: str = "drop"  #: :attr:`MorphSettings.prior_ties` the choice was made with (decisions before it: "drop")


@dataclass
class StepSelection:
    """Where the run's own step is uniform Adam (``adam_quantile`` 1), the winner so far also ran with the quantile
    step from the same start to the selection point; it continued only where its validation L1 there was below
    (1 − ``margin``) × the winner's (it changes the optimiser, not the model: the photos must ask for it)."""

    candidate: str  #: folder of the winner so far (uniform Adam)
    at_iteration: int
    validation_l1_uniform: float | None
    validation_l1_quantile: float | None
    kept: bool  #: the run with the quantile step continued
    trial_seconds: float  #: time of the run not continued, to the selection point (included in ``seconds``)
    _: KW_ONLY
    quantile: float  #: ``adam_quantile`` of the run with it
    lr: float  #: its ``lr``
    margin: float = 0.0


@dataclass
class LightSelection:
    """Where the light estimate and colour large steps were off, the winner so far also ran with them from the same
    start to the selection point; they stayed on only where that run's validation L1 there was below
    (1 − ``margin``) × the winner's. Both L1 are measured the same way, after a fresh estimate of the missing light
    on each run's own mesh (:func:`validation_l1_with_light`), so they differ by their meshes and colours only."""

    candidate: str  #: folder of the winner so far (without)
    at_iteration: int
    validation_l1_without: float | None
    validation_l1_with: float | None
    kept: bool  #: the run with them continued
    trial_seconds: float  #: the run not continued, to the selection point, and both measurements
    _: KW_ONLY
    every: int  #: ``indirect_every`` of the run with them
    colour_lambda: float
    margin: float = 0.0
    #: the estimate both were scored with and the run with them used (``indirect_spp``, ``indirect_reference``,
    #: ``indirect_downsample``); None in decisions made before they were recorded, which are taken as made (a
    #: decision with ``spp`` but no ``downsample`` was made at the fitting resolution, 1)
    spp: int | None = None
    reference: str | None = None
    downsample: int | None = None


@dataclass
class MorphResult(MorphEvaluation):
    """``metrics.json`` of a morph run."""

    seconds: float  #: set-up of the last call + optimisation time over all calls (evaluation not counted)
    iterations: int
    vertices: int
    method: str  #: "large_steps", "plain" (per-vertex Adam) or "gcn"
    settings: MorphSettings
    training: TrainingSummary
    planarity: PlanarityDecision | None = None
    colour_prior: ColourPriorDecision | None = None
    repair: RepairReport | None = None
    pleats: PleatReport | None = None  #: the final ironing of pleats (after the unfolding of flips)
    spike_ironing: SpikeReport | None = None  #: spikes the repairs left, brought back to their neighbours (last)
    border_turns: TurnReport | None = None  #: curls of the open border ironed (after the flip repair)
    pretrain_loss_last: float | None = None  #: GCN only: identity pre-training
    trace: list[TracePoint] = field(default_factory=list)
    stopped_early: bool = False  #: the validation loss stopped improving before ``settings.iterations``
    validation_views: list[int] = field(default_factory=list)  #: training photos kept out of the fit
    validation_seconds: float = 0.0  #: time spent rendering the validation views (not in ``seconds``)
    trace_chamfer_input: float | None = None  #: the coarse input's Chamfer with the trace's estimator
    lambda_selection: LambdaSelection | None = None  #: when ``settings.lambda_select`` chose the λ schedule
    colour_selection: ColourSelection | None = None  #: when the validation photos decided the colour prior
    light_selection: LightSelection | None = None  #: when they decided the light estimate and colour large steps
    step_selection: StepSelection | None = None  #: when they decided the step (uniform or quantile Adam)
    #: radiance above which pixels stayed out of the loss (``settings.saturation`` × the photos' 99th percentile)
    saturation_level: float = 0.0

    @property
    def trial_seconds(self) -> float:
        """Time of the selection's runs not continued (in ``seconds``, not in the finished run's iterations)."""
        return sum(c.trial_seconds for c in (self.lambda_selection, self.colour_selection, self.light_selection,
                                             self.step_selection) if c is not None)


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

    pymeshlab's remesh of byte-identical input has differed between processes (docs/morph.md, "run-to-run
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


def run_morph(bench: MorphBenchmark, out: str | Path, s: MorphSettings | None = None,
              show_progress: bool = True, budget_iterations: int | None = None) -> MorphResult | None:
    """Morph the benchmark's coarse mesh; write morphed.ply, held-out renders, metrics.json; resumable.

    ``budget_iterations`` stops after that many iterations *in this call* (e.g. a cluster job's
    wall-time slice) with a checkpoint written, and returns None; calling again with the same
    settings continues exactly.
    """
    s = s or MorphSettings()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    if selection_point(s) is not None:
        return _run_selected(bench, out, s, show_progress, budget_iterations)
    stage = MorphStage(bench, out, s)
    try:
        return run_loop(stage, LoopSettings(steps=s.iterations, checkpoint_every=s.checkpoint_every),
                        checkpoint=out / "checkpoint.npz", budget_steps=budget_iterations,
                        show_progress=show_progress, metrics_path=out / "metrics.json")
    finally:
        stage.close()


# -- λ decided from the input ------------------------------------------------------------------------------------


def selection_point(s: MorphSettings) -> int | None:
    """The iteration where the selection's candidates are compared, or None when no choice is to be made
    (``lambda_start`` set, fewer than two candidates, plain Adam, no validation photos, or a cap that ends before
    the warm-up does)."""
    n = len(s.lambda_select) + (len(s.planarity_select) if s.planarity_weight is None else 0)
    if s.lambda_start is not None or n < 2 or s.parameterisation != "large_steps" or not s.validation_views:
        return None
    at = int(np.ceil(s.lambda_warmup * s.iterations / s.check_every)) * s.check_every
    return at if 0 < at < s.iterations else None


def selection_candidates(s: MorphSettings, prior_on: bool) -> list[Candidate]:
    """The λ candidates (planarity by the rule), then the planarity weights at constant λ unless the rule has
    already switched the prior on (``prior_on``) or the weight is set."""
    out = [Candidate(x) for x in s.lambda_select] or [Candidate(s.lambda_)]
    if s.planarity_weight is None and not prior_on:
        out += [Candidate(s.lambda_, w) for w in s.planarity_select]
    return out


def choose_with_margin(scores: list[float | None], with_prior: list[bool], margin: float, ties: str = "drop") -> int:
    """Index of the candidate that continues: the lowest score, except that a candidate with a prior wins only where
    it is below (1 − ``margin``) × the best score without one; no scores (no validation photos): the first.
    ``ties`` "keep": the other way round — the best candidate with a prior continues unless the best one without is
    below (1 − ``margin``) × its score."""
    if any(x is None for x in scores):
        return 0
    best = min(range(len(scores)), key=lambda i: scores[i])
    plain = [i for i in range(len(scores)) if not with_prior[i]]
    if ties == "keep":
        prior = [i for i in range(len(scores)) if with_prior[i]]
        if not prior or not plain:
            return best
        simplest, modelled = (min(c, key=lambda i: scores[i]) for c in (plain, prior))
        return simplest if scores[simplest] < (1.0 - margin) * scores[modelled] else modelled
    if with_prior[best] and plain:
        simplest = min(plain, key=lambda i: scores[i])
        if not scores[best] < (1.0 - margin) * scores[simplest]:
            return simplest
    return best


def candidate_settings(s: MorphSettings, c: Candidate) -> MorphSettings:
    """One candidate's own run: its λ start (≤ λ: constant λ) and planarity weight, no selection of its own."""
    out = replace(s, lambda_start=float(c.lambda_start) if c.lambda_start > s.lambda_ else None, lambda_select=(),
                  planarity_select=(), planarity_weight=s.planarity_weight if c.planarity is None else c.planarity,
                  colour_prior_weight=s.colour_prior_weight if c.colour is None else c.colour)
    if c.planarity is not None:  # a weight the photos are asked about: on the edges planarity_select_where says
        out = replace(out, planarity_where=s.planarity_select_where)
    if c.step:
        out = replace(out, adam_quantile=s.step_select_quantile, lr=s.step_select_lr)
    return replace(out, indirect_every=s.light_select_every, colour_lambda=s.light_select_colour_lambda) \
        if c.light else out


def step_select_on(s: MorphSettings) -> bool:
    """Whether the selection asks the photos about the quantile step (the run's own step is uniform Adam)."""
    return s.step_select_quantile < 1.0 and s.adam_quantile == 1.0


def light_select_on(s: MorphSettings) -> bool:
    """Whether the selection asks the photos about the light estimate and colour large steps (both off, lit)."""
    return s.light_select_every > 0 and not s.indirect_every and not s.colour_lambda and s.mode == "lit"


def validation_l1_with_light(bench: MorphBenchmark, folder: Path, s: MorphSettings, at: int) -> float | None:
    """Validation L1 of the run in ``folder`` (settings ``s``, checkpoint at iteration ``at``) after a fresh estimate
    of the light its direct renders miss, on its own mesh and colours (fixed seeds: runs compare like with like)."""
    return _validation_l1s_with_light(bench, folder, s, at, 1)[0]


def _validation_l1s_with_light(bench: MorphBenchmark, folder: Path, s: MorphSettings, at: int,
                               draws: int) -> list[float | None]:
    """:func:`validation_l1_with_light` under ``draws`` draws of the estimate's random numbers (the first: its own)."""
    import tempfile

    from foundation.loop import read_checkpoint

    saved = read_checkpoint(folder / "checkpoint.npz")
    if saved.run.step > at and selection_checkpoint(folder, at).is_file():  # the winner ran on: its state at ``at``
        saved = read_checkpoint(selection_checkpoint(folder, at))
    if saved.run.step != at and not (saved.run.done and saved.run.step < at):  # one that ended sooner: as it ended
        # a winner that ran on before its state at ``at`` was kept: rerunning that one candidate is enough
        raise UsageError(f"{folder}: the light choice compares runs at iteration {at}, this one is at "
                         f"{saved.run.step} (no {selection_checkpoint(folder, at).name}); delete {folder} to rerun "
                         f"it, or {folder.parent} to start over")
    with tempfile.TemporaryDirectory(prefix=".light_", dir=folder) as tmp:
        stage = MorphStage(bench, Path(tmp), replace(s, indirect_every=s.indirect_every or 1))
        try:
            stage.load_state(saved.stage)
            out = []
            for k in range(draws):
                stage.estimate_indirect(stage.val_ids, draw=k)
                out.append(stage.validation_l1())
            return out
        finally:
            stage.close()


def light_choice_draws(bench: MorphBenchmark, out: Path, s: MorphSettings, draws: int = 4) -> dict | None:
    """The stored light choice of the run in ``out`` (settings ``s``) scored again under ``draws`` draws of the
    estimate's random numbers (draw 0: the choice's own, which reproduces its stored scores): how much of the
    decision the estimate's draw decides. None where no light choice was made. Per draw the L1 of both runs at the
    selection point, the light run's advantage 1 − with / without, whether that draw keeps the light run."""
    validate.integer("draws", draws, 1, 64)
    path = Path(out) / "lambda_select" / "light_decision.json"
    if not path.is_file():
        return None
    from foundation.files import read_json

    d = from_json(LightSelection, read_json(path, "light selection"), str(path))
    estimate = (s.indirect_spp, s.indirect_reference, s.indirect_downsample)
    if d.spp is not None and (d.spp, d.reference, d.downsample or 1) != estimate:
        raise UsageError(f"{path}: scored with the estimate {d.reference} at {d.spp} spp, 1/{d.downsample or 1} "
                         f"resolution; these settings estimate {estimate[1]} at {estimate[0]} spp, 1/{estimate[2]}")
    plain = replace(s, indirect_every=0, colour_lambda=0.0)
    step = path.with_name("step_decision.json")
    if d.candidate.endswith("_step"):  # both runs took the quantile step the photos chose
        if not step.is_file():
            raise UsageError(f"{path}: made on {d.candidate}, but {step.name} (its step) is missing; delete "
                             f"{path.parent} to start over")
        st = from_json(StepSelection, read_json(step, "step selection"), str(step))
        plain = replace(plain, adam_quantile=st.quantile, lr=st.lr)
    light = replace(plain, indirect_every=d.every, colour_lambda=d.colour_lambda)
    folder = Path(out) / "lambda_select" / d.candidate
    without = _validation_l1s_with_light(bench, folder, plain, d.at_iteration, draws)
    with_ = _validation_l1s_with_light(bench, folder.with_name(d.candidate + "_light"), light, d.at_iteration, draws)
    adv = [1.0 - w / o for w, o in zip(with_, without)]
    keeps = [w < (1.0 - d.margin) * o for w, o in zip(with_, without)]
    return {"candidate": d.candidate, "at_iteration": d.at_iteration, "margin": d.margin, "kept": d.kept,
            "stored_advantage": 1.0 - d.validation_l1_with / d.validation_l1_without
            if d.validation_l1_with and d.validation_l1_without else None,
            "validation_l1_without": without, "validation_l1_with": with_, "advantage": adv,
            "advantage_sd": float(np.std(adv, ddof=1)) if draws > 1 else None,
            "keeps": keeps, "draws_against_stored": int(sum(k != d.kept for k in keeps))}


def _trial_dir(out: Path, c: Candidate) -> Path:
    return out / "lambda_select" / c.folder


def selection_checkpoint(folder: Path, at: int) -> Path:
    """Where the winner's state at the selection point is kept before it runs on (a light choice remade later, e.g.
    under another estimate, scores each run's mesh as it was there)."""
    return folder / f"checkpoint_at_{at}.npz"


def _trial_status(ckpt: Path, at: int | None = None) -> tuple[int, bool, float | None, float]:
    """(step, finished, validation L1, seconds) of a candidate's checkpoint at its last trace point, or at its last
    point up to iteration ``at`` (the winner's folder runs on past the selection point; a decision remade later must
    read the figures it was made from)."""
    from foundation.loop import read_checkpoint

    if not ckpt.is_file():
        return 0, False, None, 0.0
    saved = read_checkpoint(ckpt)
    trace = saved.stage.get("trace") or []
    upto = [t for t in trace if at is None or t.get("iteration", 0) <= at] or trace
    last = upto[-1] if upto else {}
    return int(saved.run.step), bool(saved.run.done), last.get("validation_l1"), float(last.get("seconds") or 0.0)


def _advance(bench: MorphBenchmark, folder: Path, s: MorphSettings, at: int, show_progress: bool,
             budget: int | None) -> tuple[bool, int | None]:
    """Run a trial to iteration ``at`` (resumable): whether it got there, and the budget left (None: no budget)."""
    step, done, _, _ = _trial_status(folder / "checkpoint.npz")
    todo = 0 if done else at - step
    if todo <= 0:
        return True, budget
    if budget is not None and budget <= 0:
        return False, budget
    n = todo if budget is None else min(todo, budget)
    run_morph(bench, folder, s, show_progress, budget_iterations=n)
    return n == todo, None if budget is None else budget - n


def _advance_each(bench: MorphBenchmark, out: Path, s: MorphSettings, cands, at: int, show_progress: bool,
                  budget: int | None) -> tuple[bool, int | None]:
    """:func:`_advance` for each candidate of the selection in turn, each in its own folder with its own settings."""
    for c in cands:
        reached, budget = _advance(bench, _trial_dir(out, c), candidate_settings(s, c), at, show_progress, budget)
        if not reached:
            return False, budget
    return True, budget


def colour_rule_on(bench: MorphBenchmark, s: MorphSettings) -> bool:
    """Whether the rule (not a given weight) switches the colour prior on for this benchmark's input."""
    if s.colour_prior_weight is not None:
        return False
    v, f, c = read_ply_colours(bench.coarse)
    return decide_colour_prior(c, f, s).weight > 0


def _ties(ties: str) -> str:
    return "" if ties == "drop" else f", ties {ties}"


def _decision_file(path: Path, cls: type, what: str, made_for, wanted: tuple, describe, make):
    """One choice of the selection (λ and planarity, colour prior, light): read from ``path`` — refused, naming the
    file, where ``made_for(decision) != wanted`` (``describe`` says what it was made for) — or made by ``make``
    (None: the iteration budget ran out first) and written there."""
    from foundation.files import read_json, write_json

    if path.is_file():
        d = from_json(cls, read_json(path, what), str(path))
        if made_for(d) != wanted:
            raise UsageError(f"{path}: made for {describe(d)}; delete {path.parent} to start over")
        return d
    d = make()
    if d is not None:
        write_json(path, to_json(d))
    return d


def _run_selected(bench: MorphBenchmark, out: Path, s: MorphSettings, show_progress: bool,
                  budget: int | None) -> MorphResult | None:
    """Every candidate (:func:`selection_candidates`) to the selection point, then the one with the lowest
    validation L1 to the end, in ``OUT/lambda_select/<candidate>`` (each resumable); the winner's files are copied
    into ``out`` with the choice recorded. ``budget`` counts iterations of this call over all candidates."""
    import shutil

    from foundation.files import atomic_path, write_json

    at = selection_point(s)
    prior_on = False
    if s.planarity_weight is None and s.planarity_select:  # the rule first: the input remeshed (memoised) as run
        prior_on = decide_planarity(*start_mesh(bench, s)[1][:2], s).weight > 0
    cands = selection_candidates(s, prior_on)

    def decide_lambda() -> LambdaSelection | None:
        nonlocal budget
        reached, budget = _advance_each(bench, out, s, cands, at, show_progress, budget)
        if not reached:
            return None
        status = {c: _trial_status(_trial_dir(out, c) / "checkpoint.npz", at) for c in cands}
        scores = [status[c][2] for c in cands]
        # planarity candidates carry a prior the λ candidates do not (those take the rule's weight, off here)
        chosen = cands[choose_with_margin(scores, [c.planarity is not None for c in cands], s.prior_margin,
                                          s.prior_ties)]
        return LambdaSelection([c.lambda_start for c in cands], at, scores, chosen.lambda_start,
                               float(sum(status[c][3] for c in cands if c != chosen)),
                               planarity=[c.planarity for c in cands], chosen_planarity=chosen.planarity,
                               margin=s.prior_margin, ties=s.prior_ties)

    sel = _decision_file(
        out / "lambda_select" / "decision.json", LambdaSelection, "λ selection",
        lambda d: (d.candidate_list(), d.at_iteration, d.margin, d.ties), (cands, at, s.prior_margin, s.prior_ties),
        lambda d: f"candidates {[c.folder for c in d.candidate_list()]} at iteration {d.at_iteration} with "
                  f"prior_margin {d.margin:g}{_ties(d.ties)}, not {[c.folder for c in cands]} at {at} with "
                  f"{s.prior_margin:g}{_ties(s.prior_ties)}",
        decide_lambda)
    if sel is None:
        return None
    winner, extra, colour, light = sel.winner, 0.0, None, None
    if colour_rule_on(bench, s):  # then the winner without the colour prior, to the same point: the photos decide
        twin = replace(winner, colour=0.0)

        def decide_colour() -> ColourSelection | None:
            nonlocal budget
            reached, budget = _advance(bench, _trial_dir(out, twin), candidate_settings(s, twin), at, show_progress,
                                       budget)
            if not reached:
                return None
            with_l1 = sel.validation_l1[sel.candidate_list().index(winner)]
            _, _, without_l1, _ = _trial_status(_trial_dir(out, twin) / "checkpoint.npz", at)
            # no scores (no validation photos): the rule's choice stands
            kept = without_l1 is None or with_l1 is None or \
                choose_with_margin([without_l1, with_l1], [False, True], s.prior_margin, s.prior_ties) == 1
            lost = _trial_dir(out, twin if kept else winner) / "checkpoint.npz"
            return ColourSelection(winner.folder, at, with_l1, without_l1, kept, _trial_status(lost, at)[3],
                                   margin=s.prior_margin, ties=s.prior_ties)

        colour = _decision_file(
            out / "lambda_select" / "colour_decision.json", ColourSelection, "colour-prior selection",
            lambda d: (d.candidate, d.at_iteration, d.margin, d.ties), (winner.folder, at, s.prior_margin, s.prior_ties),
            lambda d: f"{d.candidate} at iteration {d.at_iteration} with prior_margin {d.margin:g}{_ties(d.ties)}, "
                      f"not {winner.folder} at {at} with {s.prior_margin:g}{_ties(s.prior_ties)}", decide_colour)
        if colour is None:
            return None
        extra += colour.trial_seconds
        if not colour.kept:
            winner = twin
    step = None
    if step_select_on(s):  # then the winner with the quantile step, to the same point: the photos decide
        twin = replace(winner, step=True)

        def decide_step() -> StepSelection | None:
            nonlocal budget
            reached, budget = _advance_each(bench, out, s, (winner, twin), at, show_progress, budget)
            if not reached:
                return None
            l1 = [_trial_status(_trial_dir(out, c) / "checkpoint.npz", at)[2] for c in (winner, twin)]
            kept = None not in l1 and choose_with_margin(l1, [False, True], s.prior_margin) == 1
            lost = _trial_dir(out, winner if kept else twin) / "checkpoint.npz"
            return StepSelection(winner.folder, at, l1[0], l1[1], kept, _trial_status(lost, at)[3],
                                 quantile=s.step_select_quantile, lr=s.step_select_lr, margin=s.prior_margin)

        step = _decision_file(
            out / "lambda_select" / "step_decision.json", StepSelection, "step selection",
            lambda d: (d.candidate, d.at_iteration, d.margin, d.quantile, d.lr),
            (winner.folder, at, s.prior_margin, s.step_select_quantile, s.step_select_lr),
            lambda d: f"{d.candidate} at iteration {d.at_iteration} with prior_margin {d.margin:g}, quantile "
                      f"{d.quantile:g}, lr {d.lr:g}; not for these settings", decide_step)
        if step is None:
            return None
        extra += step.trial_seconds
        if step.kept:
            winner = twin
    if light_select_on(s):  # then the winner with the light estimate and colour large steps: the photos decide
        twin = replace(winner, light=True)

        def decide_light() -> LightSelection | None:
            nonlocal budget
            reached, budget = _advance_each(bench, out, s, (winner, twin), at, show_progress, budget)
            if not reached:
                return None
            t0 = time.perf_counter()
            l1 = [validation_l1_with_light(bench, _trial_dir(out, c), candidate_settings(s, c), at)
                  for c in (winner, twin)]
            kept = None not in l1 and choose_with_margin(l1, [False, True], s.prior_margin) == 1
            lost = _trial_dir(out, winner if kept else twin) / "checkpoint.npz"
            return LightSelection(winner.folder, at, l1[0], l1[1], kept,
                                  _trial_status(lost, at)[3] + time.perf_counter() - t0,
                                  every=s.light_select_every, colour_lambda=s.light_select_colour_lambda,
                                  margin=s.prior_margin, spp=s.indirect_spp, reference=s.indirect_reference,
                                  downsample=s.indirect_downsample)

        estimate = (s.indirect_spp, s.indirect_reference, s.indirect_downsample)
        light = _decision_file(
            out / "lambda_select" / "light_decision.json", LightSelection, "light selection",
            lambda d: (d.candidate, d.at_iteration, d.margin, d.every, d.colour_lambda,
                       estimate if d.spp is None else (d.spp, d.reference, d.downsample or 1)),
            (winner.folder, at, s.prior_margin, s.light_select_every, s.light_select_colour_lambda, estimate),
            lambda d: f"{d.candidate} at iteration {d.at_iteration} with prior_margin {d.margin:g}, every {d.every}, "
                      f"colour λ {d.colour_lambda:g}" +
                      ("" if d.spp is None else
                       f", estimate {d.reference} at {d.spp} spp, 1/{d.downsample or 1} resolution") +
                      "; not for these settings", decide_light)
        if light is None:
            return None
        extra += light.trial_seconds
        if light.kept:
            winner = twin
    if budget is not None and budget <= 0:
        return None
    win = _trial_dir(out, winner)
    kept = selection_checkpoint(win, at)
    if not kept.is_file() and _trial_status(win / "checkpoint.npz")[0] == at:
        with atomic_path(kept) as tmp:
            shutil.copyfile(win / "checkpoint.npz", tmp)
    r = run_morph(bench, win, candidate_settings(s, winner), show_progress, budget_iterations=budget)
    if r is None:
        return None
    for f in sorted(win.iterdir()):
        if f.is_file() and not f.name.startswith(("checkpoint", ".")) and f.name != "metrics.json":
            with atomic_path(out / f.name) as tmp:
                shutil.copyfile(f, tmp)
    r = replace(r, settings=s, lambda_selection=sel, colour_selection=colour, light_selection=light,
                step_selection=step,
                seconds=r.seconds + sel.trial_seconds + extra)
    write_json(out / "metrics.json", to_json(r))
    return r

