"""Material diffusion (seed 002 §3.2, §4.4) at toy sizes: the seed's choices against closed forms, tileability,
resume, the dataset build, generation into a neural_btf scene, the evaluation helpers and bad input."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch

import mi_plugins  # noqa: F401
import mitsuba as mi

from foundation.assets import bundled_basis
from foundation.errors import UsageError
from generative.btf import data as md
from generative.btf import train_matdiff
from generative.btf import evaluate as me
from generative.btf import model as mm
from generative.btf import sample as ms
from generative.btf import train as mt
from mi_plugins.neural_basis import check_pair, load_basis, load_material
from photoreal.cli import main

TINY = dict(widths=(16, 32), attention_levels=1, head_dim=16, batch=4, threads=1, checkpoint_every=5,
            max_seconds=None, feature_scale=0.0)


# -- keywords ---------------------------------------------------------------------------------------------------------


def test_keywords_from_maps_and_prompts():
    # Oracle: hand-picked linear colours whose sRGB hue/value fall well inside one named sector.
    assert md.colour_word(np.full((4, 4, 3), (0.6, 0.02, 0.02))) == "red"
    assert md.colour_word(np.full((4, 4, 3), (0.02, 0.02, 0.5))) == "blue"
    assert md.colour_word(np.full((4, 4, 3), 0.01)) == "black"
    assert md.colour_word(np.full((4, 4, 3), 0.2)) == "grey"
    assert md.colour_word(np.full((4, 4, 3), 0.9)) == "white"
    assert md.colour_word(np.full((4, 4, 3), (0.15, 0.05, 0.01))) == "brown"
    assert md.finish_word(np.full(4, 0.2)) == "polished" and md.finish_word(np.full(4, 0.9)) == "rough"
    assert md.parse_keywords("rough red leather") == ["leather", "red", "rough"]
    assert md.parse_keywords("Metal, shiny") == ["metal", None, "polished"]
    with pytest.raises(UsageError, match="unknown word 'velvet'.*fabric"):
        md.parse_keywords("red velvet")
    with pytest.raises(UsageError, match="same slot"):
        md.parse_keywords("wood stone")
    oh = md.keyword_onehots([["wood", None, "satin"]])
    assert oh.shape == (1, 3, len(md.VOCABULARY)) and oh.sum() == 2 and oh[0, 1].sum() == 0
    assert oh[0, 0, md.VOCABULARY.index("wood")] == 1 and oh[0, 2, md.VOCABULARY.index("satin")] == 1


# -- the seed's choices -----------------------------------------------------------------------------------------------


def test_shifted_schedule_scales_snr_and_reaches_the_scheduler():
    s = mm.MatDiffSettings(shift_base=16)
    base = mm.alphas_cumprod(mm.MatDiffSettings(shift_base=0), 32)
    shifted = mm.alphas_cumprod(s, 32)
    ok = (base > 1e-6) & (base < 1 - 1e-6)
    # closed form: SNR_shift = SNR · (16/32)²
    np.testing.assert_allclose((shifted / (1 - shifted))[ok], (base / (1 - base))[ok] * 0.25, rtol=1e-9)
    sched = mm.make_material_scheduler(s, 32)  # betas → cumprod inside diffusers gives ᾱ back (float32)
    np.testing.assert_allclose(sched.alphas_cumprod.numpy(), shifted, rtol=2e-4, atol=1e-7)


def test_min_snr_weight_and_cube_root_round_trip():
    snr = torch.tensor([0.1, 1.0, 5.0, 50.0])
    v = mm.loss_weight(snr, mm.MatDiffSettings(min_snr_gamma=5.0, snr_floor=False))
    np.testing.assert_allclose(v.numpy(), [0.1 / 1.1, 1 / 2, 5 / 6, 5 / 51], rtol=1e-6)
    # the floor: x₀ weight (SNR + 1)·w = min(SNR, γ) + 1 — 1 at pure noise (plain v-loss there), γ + 1 at high SNR
    vf = mm.loss_weight(snr, mm.MatDiffSettings(min_snr_gamma=5.0, snr_floor=True))
    np.testing.assert_allclose((vf * (snr + 1)).numpy(), [1.1, 2, 6, 6], rtol=1e-6)
    np.testing.assert_allclose(mm.loss_weight(torch.tensor([0.0]), mm.MatDiffSettings(snr_floor=True)).numpy(), [1.0])
    e = mm.loss_weight(snr, mm.MatDiffSettings(min_snr_gamma=5.0, prediction="epsilon"))
    np.testing.assert_allclose(e.numpy(), [1, 1, 1, 0.1], rtol=1e-6)
    assert torch.all(mm.loss_weight(snr, mm.MatDiffSettings(min_snr_gamma=0.0)) == 1)
    f = np.random.default_rng(0).normal(0, 2, (2, 16, 8, 8)).astype(np.float32)
    for cube in (True, False):
        s = mm.MatDiffSettings(cube_root=cube, feature_scale=3.0)
        np.testing.assert_allclose(mm.from_model_space(mm.to_model_space(f, s), s), f, rtol=1e-5, atol=1e-5)
        t = torch.from_numpy(f)
        np.testing.assert_allclose(mm.from_model_space(mm.to_model_space(t, s), s).numpy(), f, rtol=1e-5, atol=1e-5)
    s = mm.MatDiffSettings(feature_scale=2.0)
    np.testing.assert_allclose(mm.to_model_space(np.array([-16.0, 2.0, 0.25]), s), [-2.0, 1.0, 0.5], rtol=1e-6)


def test_ddim_with_an_oracle_denoiser_returns_the_data_point():
    # Oracle: for data made of one point x*, the exact v(x_t, t) = α_t ε − σ_t x* with ε = (x_t − α_t x*)/σ_t;
    # DDIM (η = 0) on the shifted schedule must then land on x* (to float32 rounding), with and without clamping.
    s = mm.MatDiffSettings(**{**TINY, "feature_scale": 1.0}, cube_root=False, exemplar_local=False, train_res=16)
    model = mm.build_model(s)
    ac = mm.make_material_scheduler(s, 16).alphas_cumprod
    x_star = torch.rand(1, 16, 16, 16) * 1.6 - 0.8

    def oracle(x, t, local, tokens, class_vec=None):
        a, sg = ac[t].sqrt().view(-1, 1, 1, 1), (1 - ac[t]).sqrt().view(-1, 1, 1, 1)
        return a * (x - a * x_star) / sg - sg * x_star

    model.forward = oracle
    for clip in (None, 1.0):
        out = ms.sample_materials(model, s, [ms.MaterialPrompt()], 16, steps=10, guidance=1.0, clip=clip)
        np.testing.assert_allclose(out[0], x_star[0].numpy(), atol=1e-5)
    # the bench's denoising check: the oracle's x̂₀ is exact; no denoising errs by σ²/α² on average (4096 values:
    # relative sd √(2/4096) = 2.2 %, so 10 % is 4.5 sd)
    rows = me.denoising_check(model, s, x_star.numpy(), [[None, None, None]], timesteps=(39, 319))
    for r in rows:
        assert r["model"] < 1e-8 and r["naive"] == pytest.approx(r["noise_to_signal"] ** 2, rel=0.1)
        assert r["blur"] > r["model"]
    # a 2× texture is sampled on the training size's schedule (a wrong schedule misses x* by O(1))
    x_star = torch.rand(1, 16, 32, 32) * 1.6 - 0.8
    out = ms.sample_materials(model, s, [ms.MaterialPrompt()], 32, steps=10, guidance=1.0)
    np.testing.assert_allclose(out[0], x_star[0].numpy(), atol=1e-5)


def test_circular_padding_makes_the_denoiser_shift_equivariant():
    # Oracle: with periodic boundaries a conv net commutes with circular shifts by a multiple of its total stride
    # (2 here); zero padding breaks this at the borders.
    torch.manual_seed(0)
    x = torch.randn(1, 16, 16, 16)
    loc = torch.randn(1, 3, 16, 16)
    t = torch.tensor([500])
    errs = {}
    for circ in (True, False):
        s = mm.MatDiffSettings(**{**TINY, "feature_scale": 1.0}, circular=circ)
        model = mm.build_model(s).eval()
        tok = model.null_tokens.expand(1, -1, -1)
        with torch.no_grad():
            a = torch.roll(model(x, t, loc, tok), (6, 4), (2, 3))
            b = model(torch.roll(x, (6, 4), (2, 3)), t, torch.roll(loc, (6, 4), (2, 3)), tok)
        errs[circ] = float((a - b).abs().max() / a.abs().max())
    assert errs[True] < 1e-5, errs
    assert errs[False] > 1e-3, errs


# -- data, training, generation ---------------------------------------------------------------------------------------


def _toy_set(n: int = 8, res: int = 8, seed: int = 0) -> md.MaterialSet:
    rng = np.random.default_rng(seed)
    fam = np.arange(n) % 8
    kws = [[md.FAMILIES[f], "grey", "rough"] for f in fam]
    feats = rng.normal(0, 0.3, (n, 16, res, res)).astype(np.float32)
    sw = rng.uniform(0, 0.5, (n, 4, res, res, 3)).astype(np.float32)
    return md.MaterialSet([f"m{i}" for i in range(n)], fam, kws, feats, sw, np.full(n, 30.0), np.zeros(n, bool),
                          load_basis(bundled_basis()).meta.get("id", ""))


def test_training_resumes_exactly_and_generates_into_a_neural_btf_scene(tmp_path, capsys):
    data = _toy_set()
    s = mm.MatDiffSettings(**TINY, steps=6)
    whole = train_matdiff(data, tmp_path / "a", s, show_progress=False)
    assert whole.training.steps == 6 and np.isfinite(whole.training.loss_last)
    assert train_matdiff(data, tmp_path / "b", s, budget_steps=3, show_progress=False) is None
    train_matdiff(data, tmp_path / "b", s, show_progress=False)
    (ma, _), (mb, _) = mt.load_matdiff(tmp_path / "a"), mt.load_matdiff(tmp_path / "b")
    for (k, a), b in zip(ma.state_dict().items(), mb.state_dict().values()):
        assert torch.equal(a, b), k  # one thread: a resumed run is the uninterrupted run, bit for bit

    out = tmp_path / "gen.npz"
    assert main(["btf", "generate", "--run", str(tmp_path / "a"), "--keywords", "rough leather", "--size", "16",
                 "--steps", "3", "--out", str(out)]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["keywords"] == ["leather", None, "rough"] and summary["size"] == 16
    mat = load_material(out, channels=8)
    assert mat.t_off.shape == (16, 16, 8) and np.isfinite(mat.t_rgb).all()
    check_pair(load_basis(bundled_basis()), mat)  # it names the basis it decodes through
    # the same seed gives the same material; an exemplar image conditions too
    main(["btf", "generate", "--run", str(tmp_path / "a"), "--keywords", "rough leather", "--size", "16",
          "--steps", "3", "--out", str(tmp_path / "again.npz")])
    np.testing.assert_array_equal(load_material(tmp_path / "again.npz").t_rgb, mat.t_rgb)
    assert main(["btf", "generate", "--run", str(tmp_path / "a"), "--image", "brick", "--steps", "2",
                 "--out", str(tmp_path / "ex.npz")]) == 0
    capsys.readouterr()
    # a run's recorded sampler (what `bench matdiff` chose) is the default: the same material as those arguments
    assert mt.run_sampler(tmp_path / "a")["source"] == "default"
    mt.save_sampler(tmp_path / "a", 3, 2.0, "test")
    main(["btf", "generate", "--run", str(tmp_path / "a"), "--keywords", "rough leather", "--size", "16",
          "--out", str(tmp_path / "rec.npz")])
    rec = json.loads(capsys.readouterr().out)
    assert rec["steps"] == 3 and rec["guidance"] == 2.0 and rec["sampler_from"].endswith(mt.SAMPLER_FILE)
    np.testing.assert_array_equal(load_material(tmp_path / "rec.npz").t_rgb, mat.t_rgb)
    main(["btf", "generate", "--run", str(tmp_path / "a"), "--keywords", "wood", "--steps", "2", "--size", "8",
          "--out", str(tmp_path / "half.npz")])
    assert json.loads(capsys.readouterr().out)["sampler_from"].startswith("arguments and ")
    for bad in ('{"steps": "many", "guidance": 2}', '{"steps": 2.7, "guidance": 2}'):
        (tmp_path / "a" / mt.SAMPLER_FILE).write_text(bad)
        assert main(["btf", "generate", "--run", str(tmp_path / "a"), "--keywords", "wood", "--out",
                     str(tmp_path / "bad.npz")]) == 2
        assert mt.SAMPLER_FILE in capsys.readouterr().err and not (tmp_path / "bad.npz").exists()
    # both given on the command line: the record is not read
    assert main(["btf", "generate", "--run", str(tmp_path / "a"), "--keywords", "wood", "--steps", "2", "--guidance",
                 "1", "--size", "8", "--out", str(tmp_path / "args.npz")]) == 0
    assert json.loads(capsys.readouterr().out)["sampler_from"] == "arguments"
    (tmp_path / "a" / mt.SAMPLER_FILE).unlink()
    # a random material: keywords drawn from the training materials' triples (recorded by train_matdiff)
    main(["btf", "generate", "--run", str(tmp_path / "a"), "--from-prior", "--seed", "3", "--size", "16",
          "--steps", "2", "--out", str(tmp_path / "prior.npz")])
    drawn = json.loads(capsys.readouterr().out)
    assert drawn["keywords_from_prior"] and drawn["keywords"] in data.keywords
    assert mt.prior_keywords(tmp_path / "a", 1, 3)[0] == drawn["keywords"]
    # 400 draws over 8 equally likely triples miss one with probability < 8·(7/8)⁴⁰⁰ ≈ 5·10⁻²³
    assert {tuple(k) for k in mt.prior_keywords(tmp_path / "a", 400, 0)} == {tuple(k) for k in data.keywords}
    with pytest.raises(UsageError, match="data digest"):  # a prior is recorded only for the run's own materials
        mt.save_keyword_prior(tmp_path / "a", _toy_set(5))
    # the counts are the weights: a triple held by 3 of 4 materials is drawn ~3/4 of the time (2000 draws: ±0.01)
    w = tmp_path / "w"
    w.mkdir()
    (w / mt.PRIOR_FILE).write_text(json.dumps({"triples": [["wood", "red", "rough"], ["metal", "", "polished"]],
                                               "counts": [3, 1]}))
    draws = mt.prior_keywords(w, 2000, 0)
    assert abs(np.mean([k[0] == "wood" for k in draws]) - 0.75) < 0.05 and ["metal", None, "polished"] in draws
    (w / mt.PRIOR_FILE).write_text(json.dumps({"triples": [["wood", "red"]], "counts": [1]}))
    with pytest.raises(UsageError, match="malformed keyword prior"):
        mt.prior_keywords(w, 1, 0)

    scene = mi.load_dict({
        "type": "scene", "integrator": {"type": "direct"},
        "sensor": {"type": "perspective", "fov": 30, "to_world": mi.ScalarTransform4f().look_at([0, 0, 3], [0, 0, 0], [0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 16, "height": 16}},
        "light": {"type": "constant"},
        "plane": {"type": "rectangle", "bsdf": {"type": "neural_btf", "basis": str(bundled_basis()), "material": str(out)}}})
    img = np.asarray(mi.render(scene, spp=4))
    assert np.isfinite(img).all() and img.mean() > 0


def test_bad_input_names_the_thing(tmp_path, capsys):
    assert main(["btf", "generate", "--run", str(tmp_path / "none"), "--keywords", "wood", "--out",
                 str(tmp_path / "x.npz")]) == 2
    assert "checkpoint" in capsys.readouterr().err
    assert main(["btf", "generate", "--run", str(tmp_path), "--out", str(tmp_path / "x.npz")]) == 2
    assert "--keywords" in capsys.readouterr().err
    assert main(["btf", "generate", "--run", str(tmp_path), "--keywords", "wood", "--out", str(tmp_path / "x.png")]) == 2
    assert ".npz" in capsys.readouterr().err
    with pytest.raises(UsageError, match="at least 2"):
        train_matdiff(_toy_set(1), tmp_path / "r", mm.MatDiffSettings(**TINY))
    with pytest.raises(UsageError, match="divide by"):
        train_matdiff(_toy_set(4, res=7), tmp_path / "r", mm.MatDiffSettings(**TINY))
    with pytest.raises(UsageError, match="index.json"):
        md.load_material_dataset(tmp_path)


def test_dataset_build_resumes_and_decodes_like_its_swatches(tmp_path):
    # the sizes of test_btf_cli's data (Dr.Jit's kernels are shared), the least that still fits a material
    s = md.MaterialDataSettings(count=16, tex_res=8, slices=8, spp=2, swatch_spp=2, mesh_res=16, svbrdf_res=16,
                                fit_iterations=20, fit_batch=1024)
    out = md.build_material_dataset(tmp_path / "d", s, progress=False)
    ds = md.load_material_dataset(out)
    assert len(ds.names) == 16 and ds.features.shape == (16, 16, 8, 8) and ds.swatches.shape == (16, 4, 8, 8, 3)
    for f in range(len(md.FAMILIES)):  # two per family: the last of each is held out
        assert ds.heldout[np.flatnonzero(ds.families == f)].tolist() == [False, True]
    assert all(k[0] == md.FAMILIES[f] for k, f in zip(ds.keywords, ds.families))
    stamp = {p.name: p.stat().st_mtime_ns for p in (out / "fit").glob("*.npz")}
    md.build_material_dataset(out, s, progress=False)  # a rerun continues: nothing is redone
    assert stamp == {p.name: p.stat().st_mtime_ns for p in (out / "fit").glob("*.npz")}
    with pytest.raises(UsageError, match="other settings"):
        md.build_material_dataset(out, md.MaterialDataSettings(**{**s.__dict__, "spp": 3}), progress=False)
    # Oracle: a fitted diffuse-ish material decoded at the swatch pairs is close to its path-traced swatches
    # (the basis' own error; plaster is rough and nearly Lambertian): mean relative error < 25 %.
    i = int(np.flatnonzero(ds.families == md.FAMILIES.index("plaster"))[0])
    dec = md.decode_swatches(load_basis(bundled_basis()), ds.features[i, :8].transpose(1, 2, 0),
                             ds.features[i, 8:].transpose(1, 2, 0))
    assert abs(dec.mean() / ds.swatches[i].mean() - 1) < 0.25


# -- evaluation helpers -----------------------------------------------------------------------------------------------


def test_evaluation_helpers_against_closed_forms():
    rng = np.random.default_rng(1)
    y, x = np.mgrid[0:256, 0:256] / 256.0
    noise = rng.uniform(0, 1, (256, 256, 3))  # i.i.d. texels: the wrap-around step is an ordinary step (~3 % spread)
    ramp = np.stack([x + y] * 3, -1)
    assert abs(me.seam_ratio(noise) - 1.0) < 0.15
    assert me.seam_ratio(ramp) > 20  # a ramp jumps by its whole range at the wrap
    img = rng.uniform(0, 1, (16, 16, 3))
    assert me.best_shift(img, np.roll(img, (3, 11), (0, 1))) == (3, 11)
    # aligned ꟻLIP: a rolled copy scores like the original (0), a different texture does not
    sw = np.repeat(img[None], 4, 0).astype(np.float32)
    assert me.aligned_flip(np.roll(sw, (5, 2), (1, 2)), sw) < 1e-6
    assert me.aligned_flip(rng.uniform(0, 1, sw.shape).astype(np.float32), sw) > 0.1
    # the Gaussian baseline reproduces the training mean and covariance (many samples; 5 % of the spread)
    train = rng.normal(0, 1, (6, 2, 2, 2)) * np.array([1, 3]).reshape(1, 2, 1, 1) + 2
    g = me.gaussian_baseline(train.astype(np.float32), 20000, rng).reshape(20000, -1)
    flat = train.reshape(6, -1)
    np.testing.assert_allclose(g.mean(0), flat.mean(0), atol=0.05 * flat.std(0).max())
    np.testing.assert_allclose(np.cov(g, rowvar=False), np.cov(flat, rowvar=False), atol=0.1 * flat.var(0).max())
    c = me.crop_baseline(rng.normal(0, 1, (3, 4, 8, 8)).astype(np.float32), 5, rng)
    assert c.shape == (5, 4, 8, 8) and np.array_equal(c[..., :4, :4], c[..., 4:, 4:])
    a = rng.normal(0, 1, (5, 3))
    assert np.allclose(me.nearest_distances(a, a), 0) and me.mean_pairwise(np.eye(3)) == pytest.approx(np.sqrt(2))



def test_keyword_reference_generators_keep_what_they_promise():
    rng = np.random.default_rng(2)
    # two families of 4-channel 8² textures: family 1 brighter and with more variance than family 0
    x = np.concatenate([rng.normal(0, 1, (5, 4, 8, 8)), rng.normal(3, 2, (5, 4, 8, 8))]).astype(np.float32)
    fams = np.array([0] * 5 + [1] * 5)
    # phase randomisation: every channel keeps the member's mean and its power spectrum exactly, and one phase
    # field for all channels keeps the cross-spectra; the texture itself changes
    p, pf = me.phase_randomised_baseline(x, fams, 3, rng)
    assert p.shape == (6, 4, 8, 8) and list(pf) == [0, 0, 0, 1, 1, 1]
    for sample, f in zip(p, pf):
        members = x[fams == f]
        power = np.abs(np.fft.fft2(sample)) ** 2
        match = [i for i, m in enumerate(members) if np.allclose(power, np.abs(np.fft.fft2(m)) ** 2, rtol=1e-3, atol=1e-2)]
        assert len(match) == 1, "the spectrum of exactly one member of its family"
        m = members[match[0]]
        np.testing.assert_allclose(sample.mean((1, 2)), m.mean((1, 2)), atol=1e-4)
        cross = np.fft.fft2(sample[0]) * np.conj(np.fft.fft2(sample[1]))
        np.testing.assert_allclose(np.abs(cross), np.abs(np.fft.fft2(m[0]) * np.conj(np.fft.fft2(m[1]))), rtol=1e-3, atol=1e-2)
        assert not np.allclose(sample, m, atol=0.1)
    # the per-family Gaussian: many samples reproduce each family's per-channel mean and spread (rolls leave both)
    g, gf = me.family_gaussian_baseline(x, fams, 4000, rng)
    for f in (0, 1):
        np.testing.assert_allclose(g[gf == f].mean((0, 2, 3)), x[fams == f].mean((0, 2, 3)), atol=0.1 * (1 + f))
        np.testing.assert_allclose(g[gf == f].std((0, 2, 3)), x[fams == f].std((0, 2, 3)), rtol=0.1)

def _striped(n: int, vertical: bool, rng: np.random.Generator) -> np.ndarray:
    """(n, 4, 32, 32, 3) swatches of stripes (period 8) of random colour and phase, horizontal or vertical."""
    out = []
    for _ in range(n):
        c = rng.uniform(0.1, 0.6, 3)
        ph = rng.integers(8)
        s = (np.arange(32) + ph) % 8 < 4
        m = np.repeat(s[None, :], 32, 0) if vertical else np.repeat(s[:, None], 32, 1)
        img = np.where(m[..., None], c, 0.3 * c) + rng.normal(0, 0.01, (32, 32, 3))
        out.append(np.repeat(img[None], 4, 0))
    return np.clip(np.stack(out), 0, None).astype(np.float32)


def test_family_classifier_learns_a_family_from_few_swatches_and_resumes(tmp_path):
    # Oracle: two synthetic "families" that differ only in stripe orientation (colour and phase random), new
    # instances held out — the MobileNetV2 trunk separates them from 8 training swatches each.
    rng = np.random.default_rng(0)
    sw = np.concatenate([_striped(8, False, rng), _striped(8, True, rng)])
    fam = np.repeat([0, 1], 8)
    s = me.ClassifierSettings(steps=150, rolls=2, max_seconds=None, threads=1, checkpoint_every=50)
    clf = me.train_classifier(sw, fam, tmp_path / "c", s, show_progress=False)
    test = np.concatenate([_striped(6, False, rng), _striped(6, True, rng)])
    pred, feats = me.classify(clf, test)
    assert np.array_equal(pred, np.repeat([0, 1], 6)) and feats.shape == (12, s.width)
    # the precomputed-features path gives the same answer; a second call resumes the finished run unchanged
    assert np.array_equal(me.classify(clf, test, me.mnv2_features(test))[0], pred)
    again = me.train_classifier(sw, fam, tmp_path / "c", s, show_progress=False)
    assert all(torch.equal(a, b) for a, b in zip(clf.state_dict().values(), again.state_dict().values()))


def test_ema_weights_are_the_running_average_that_sampling_loads(tmp_path):
    # Oracle: replay the raw weights of every step (one run per step count, one thread: bit-identical prefixes)
    # through e ← d e + (1 − d) w with d = min(ema, (1 + it)/(10 + it)); load_matdiff must return that average.
    data = _toy_set()
    s = mm.MatDiffSettings(**TINY, steps=3, ema=0.5)
    raws = [mm.build_model(s).state_dict()]
    for n in (1, 2, 3):
        train_matdiff(data, tmp_path / f"r{n}", mm.MatDiffSettings(**TINY, steps=n, ema=0.5), show_progress=False)
        from foundation.loop import read_checkpoint

        raws.append({k: torch.as_tensor(v) for k, v in read_checkpoint(tmp_path / f"r{n}" / "checkpoint.npz").stage["model"].items()})
    key = next(k for k, v in raws[0].items() if v.is_floating_point() and v.numel() > 10)
    e = raws[0][key].clone()
    for it in range(3):
        d = min(0.5, (1.0 + it) / (10.0 + it))
        e = d * e + (1 - d) * raws[it + 1][key]
    loaded, _ = mt.load_matdiff(tmp_path / "r3")
    torch.testing.assert_close(loaded.state_dict()[key], e, rtol=1e-5, atol=1e-7)
    assert not torch.equal(loaded.state_dict()[key], raws[3][key])  # not the raw weights


def test_crop_training_sees_wrapped_crops_with_zero_padding_and_samples_stay_circular(tmp_path):
    data = _toy_set(res=16)
    s = mm.MatDiffSettings(**TINY, steps=2, train_crop=8)
    seen = []
    stage = mt.MatDiffStage(data, dataclasses.replace(s, feature_scale=1.0, train_res=16),
                            np.zeros((8, 4, mm.EXEMPLAR_TOKENS, mm.FEATURE_DIM), np.float32))
    conv = stage.model.unet.conv_in
    conv.register_forward_hook(lambda m, i, o: seen.append((tuple(i[0].shape[-2:]), m.padding_mode)))
    r = stage.step(0)
    assert np.isfinite(r.loss) and seen == [((8, 8), "zeros")]  # a crop is not periodic: no wrap-around in training
    assert conv.padding_mode == "circular"  # restored: sampling at any size still tiles
    whole = train_matdiff(data, tmp_path / "c", s, show_progress=False)
    assert whole.training.steps == 2 and np.isfinite(whole.training.loss_last)
    with pytest.raises(UsageError, match="train_crop"):
        mm.MatDiffSettings(**TINY, train_crop=3)  # the UNet halves the size once


def test_device_names_weights_only_runs_and_the_bench_main_run_check(tmp_path):
    from foundation.errors import CheckpointError
    from foundation.loop import read_checkpoint, weights_only
    from generative.diffusion.core import torch_device
    from photoreal.benchmarks.matdiff import _check_trained_on

    assert torch_device("cpu") == "cpu"
    if torch.cuda.is_available():
        assert torch_device("cuda").startswith("cuda")
    else:  # the CPU machines this suite runs on: asking for a GPU is refused by name, before any training
        with pytest.raises(UsageError, match="--device cuda: torch sees no CUDA device"):
            train_matdiff(_toy_set(), tmp_path / "g", mm.MatDiffSettings(**TINY, steps=2), device="cuda")
        assert not (tmp_path / "g").exists()
    with pytest.raises(UsageError, match="not a torch device"):
        torch_device("gpu0")

    data = _toy_set()
    s = mm.MatDiffSettings(**TINY, steps=3, ema=0.5)
    train_matdiff(data, tmp_path / "full", s, show_progress=False)
    slim = tmp_path / "slim"
    slim.mkdir()
    weights_only(tmp_path / "full" / "checkpoint.npz", slim / "checkpoint.npz", keep=("ema",))
    (slim / "metrics.json").write_text((tmp_path / "full" / "metrics.json").read_text())
    assert "opt" not in read_checkpoint(slim / "checkpoint.npz").stage
    assert (slim / "checkpoint.npz").stat().st_size < 0.4 * (tmp_path / "full" / "checkpoint.npz").stat().st_size
    (a, _), (b, _) = mt.load_matdiff(tmp_path / "full"), mt.load_matdiff(slim)  # sampling loads the same EMA weights
    assert all(torch.equal(x, y) for x, y in zip(a.state_dict().values(), b.state_dict().values()))
    with pytest.raises(CheckpointError, match="weights-only"):
        train_matdiff(data, slim, s, show_progress=False)
    # float16 weights: half the size again, each weight within float16's rounding (relative 2⁻¹¹) of its float32
    f16 = tmp_path / "f16"
    f16.mkdir()
    weights_only(tmp_path / "full" / "checkpoint.npz", f16 / "checkpoint.npz", keep=("ema",), half=True)
    assert (f16 / "checkpoint.npz").stat().st_size < 0.6 * (slim / "checkpoint.npz").stat().st_size
    c, _ = mt.load_matdiff(f16)
    for (k, x), y in zip(a.state_dict().items(), c.state_dict().values()):
        assert y.dtype == x.dtype, k  # the model stays float32
        if x.is_floating_point():
            assert torch.allclose(x, y, rtol=2.0 ** -11, atol=6e-8), k
    train_matdiff(data, tmp_path / "half", s, budget_steps=1, show_progress=False)
    with pytest.raises(CheckpointError, match="not finished"):
        weights_only(tmp_path / "half" / "checkpoint.npz", tmp_path / "x.npz")

    # the bench evaluates a run trained elsewhere only if it was trained on exactly its training split
    _check_trained_on(slim, data)
    with pytest.raises(UsageError, match="other materials"):
        _check_trained_on(slim, _toy_set(seed=1))
    with pytest.raises(UsageError, match="not finished"):
        _check_trained_on(tmp_path / "half", data)
