"""`photoreal bench morph` and its summaries: work folders by seed, the suite chart, draws summed up and compared, light draws, iteration cost."""


import json
import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from foundation.errors import UsageError

from inverse.morph import MorphSettings


ARMADILLO = Path(__file__).resolve().parents[2] / "scenes" / "assets" / "meshes" / "armadillo.ply"


def test_bench_seed_gets_its_own_work_folder(tmp_path):
    """``photoreal bench morph --seed k``: finished pool items are resumed by folder (their metrics.json), so another
    draw must not find seed 0's runs — each seed works in a folder of its own (seed 0 keeps the old name)."""
    from photoreal.benchmarks import work_folder
    from photoreal.benchmarks.morph.bench import MorphBenchSettings
    from photoreal.cli import build_parser
    from photoreal.options import settings_from

    a = build_parser().parse_args(["bench", "morph", "--parts", "suite", "--suite", "josie", "--seed", "3",
                                   "--json", str(tmp_path / "m.json")])
    s = settings_from(MorphBenchSettings, a)
    assert s.seed == 3 and s.suite == ("josie",)
    assert work_folder("morph", s, tmp_path / "m.json") == tmp_path / "morph_work_seed3"
    assert work_folder("morph", MorphBenchSettings(), tmp_path / "m.json") == tmp_path / "morph_work"
    with pytest.raises(UsageError, match="seed"):
        MorphBenchSettings(seed=-1)
    from inverse.morph import MORPH_SEED_MAX  # the runs' own bound, refused before any benchmark is made

    with pytest.raises(UsageError, match=f"seed must be ≤ {MORPH_SEED_MAX}"):
        MorphBenchSettings(seed=MORPH_SEED_MAX + 1)


def _suite_file(path, seed, rows, iterations=600, truth_normals="vertex"):
    """A ``bench morph --parts suite`` result as the bench writes it (the fields the draws' summary reads)."""
    from foundation.files import write_json

    meshes = {}
    for name, (cr, pg, facing_in, facing_out) in rows.items():
        checks = {"chamfer_reduction": cr >= 0.4, "psnr_gain": pg >= 3.0, "no_spikes": True, "no_inverted": True,
                  "facing_not_worse": facing_out <= facing_in, "normal_consistency_up": True}
        meshes[name] = {"kind": "scan", "chamfer_reduction": cr, "psnr_gain_db": pg, "spike_vertices": 0,
                        "inverted_triangles": 0, "seconds": 600.0,
                        "facing_against_truth_area": {"input": facing_in, "start": facing_in, "morphed": facing_out},
                        "normal_consistency": {"input": 0.87, "morphed": 0.93}, "checks": checks,
                        "passes": all(checks.values())}
    failing = {n: [c for c, ok in r["checks"].items() if not ok] for n, r in meshes.items() if not r["passes"]}
    mean = {"chamfer_reduction": float(np.mean([r[0] for r in rows.values()]))}
    write_json(path, {"settings": {"seed": seed, "iterations": iterations, "truth_normals": truth_normals},
                      "suite": {"meshes": meshes, "mean": mean, "failing": failing}})
    return path


def test_suite_chart_tells_every_mesh_apart(tmp_path):
    """The suite chart: the whole suite (13 meshes) gets 13 different lines, and a PNG of both panels is written."""
    import matplotlib.image

    from inverse.morph.suite import SUITE, UNSEEN
    from photoreal.benchmarks.morph.charts import suite_chart, suite_line_style

    names = SUITE + UNSEEN + ("village", "armadillo")
    styles = {(suite_line_style(i)["color"], suite_line_style(i)["ls"]) for i in range(len(names))}
    assert len(names) == 13 and len(styles) == 13
    trace = [{"iteration": k, "seconds": 2.0 * k, "validation_l1": 0.02 / (1 + k), "chamfer": 0.01 / (1 + k)}
             for k in range(0, 50, 10)]
    meshes = {n: {"kind": "scan", "trace": trace, "trace_chamfer_input": 0.01, "chamfer_reduction": 0.85}
              for n in names}
    meshes["bone"].pop("chamfer_reduction")  # a row without the headline figure draws its line alone
    out = suite_chart({"meshes": meshes, "targets": {"chamfer_reduction": 0.4}}, tmp_path / "suite.png")
    img = matplotlib.image.imread(out)
    assert img.shape[0] > 300 and img.shape[1] > 1000


def test_suite_over_draws_sums_up_each_mesh(tmp_path, capsys):
    """``photoreal bench morph-seeds``: per mesh the mean, worst and best over the draws and the draws where every
    target holds; files that are not draws of one experiment are refused by name, nothing written."""
    from photoreal.benchmarks.morph.seeds import seeds_summary
    from photoreal.cli import main

    a = _suite_file(tmp_path / "s0.json", 0, {"josie": (0.323, 3.76, 0.0178, 0.0146),
                                              "cow": (0.488, 8.71, 0.0225, 0.0134)})
    b = _suite_file(tmp_path / "s1.json", 1, {"josie": (0.087, 2.02, 0.0345, 0.0360),
                                              "cow": (0.210, 4.92, 0.0258, 0.0231), "paul": (0.5, 4.0, 0.01, 0.009)})
    c = _suite_file(tmp_path / "s2.json", 2, {"josie": (0.156, 3.66, 0.0213, 0.0273),
                                              "cow": (0.55, 9.0, 0.02, 0.01)})
    s = seeds_summary([c, a, b])
    assert s["seeds"] == [0, 1, 2]
    j = s["meshes"]["josie"]
    assert j["chamfer_reduction"]["mean"] == pytest.approx((0.323 + 0.087 + 0.156) / 3, abs=1e-12)
    assert j["chamfer_reduction"]["worst"] == 0.087 and j["chamfer_reduction"]["best"] == 0.323
    assert j["chamfer_reduction"]["sd"] == pytest.approx(np.std([0.323, 0.087, 0.156], ddof=1), abs=1e-12)
    assert j["psnr_gain_db"]["worst"] == 2.02 and (j["passes"], j["of"]) == (0, 3)
    assert j["per_seed"]["1"]["failing"] == ["chamfer_reduction", "psnr_gain", "facing_not_worse"]
    cow = s["meshes"]["cow"]
    assert (cow["passes"], cow["of"]) == (2, 3) and cow["per_seed"]["1"]["failing"] == ["chamfer_reduction"]
    assert s["meshes"]["paul"]["seeds"] == [1] and s["meshes"]["paul"]["chamfer_reduction"]["sd"] is None
    assert s["every_seed_pass"] == ["paul"]  # over the one draw it has
    assert s["per_seed"]["1"]["passing"] == 1 and s["per_seed"]["1"]["of"] == 3
    out = tmp_path / "seeds" / "morph_seeds.json"
    out.parent.mkdir()
    assert main(["bench", "morph-seeds", str(a), str(b), str(c), "--json", str(out)]) == 0
    written = json.loads(out.read_text())
    assert written["meshes"]["cow"]["chamfer_reduction"]["worst"] == 0.21
    assert (out.parent / "morph_seeds.png").stat().st_size > 10_000
    # refused, naming the file, before anything is written
    other = _suite_file(tmp_path / "o.json", 3, {"josie": (0.3, 3.0, 0.01, 0.01)}, iterations=300)
    twice = _suite_file(tmp_path / "t.json", 1, {"josie": (0.3, 3.0, 0.01, 0.01)})
    (tmp_path / "bad.json").write_text("{not json")
    (tmp_path / "nosuite.json").write_text(json.dumps({"settings": {"seed": 4}, "iteration_cost": {}}))
    for files, msg in (([a], "at least two"), ([a, other], "o.json: settings .* differ"),
                       ([a, b, twice], "t.json: seed 1 again"), ([a, tmp_path / "bad.json"], "bad.json"),
                       ([a, tmp_path / "nosuite.json"], "nosuite.json: not a `photoreal bench morph` result"),
                       ([a, tmp_path / "none.json"], "none.json: no such")):
        out2 = tmp_path / "refused.json"
        assert main(["bench", "morph-seeds", *map(str, files), "--json", str(out2)]) == 2
        assert re.search(msg, capsys.readouterr().err)
        assert not out2.exists() and not (tmp_path / "refused.png").exists()


def test_light_draws_refuses_results_without_their_runs(tmp_path, capsys):
    """``photoreal bench morph-light-draws`` rescores light choices from the runs a suite kept: a result whose work
    folder is gone, or whose runs made no light choice, is refused by name with nothing written; a bad --draws too.
    (The rescoring itself: ``light_choice_draws`` in the λ-selection test; its figures in docs/results/morph.md.)"""
    from photoreal.cli import main

    r = _suite_file(tmp_path / "r.json", 0, {"josie": (0.3, 3.0, 0.01, 0.01)})
    out = tmp_path / "draws.json"
    assert main(["bench", "morph-light-draws", str(r), "--json", str(out)]) == 2
    assert re.search(r"r.json: its work folder .*morph_work is gone \(the bench keeps it unless run with --clean\)",
                     capsys.readouterr().err)
    (tmp_path / "morph_work" / "suite_josie" / "lambda_select").mkdir(parents=True)
    assert main(["bench", "morph-light-draws", str(r), "--json", str(out)]) == 2
    assert "no light choice in these results' work folders" in capsys.readouterr().err
    r1 = _suite_file(tmp_path / "s1" / "r1.json", 1, {"josie": (0.3, 3.0, 0.01, 0.01)})
    (r1.parent / "morph_work_seed1").mkdir()  # seed K's work folder is morph_work_seedK
    assert main(["bench", "morph-light-draws", str(r1), "--json", str(out)]) == 2
    assert "no light choice" in capsys.readouterr().err
    assert main(["bench", "morph-light-draws", str(r), "--draws", "0", "--json", str(out)]) == 2
    assert "draws" in capsys.readouterr().err
    assert not out.exists() and not (tmp_path / "draws.png").exists()


def test_two_settings_compared_draw_by_draw(tmp_path, capsys):
    """``bench morph-seeds NEW… --against BASE…``: a seed run in parts is merged; the two settings are paired by mesh
    and seed (changes, their mean and standard error, wins and losses with a sign test, targets gained and lost) —
    figures against their closed forms; overlapping parts and sets of other experiments are refused, nothing written."""
    from math import comb

    from photoreal.benchmarks.morph.seeds import seeds_compare, seeds_summary
    from photoreal.cli import main

    base = [_suite_file(tmp_path / "b0.json", 0, {"josie": (0.32, 3.8, 0.02, 0.015), "cow": (0.49, 8.7, 0.02, 0.01)}),
            _suite_file(tmp_path / "b1a.json", 1, {"josie": (0.09, 2.0, 0.03, 0.04)}),  # seed 1 in two parts
            _suite_file(tmp_path / "b1b.json", 1, {"cow": (0.21, 4.9, 0.03, 0.02), "paul": (0.5, 4.0, 0.01, 0.009)})]
    new = [_suite_file(tmp_path / "n0.json", 0, {"josie": (0.35, 3.9, 0.02, 0.015), "cow": (0.45, 8.0, 0.02, 0.01),
                                                 "bone": (0.7, 9.0, 0.01, 0.0)}),
           _suite_file(tmp_path / "n1.json", 1, {"josie": (0.42, 3.5, 0.03, 0.02), "cow": (0.30, 5.0, 0.03, 0.02),
                                                 "paul": (0.55, 4.2, 0.01, 0.009)})]
    b = seeds_summary(base)
    assert b["seeds"] == [0, 1] and b["per_seed"]["1"]["of"] == 3 and len(b["per_seed"]["1"]["files"]) == 2
    assert b["per_seed"]["1"]["mean"]["chamfer_reduction"] == pytest.approx((0.09 + 0.21 + 0.5) / 3, abs=1e-12)
    assert set(b["per_seed"]["1"]["failing"]) == {"josie", "cow"}
    c = seeds_compare(seeds_summary(new), b)
    d = [0.35 - 0.32, 0.45 - 0.49, 0.42 - 0.09, 0.30 - 0.21, 0.55 - 0.5]  # josie, cow at 0; josie, cow, paul at 1
    assert c["pairs"] == 5 and "bone" not in c["meshes"]  # bone has no base to pair with
    assert c["chamfer_delta"]["mean"] == pytest.approx(np.mean(d), abs=1e-12)
    assert c["chamfer_delta"]["se"] == pytest.approx(np.std(d, ddof=1) / np.sqrt(5), abs=1e-12)
    assert c["psnr_delta_db"]["mean"] == pytest.approx(np.mean([0.1, -0.7, 1.5, 0.1, 0.2]), abs=1e-12)
    assert (c["wins"], c["losses"]) == (4, 1)
    assert c["sign_test_p"] == pytest.approx(2 * (comb(5, 0) + comb(5, 1)) / 2 ** 5, abs=1e-12)
    assert c["gained"] == ["josie@1"] and c["lost"] == []
    assert c["passes"] == {"base": 2, "new": 3, "of": 5}
    assert c["every_seed_pass"] == {"base": ["paul"], "new": ["paul"]}
    assert c["meshes"]["josie"]["chamfer_delta_mean"] == pytest.approx((0.03 + 0.33) / 2, abs=1e-12)
    out = tmp_path / "cmp" / "morph_seeds.json"
    out.parent.mkdir()
    assert main(["bench", "morph-seeds", *map(str, new), "--against", *map(str, base), "--json", str(out)]) == 0
    written = json.loads(out.read_text())
    assert written["comparison"]["wins"] == 4 and written["against"]["seeds"] == [0, 1]
    assert (out.parent / "morph_seeds_against.png").stat().st_size > 10_000
    # refused, naming the file or the clash, before anything is written
    overlap = _suite_file(tmp_path / "o1.json", 1, {"cow": (0.2, 4.0, 0.03, 0.02)})
    longer = [_suite_file(tmp_path / f"l{k}.json", k, {"josie": (0.3, 3.0, 0.01, 0.01)}, iterations=300)
              for k in (0, 1)]
    apart = [_suite_file(tmp_path / f"a{k}.json", k, {"bunny": (0.5, 8.0, 0.01, 0.005)}) for k in (0, 1)]
    for files, against, msg in (([*base, overlap], new, "o1.json: seed 1 again with cow"),
                                (new, longer, "differ in .* not the same experiment"),
                                (new, apart, "share no mesh"),
                                (new[:1], base, "at least two seeds")):
        out2 = tmp_path / "refused.json"
        assert main(["bench", "morph-seeds", *map(str, files), "--against", *map(str, against),
                     "--json", str(out2)]) == 2
        assert re.search(msg, capsys.readouterr().err)
        assert not out2.exists() and not (tmp_path / "refused_against.png").exists()


def test_the_iteration_cost_bench_times_the_recipes_at_the_same_vertices(small_armadillo, tmp_path):
    from photoreal.benchmarks.morph.bench import MorphBenchSettings, cost_recipes, iteration_cost

    recipes = {k: replace(v, resolution=24, target_vertices=600, min_vertices=None)
               for k, v in cost_recipes(MorphBenchSettings()).items()}
    issue, plain, light = recipes["issue_recipe"], recipes["defaults"], recipes["defaults_light"]
    assert (issue.indirect_every, issue.colour_lambda, issue.validation_views) == (0, 0.0, 0)
    assert (plain.indirect_every, plain.colour_lambda) == (0, 0.0) and plain.validation_views
    assert light.indirect_every and light.colour_lambda and light.validation_views
    # today's recipes carry the bench's silhouette loss and boundary samples (the defaults unless set); the issue's
    # recipe had neither
    assert (issue.mask_weight, issue.boundary_spp) == (0.0, None)
    for r in (plain, light):
        assert (r.mask_weight, r.mask_every, r.mask_downsample, r.boundary_spp) == \
            (MorphSettings.mask_weight, MorphSettings.mask_every, MorphSettings.mask_downsample,
             MorphSettings.boundary_spp)
    other = cost_recipes(MorphBenchSettings(mask_weight=0.0, boundary_spp=None))["defaults_light"]
    assert (other.mask_weight, other.boundary_spp) == (0.0, None)
    out = iteration_cost(small_armadillo, recipes, iterations=2, rounds=2, tmp=tmp_path)
    assert len(set(out["vertices"].values())) == 1 and out["views"]
    for k in recipes:
        assert len(out["blocks"][k]) == 2 and all(b["total"] > 0 for b in out["blocks"][k])
        assert out["s_per_iteration"][k] == pytest.approx(np.median([b["total"] for b in out["blocks"][k]]))
    assert all("light_estimate" in b and "validation" in b for b in out["blocks"]["defaults_light"])
    assert all("validation" in b and "light_estimate" not in b for b in out["blocks"]["defaults"])
    assert not any("light_estimate" in b or "validation" in b for b in out["blocks"]["issue_recipe"])
    assert not list(tmp_path.glob("*/.morph_work.ply"))  # each block's scene freed with its work file
    # the ratio taken round by round: each block over the issue's block of the same round (closed form)
    from photoreal.benchmarks.morph.bench import ratio_by_round
    paired = ratio_by_round({"issue_recipe": [{"total": 0.3}, {"total": 0.4}, {"total": 0.5}],
                             "light": [{"total": 0.33}, {"total": 0.4}, {"total": 0.45}]}, "issue_recipe")
    assert list(paired) == ["light"] and paired["light"]["per_round"] == pytest.approx([1.1, 1.0, 0.9])
    assert (paired["light"]["median"], paired["light"]["min"], paired["light"]["max"]) == pytest.approx((1.0, 0.9, 1.1))


def test_time_to_quality_counts_the_trials_and_the_validation_renders():
    from types import SimpleNamespace as NS

    from inverse.morph.results import TracePoint
    from photoreal.benchmarks.morph.bench import TTQ_GOALS, time_to_quality

    def run(points, validation_seconds=0.0, trials=0.0, seconds=None, vertices=20_000):
        trace = [TracePoint(it, sec, None, chamfer=c) for it, sec, c in points]
        return NS(trace=trace, validation_seconds=validation_seconds, trial_seconds=trials,
                  seconds=seconds if seconds is not None else trace[-1].seconds, iterations=trace[-1].iteration,
                  vertices=vertices, chamfer_morphed=0.0, psnr_heldout_morphed=0.0)

    recipe = run([(0, 1.0, 0.10), (300, 100.0, 0.05), (600, 200.0, 0.04)], validation_seconds=0.0)
    # two checks of 3 s each: the second point's seconds are 20 + 2·3; 50 s of trials count in full
    ours = run([(0, 2.0, 0.10), (25, 20.0, 0.039), (50, 40.0, 0.03)], validation_seconds=9.0, trials=50.0,
               seconds=140.0)
    q = time_to_quality(recipe, ours)
    assert q["target_chamfer"] == 0.04 and q["recipe_seconds"] == 200.0
    assert q["defaults_reached_at_iteration"] == 25
    assert q["defaults_seconds_to_target"] == pytest.approx(20.0 + 2 * 3.0 + 50.0)
    assert q["kept_run_seconds_to_target"] == pytest.approx(20.0 + 2 * 3.0)
    assert q["ratio"] == pytest.approx(76.0 / 200.0) and q["met"]["ratio"] is (76.0 / 200.0 <= TTQ_GOALS["ratio"])
    assert q["defaults_seconds_per_10k_vertices"] == pytest.approx((140.0 + 9.0) / 2)
    never = run([(0, 2.0, 0.10), (50, 40.0, 0.05)])
    q = time_to_quality(recipe, never)
    assert q["ratio"] is None and q["defaults_seconds_to_target"] is None and q["met"]["ratio"] is False
    with pytest.raises(ValueError, match="Chamfer traces"):
        time_to_quality(recipe, run([(0, 1.0, None)]))
