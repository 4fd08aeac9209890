"""The choices the validation photos make (REAL-DIBS §4 leaves λ to the user; here the photos decide): the
candidates run from the same start to one iteration, the lowest validation L1 continues. λ and the planarity prior
are one choice among candidates; the colour prior, the quantile step and the light estimate are each a choice
between the current winner and its twin with one thing changed (:data:`TWIN_CHOICES`, walked in order by
:func:`run_selected`). Every choice is written to ``OUT/lambda_select/`` and read back by a rerun."""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

import numpy as np

import mi_plugins  # noqa: F401

from foundation import validate
from foundation.errors import UsageError
from foundation.mesh import read_ply_colours
from foundation.records import from_json, to_json

from .benchmark import MorphBenchmark

from .results import (Candidate, ColourSelection, LambdaSelection, LightSelection, ModeSelection, MorphResult,
                      StepSelection)
from .settings import (MorphSettings)
from .stage import (MorphStage, decide_colour_prior, decide_planarity, run_stage, start_mesh)


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
    if c.unlit:
        out = replace(out, mode="unlit")
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
    run_stage(bench, folder, s, show_progress, budget_iterations=n)
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


class TwinChoice:
    """One choice between the winner so far and its twin with one thing changed, both run from the same start to
    the selection point: its settings switch (:meth:`on`), the twin, how both are scored, which continues, and the
    decision record written to ``OUT/lambda_select/<file>`` (a rerun reads it back; one made for other settings is
    refused by name)."""

    file: str  #: the decision record's file name
    kind: type  #: its record class
    what: str  #: what it is, in messages
    scoring_counts = False  #: the scoring's own time counts in the record's ``trial_seconds``

    def on(self, bench: MorphBenchmark, s: MorphSettings) -> bool:
        raise NotImplementedError

    def twin(self, winner: Candidate) -> Candidate:
        raise NotImplementedError

    def scores(self, bench, out: Path, s: MorphSettings, sel: LambdaSelection, winner: Candidate, twin: Candidate,
               at: int) -> tuple[float | None, float | None]:
        """The winner's and the twin's validation L1 at the selection point."""
        return tuple(_trial_status(_trial_dir(out, c) / "checkpoint.npz", at)[2] for c in (winner, twin))

    def takes_twin(self, l1_winner, l1_twin, s: MorphSettings) -> bool:
        """The twin continues only when it is lower by the margin (it changes one thing: the photos must ask)."""
        return None not in (l1_winner, l1_twin) and \
            choose_with_margin([l1_winner, l1_twin], [False, True], s.prior_margin) == 1

    def record(self, winner, at, l1_winner, l1_twin, took, seconds, s):
        raise NotImplementedError

    def took_twin(self, d) -> bool:
        return d.kept

    def made_for(self, d, s: MorphSettings) -> tuple:
        """What a record was made for, in the terms of :meth:`wanted` (``s`` fills what old records lack)."""
        raise NotImplementedError

    def wanted(self, winner: Candidate, at: int, s: MorphSettings) -> tuple:
        raise NotImplementedError

    def describe(self, d, winner: Candidate, at: int, s: MorphSettings) -> str:
        raise NotImplementedError


class ColourChoice(TwinChoice):
    """Where the colour rule switched the prior on: the twin runs without it; the prior stays unless the run
    without it is lower by the margin (ties: :attr:`MorphSettings.prior_ties`)."""

    file, kind, what = "colour_decision.json", ColourSelection, "colour-prior selection"

    def on(self, bench, s):
        return colour_rule_on(bench, s)

    def twin(self, winner):
        return replace(winner, colour=0.0)

    def scores(self, bench, out, s, sel, winner, twin, at):
        with_l1 = sel.validation_l1[sel.candidate_list().index(winner)]
        return with_l1, _trial_status(_trial_dir(out, twin) / "checkpoint.npz", at)[2]

    def takes_twin(self, l1_winner, l1_twin, s):
        # no scores (no validation photos): the rule's choice stands
        return not (l1_twin is None or l1_winner is None or
                    choose_with_margin([l1_twin, l1_winner], [False, True], s.prior_margin, s.prior_ties) == 1)

    def record(self, winner, at, l1_winner, l1_twin, took, seconds, s):
        return ColourSelection(winner.folder, at, l1_winner, l1_twin, not took, seconds, margin=s.prior_margin,
                               ties=s.prior_ties)

    def took_twin(self, d):
        return not d.kept  # its record says whether the prior stayed on

    def made_for(self, d, s):
        return d.candidate, d.at_iteration, d.margin, d.ties

    def wanted(self, winner, at, s):
        return winner.folder, at, s.prior_margin, s.prior_ties

    def describe(self, d, winner, at, s):
        return (f"{d.candidate} at iteration {d.at_iteration} with prior_margin {d.margin:g}{_ties(d.ties)}, "
                f"not {winner.folder} at {at} with {s.prior_margin:g}{_ties(s.prior_ties)}")


class StepChoice(TwinChoice):
    """Where the run's step is uniform Adam: the twin scales it by a quantile of Adam's second moments."""

    file, kind, what = "step_decision.json", StepSelection, "step selection"

    def on(self, bench, s):
        return step_select_on(s)

    def twin(self, winner):
        return replace(winner, step=True)

    def record(self, winner, at, l1_winner, l1_twin, took, seconds, s):
        return StepSelection(winner.folder, at, l1_winner, l1_twin, took, seconds, quantile=s.step_select_quantile,
                             lr=s.step_select_lr, margin=s.prior_margin)

    def made_for(self, d, s):
        return d.candidate, d.at_iteration, d.margin, d.quantile, d.lr

    def wanted(self, winner, at, s):
        return winner.folder, at, s.prior_margin, s.step_select_quantile, s.step_select_lr

    def describe(self, d, winner, at, s):
        return (f"{d.candidate} at iteration {d.at_iteration} with prior_margin {d.margin:g}, quantile "
                f"{d.quantile:g}, lr {d.lr:g}; not for these settings")


class LightChoice(TwinChoice):
    """Where the light estimate was off: the twin runs with it and colour large steps; both are scored after a
    fresh estimate on their own meshes (:func:`validation_l1_with_light`)."""

    file, kind, what = "light_decision.json", LightSelection, "light selection"
    scoring_counts = True

    def on(self, bench, s):
        return light_select_on(s) and bench.meta.hdri is not None

    def twin(self, winner):
        return replace(winner, light=True)

    def scores(self, bench, out, s, sel, winner, twin, at):
        return tuple(validation_l1_with_light(bench, _trial_dir(out, c), candidate_settings(s, c), at)
                     for c in (winner, twin))

    def record(self, winner, at, l1_winner, l1_twin, took, seconds, s):
        return LightSelection(winner.folder, at, l1_winner, l1_twin, took, seconds, every=s.light_select_every,
                              colour_lambda=s.light_select_colour_lambda, margin=s.prior_margin,
                              spp=s.indirect_spp, reference=s.indirect_reference, downsample=s.indirect_downsample)

    def made_for(self, d, s):
        # a record without the estimate was made before it was recorded: taken as made with today's
        estimate = (s.indirect_spp, s.indirect_reference, s.indirect_downsample) if d.spp is None else \
            (d.spp, d.reference, d.downsample or 1)
        return d.candidate, d.at_iteration, d.margin, d.every, d.colour_lambda, estimate

    def wanted(self, winner, at, s):
        return (winner.folder, at, s.prior_margin, s.light_select_every, s.light_select_colour_lambda,
                (s.indirect_spp, s.indirect_reference, s.indirect_downsample))

    def describe(self, d, winner, at, s):
        return (f"{d.candidate} at iteration {d.at_iteration} with prior_margin {d.margin:g}, every {d.every}, "
                f"colour λ {d.colour_lambda:g}"
                + ("" if d.spp is None else
                   f", estimate {d.reference} at {d.spp} spp, 1/{d.downsample or 1} resolution")
                + "; not for these settings")


class ModeChoice(TwinChoice):
    """Where the light is fitted (no HDRI known) and the run is 'lit': the twin runs 'unlit'. Unlit models less (no
    light, no shading), so it continues unless the lit run is lower by the margin."""

    file, kind, what = "mode_decision.json", ModeSelection, "mode selection"

    def on(self, bench, s):
        return s.mode_select and s.mode == "lit" and bench.meta.hdri is None

    def twin(self, winner):
        return replace(winner, unlit=True)

    def takes_twin(self, l1_winner, l1_twin, s):
        return None not in (l1_winner, l1_twin) and \
            choose_with_margin([l1_twin, l1_winner], [False, True], s.prior_margin) == 0

    def record(self, winner, at, l1_winner, l1_twin, took, seconds, s):
        return ModeSelection(winner.folder, at, l1_winner, l1_twin, took, seconds, margin=s.prior_margin)

    def made_for(self, d, s):
        return d.candidate, d.at_iteration, d.margin

    def wanted(self, winner, at, s):
        return winner.folder, at, s.prior_margin

    def describe(self, d, winner, at, s):
        return (f"{d.candidate} at iteration {d.at_iteration} with prior_margin {d.margin:g}, not {winner.folder} at "
                f"{at} with {s.prior_margin:g}")


COLOUR, STEP, LIGHT, MODE = ColourChoice(), StepChoice(), LightChoice(), ModeChoice()
#: the choices after λ and the planarity prior, in the order they are made (each starts from the one before's winner)
TWIN_CHOICES = (MODE, COLOUR, STEP, LIGHT)


def run_selected(bench: MorphBenchmark, out: Path, s: MorphSettings, show_progress: bool,
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
    winner, extra, made = sel.winner, 0.0, {}
    for choice in TWIN_CHOICES:  # each: the winner so far against its twin, to the same point; the photos decide
        if not choice.on(bench, s):
            continue
        twin = choice.twin(winner)

        def decide(choice=choice, winner=winner, twin=twin):
            nonlocal budget
            reached, budget = _advance_each(bench, out, s, (winner, twin), at, show_progress, budget)
            if not reached:
                return None
            t0 = time.perf_counter()
            l1_winner, l1_twin = choice.scores(bench, out, s, sel, winner, twin, at)
            took = choice.takes_twin(l1_winner, l1_twin, s)
            lost = _trial_dir(out, winner if took else twin) / "checkpoint.npz"
            seconds = _trial_status(lost, at)[3] + (time.perf_counter() - t0 if choice.scoring_counts else 0.0)
            return choice.record(winner, at, l1_winner, l1_twin, took, seconds, s)

        d = _decision_file(out / "lambda_select" / choice.file, choice.kind, choice.what,
                           lambda d, c=choice: c.made_for(d, s),
                           choice.wanted(winner, at, s), lambda d, c=choice, w=winner: c.describe(d, w, at, s), decide)
        if d is None:
            return None
        extra += d.trial_seconds
        made[choice.file] = d
        if choice.took_twin(d):
            winner = twin
    if budget is not None and budget <= 0:
        return None
    win = _trial_dir(out, winner)
    kept = selection_checkpoint(win, at)
    if not kept.is_file() and _trial_status(win / "checkpoint.npz")[0] == at:
        with atomic_path(kept) as tmp:
            shutil.copyfile(win / "checkpoint.npz", tmp)
    r = run_stage(bench, win, candidate_settings(s, winner), show_progress, budget_iterations=budget)
    if r is None:
        return None
    for f in sorted(win.iterdir()):
        if f.is_file() and not f.name.startswith(("checkpoint", ".")) and f.name != "metrics.json":
            with atomic_path(out / f.name) as tmp:
                shutil.copyfile(f, tmp)
    r = replace(r, settings=s, lambda_selection=sel, colour_selection=made.get(COLOUR.file),
                step_selection=made.get(STEP.file), light_selection=made.get(LIGHT.file),
                mode_selection=made.get(MODE.file),
                seconds=r.seconds + sel.trial_seconds + extra)
    write_json(out / "metrics.json", to_json(r))
    return r

