"""What a morph run records: its convergence trace, the choices the validation photos made (one decision
record each, kept in ``OUT/lambda_select/``) and the result (:class:`MorphResult`)."""

from __future__ import annotations

from dataclasses import KW_ONLY, dataclass, field


import mi_plugins  # noqa: F401

from foundation.loop import (TrainingSummary)

from .evaluate import MorphEvaluation
from .mesh_edit import (PleatReport, RepairReport, SpikeReport, TurnReport)

from .settings import MorphSettings


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
    unlit: bool = False  #: in 'unlit' mode (:class:`ModeSelection`)

    @property
    def folder(self) -> str:
        return (f"start_{self.lambda_start:g}" + ("" if self.planarity is None else f"_planarity_{self.planarity:g}")
                + ("" if self.colour is None else f"_colour_{self.colour:g}") + ("_step" if self.step else "")
                + ("_light" if self.light else "") + ("_unlit" if self.unlit else ""))


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
class ModeSelection:
    """Where the light is fitted (a capture), the 'lit' winner so far also ran in 'unlit' mode (vertex colours as
    radiance, the light baked in as photogrammetry textures have it) from the same start to the selection point;
    'lit' continued only where its validation L1 there was below (1 − ``margin``) × the unlit run's (it models more:
    the photos must ask for it)."""

    candidate: str  #: folder of the winner so far ('lit')
    at_iteration: int
    validation_l1_lit: float | None
    validation_l1_unlit: float | None
    kept: bool  #: the unlit run continued
    trial_seconds: float  #: the run not continued, to the selection point (included in ``seconds``)
    _: KW_ONLY
    margin: float = 0.0


@dataclass
class PhotoFit:
    """What a run fitted beside the mesh where the photos needed it (:mod:`inverse.morph.photo_model`)."""

    mode: str  #: the appearance model the run ended with ('lit' under the fitted light, or 'unlit')
    refined_cameras: bool
    exposure: bool
    fitted_light: bool
    train_views: list[int]  #: the photos fitted (the corrections below are theirs, in this order)
    #: how far the refined cameras moved from the imported poses (degrees, × scene size)
    camera_movement: dict | None = None
    camera_rotation: list | None = None  #: per fitted photo, the rotation vector (radians, world axes)
    camera_shift: list | None = None  #: per fitted photo, the centre's shift (world units)
    #: per photo, its RGB gain (held-out and validation photos: their two nearest fitted cameras' mean, moved by the
    #: ratio of the EXIF exposures)
    gains: dict | None = None
    #: how the fitted gains follow the photos' EXIF exposures (log-log slope, 0–1); a held-out gain follows it
    exposure_slope: float | None = None
    environment: str | None = None  #: the fitted environment map, in the run folder
    focal_scale: float | None = None  #: the shared focal length's factor, where refined (``refine_focal``)
    flash: list | None = None  #: the fitted flash's RGB intensity (W/sr, the capture's length unit), where modelled
    flash_photos: list | None = None  #: the photos it lit (their indices)
    #: where the silhouettes came from: "capture" (its masks), "backdrop" (derived, :mod:`inverse.capture.backdrop`),
    #: "none" (the photos alone); ``backdrop``: what the backdrop test saw (``BackdropDecision.to_json``)
    masks: str | None = None
    backdrop: dict | None = None


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
    photo_fit: PhotoFit | None = None  #: the cameras, gains and light fitted with the mesh (captures)
    mode_selection: ModeSelection | None = None  #: when the validation photos chose 'lit' or 'unlit'

    @property
    def trial_seconds(self) -> float:
        """Time of the selection's runs not continued (in ``seconds``, not in the finished run's iterations)."""
        return sum(c.trial_seconds for c in (self.lambda_selection, self.colour_selection, self.light_selection,
                                             self.step_selection, self.mode_selection) if c is not None)


