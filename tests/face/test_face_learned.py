"""Learned UV-space face stages (seed 003 §2–§4) at toy sizes: the data against closed forms, the cross-intrinsic
attention against plain attention, LoRA branches against their backbone, exact resume, the pipeline's shapes, the
cross-model benchmark's key light against Mitsuba's own environment sampling, and bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

import mi_plugins  # noqa: F401
import mitsuba as mi

from foundation.errors import CheckpointError, UsageError
from generative.face import data as fd
from generative.face import evaluate as fe
from generative.face import completion as fc
from generative.face import decomposition as fdc
from generative.face import encoding as fm
from generative.face import superres as fsr
from generative.face import run as fr
from photoreal.cli import main

#: the module's tests share one toy run: keep them in one xdist worker (``--dist loadgroup`` in the Makefile)
pytestmark = pytest.mark.xdist_group("face_learned")

TINY_DATA = dict(train_instances=3, eval_instances=2, uv_res=32, spp=2, seed=3)
TINY_COMPLETION = dict(widths=(8, 16), attention_levels=1, head_dim=8, res=16, batch=2, threads=1, checkpoint_every=2,
                       max_seconds=None, samples=2, sample_steps=2)


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    """A whole `face train-models` run at toy sizes (every variant), built once for the module."""
    out = tmp_path_factory.mktemp("face_models") / "run"
    s = fr.FaceModelsSettings(
        data=fd.FaceDataSettings(**TINY_DATA),
        completion=fc.CompletionSettings(steps=4, **TINY_COMPLETION),
        decomposition=fdc.DecompSettings(steps=2, max_seconds=None, batch=1, rank=2, threads=1, checkpoint_every=1),
        superres=fsr.SuperResSettings(width=8, blocks=1, steps=2, max_seconds=None, batch=2, threads=1),
        variants=("cross_attention", "shared", "independent"))
    summary = fr.train_face_models(out, s, progress=False)
    return out, s, summary


# -- data ----------------------------------------------------------------------------------------------------------------


def test_chromophore_model_round_trips_and_is_physical():
    rng = np.random.default_rng(0)
    albedo = rng.uniform(0.02, 0.9, (8, 8, 3)).astype(np.float32)
    # closed form: unchanged concentrations reproduce the albedo (three directions span RGB)
    np.testing.assert_allclose(fd.skin_variation(albedo, 1.0, 1.0), albedo, rtol=1e-5, atol=1e-6)
    skin = np.array([[[0.6, 0.4, 0.3]]], np.float32)
    darker = fd.skin_variation(skin, 2.0, 1.0)[0, 0]
    # more melanin absorbs more towards blue: blue falls by a larger factor than red
    assert (darker < skin[0, 0]).all() and darker[2] / skin[0, 0, 2] < darker[0] / skin[0, 0, 0]
    redder = fd.skin_variation(skin, 1.0, 0.3)[0, 0]  # less haemoglobin: green (its strongest band) rises most
    assert redder[1] / skin[0, 0, 1] > redder[0] / skin[0, 0, 0]


def test_identity_synthesis_warps_symmetrically_and_stays_in_range():
    res = 32
    u = np.linspace(-1, 1, res)
    v = np.linspace(0, 1, res)
    sym = ((0.3 + 0.2 * np.cos(3 * u))[None, :] * (0.5 + 0.5 * v)[:, None])[..., None].repeat(3, -1).astype(np.float32)
    warped = fd.symmetric_warp(sym, np.random.default_rng(1), 0.1)
    assert np.abs(warped - sym).max() > 1e-3  # the features moved
    # closed form: u displaced antisymmetrically, v symmetrically → a symmetric image stays symmetric
    np.testing.assert_allclose(warped, warped[:, ::-1], atol=1e-5)
    pos = np.zeros((res, res, 3), np.float32)
    pos[..., 0] = u[None, :]  # the outer columns lie beyond any hair border
    out = fd.synthetic_identity(sym, pos, np.ones((res, res), bool), np.random.default_rng(2), warp=0.1)
    assert out.shape == sym.shape and np.isfinite(out).all() and (out >= 0).all() and (out <= 1).all()


def test_instances_build_resume_and_load(tiny_run):
    out, s, _ = tiny_run
    d = fd.load_face_dataset(out / "data")
    assert len(d) == 5 and d.res == 32 and d.lit.shape == (5, 32, 32, 3)
    train, ev = fd.load_face_dataset(out / "data", "train"), fd.load_face_dataset(out / "data", "eval")
    assert [r["spec"]["scan"] for r in train.records] == ["paul"] * 3
    assert [r["spec"]["scan"] for r in ev.records] == ["josie"] * 2  # held out entirely
    assert all(r["spec"]["hdri"] in s.data.eval_hdris for r in ev.records)
    for k, v in d.targets.items():
        assert np.isfinite(v).all(), k
    assert 0.0 < d.seen[d.mask].mean() < 1.0
    assert not (d.seen & ~d.mask).any()
    np.testing.assert_allclose(np.linalg.norm(d.targets["normal"][d.mask], axis=-1), 1.0, atol=1e-4)
    # unseen texels carry no light; the baseline is a complete albedo
    assert (d.lit[~d.seen] == 0).all() and (d.baseline[d.mask] > 0).mean() > 0.9
    stamp = {p.name: p.stat().st_mtime_ns for p in (out / "data").glob("*.npz")}
    fd.build_face_dataset(out / "data", s.data, progress=False)  # a rerun skips every finished instance
    assert {p.name: p.stat().st_mtime_ns for p in (out / "data").glob("*.npz")} == stamp
    with pytest.raises(UsageError, match="other settings"):
        fd.build_face_dataset(out / "data", fd.FaceDataSettings(**{**TINY_DATA, "spp": 3}), progress=False)


def test_bad_face_data_settings_and_files(tmp_path):
    with pytest.raises(UsageError, match="also a training scan"):
        fd.FaceDataSettings(train_scans=("josie",), heldout_scan="josie")
    with pytest.raises(UsageError, match="both train_hdris and eval_hdris"):
        fd.FaceDataSettings(train_hdris=("city",), eval_hdris=("city",))
    with pytest.raises(UsageError, match="not a bundled scan"):
        fd.FaceDataSettings(train_scans=("nobody",))
    with pytest.raises(UsageError, match="no face dataset"):
        fd.load_face_dataset(tmp_path)
    (tmp_path / "index.json").write_text(json.dumps({"format": fd.FORMAT, "instances": [{"name": "train_00000",
                                                                                         "spec": {"role": "train"}}]}))
    (tmp_path / "train_00000.npz").write_bytes(b"not a zip")
    with pytest.raises(UsageError, match="train_00000.npz: not a readable face instance"):
        fd.load_face_dataset(tmp_path)


# -- models ----------------------------------------------------------------------------------------------------------------


def test_cross_intrinsic_attention_is_attention_over_every_branch():
    from diffusers.models.attention_processor import Attention, AttnProcessor2_0

    torch.manual_seed(0)
    attn = Attention(query_dim=16, heads=2, dim_head=8)
    k, b, n = 3, 2, 5
    x = torch.randn(k * b, n, 16)
    out = fdc.CrossIntrinsicAttention(k)(attn, x)
    # oracle: diffusers' own processor on each sample's branches laid side by side as one token sequence
    joint = x.view(k, b, n, 16).permute(1, 0, 2, 3).reshape(b, k * n, 16)
    ref = AttnProcessor2_0()(attn, joint).view(b, k, n, 16).permute(1, 0, 2, 3).reshape(k * b, n, 16)
    torch.testing.assert_close(out, ref, rtol=1e-5, atol=1e-6)
    # one branch: ordinary self-attention
    torch.testing.assert_close(fdc.CrossIntrinsicAttention(1)(attn, x), AttnProcessor2_0()(attn, x), rtol=1e-5, atol=1e-6)
    with pytest.raises(UsageError, match="branches"):
        fdc.CrossIntrinsicAttention(4)(attn, x)


def test_decomposition_starts_at_the_baseline_and_lora_branches_stay_separate():
    cs = fc.CompletionSettings(**TINY_COMPLETION)
    backbone = fc.build_completion(cs).eval()
    dec = fdc.Decomposer(backbone, fdc.DecompSettings(variant="shared", rank=2))
    torch.manual_seed(1)
    alb, cond = torch.randn(2, 3, 16, 16), torch.randn(2, fm.COND_CHANNELS, 16, 16)
    with torch.no_grad():
        out = dec(alb, cond)
        feats = dec.features(alb, cond)
        trunk = __import__("copy").deepcopy(backbone)
        trunk.unet.conv_out = torch.nn.Identity()
        ref = trunk(alb, torch.zeros(2, dtype=torch.long), cond, trunk.tokens(None, 2))
    # untrained = the baseline: the input albedo and the template defaults (closed form)
    torch.testing.assert_close(out[:, :3], alb)
    torch.testing.assert_close(out[:, 3:], torch.tensor(fdc.DEFAULT_ENCODED).view(1, -1, 1, 1).expand(2, -1, 16, 16))
    # LoRA starts at B = 0: every branch sees the backbone's own features (oracle: the backbone's forward)
    for f in feats:
        torch.testing.assert_close(f, ref, rtol=1e-5, atol=1e-5)
    trainable = {n for n, p in dec.named_parameters() if p.requires_grad}
    assert trainable and all("lora_" in n or n.startswith("heads.") for n in trainable)
    assert not any(p.requires_grad for n, p in dec.net.named_parameters() if "lora_" not in n)  # backbone frozen
    with torch.no_grad():
        for h in dec.heads:
            h[-1].weight.normal_(0, 0.1)
        before = dec(alb, cond)
        for n, p in dec.named_parameters():  # perturb the normal branch's adapters only: only its channels move
            if ".normal." in n and "lora_B" in n:
                p.normal_(0, 0.5)
        after = dec(alb, cond)
    diff = (after - before).abs().amax(dim=(0, 2, 3))
    assert float(diff[3:6].max()) > 1e-4 and float(diff[:3].max()) == 0 and float(diff[6:].max()) == 0


def test_mirror_is_an_involution_that_flips_the_side():
    rng = np.random.default_rng(0)
    cond = rng.normal(size=(2, fm.COND_CHANNELS, 4, 6)).astype(np.float32)
    maps = rng.normal(size=(2, fm.MAP_CHANNELS, 4, 6)).astype(np.float32)
    c1, m1 = fm.mirror(cond, maps)
    np.testing.assert_array_equal(c1[:, fm.GEO.start, :, 0], -cond[:, fm.GEO.start, :, -1])
    np.testing.assert_array_equal(c1[:, 0, :, 0], cond[:, 0, :, -1])
    np.testing.assert_array_equal(m1[:, 3, :, 0], -maps[:, 3, :, -1])  # tangent-space normal x
    c2, m2 = fm.mirror(c1, m1)
    np.testing.assert_array_equal(c2, cond)
    np.testing.assert_array_equal(m2, maps)


def test_training_resumes_bit_for_bit(tiny_run, tmp_path):
    out, s, summary = tiny_run
    train = fd.load_face_dataset(out / "data", "train")
    cs = fc.CompletionSettings(steps=4, **TINY_COMPLETION)
    assert fc.train_completion(train, tmp_path / "a", cs, budget_steps=2, show_progress=False) is None
    fc.train_completion(train, tmp_path / "a", cs, show_progress=False)
    a = fc.load_completion(tmp_path / "a")[0].state_dict()
    b = fc.load_completion(out / "completion")[0].state_dict()
    assert all(torch.equal(a[k], b[k]) for k in b)  # interrupted + resumed = uninterrupted (the fixture's run)
    albedo = fr.completion_albedo(out)
    ds = fdc.DecompSettings(variant="cross_attention", steps=2, max_seconds=None, batch=1, rank=2, threads=1,
                           checkpoint_every=1)
    assert fdc.train_decomposer(train, albedo, out / "completion", tmp_path / "d", ds, budget_steps=1,
                               show_progress=False) is None
    fdc.train_decomposer(train, albedo, out / "completion", tmp_path / "d", ds, show_progress=False)
    x = fdc.load_decomposer(tmp_path / "d", out / "completion").state_dict()
    y = fdc.load_decomposer(out / "decomposition_cross_attention", out / "completion").state_dict()
    assert all(torch.equal(x[k], y[k]) for k in y)
    for key in ("completion", "decomposition_cross_attention", "decomposition_shared", "decomposition_independent",
                "superres"):
        assert np.isfinite(summary[key]["training"]["loss_last"]), key
    assert summary["decomposition_independent"]["parameters"] > 4 * summary["decomposition_shared"]["parameters"]


def test_learned_pipeline_gives_complete_maps_and_scores(tiny_run):
    out, s, _ = tiny_run
    ev = fd.load_face_dataset(out / "data", "eval")
    models = fr.load_face_models(out)
    for stages in ("completion", "decomposition", "full"):
        maps = fe.learned_maps(ev, models, stages)
        assert maps["albedo"].shape == (2, 32, 32, 3) and maps["roughness"].shape == (2, 32, 32, 1)
        for k, v in maps.items():
            assert np.isfinite(v).all(), (stages, k)
        np.testing.assert_allclose(np.linalg.norm(maps["normal"], axis=-1), 1.0, atol=1e-4)
    sc = fe.map_scores(fe.baseline_maps(ev), ev.targets, ev.seen, ev.mask)
    # oracle: the truth scores perfectly (albedo PSNR capped by the clip at 1 only; angles 0; MAE 0)
    perfect = fe.map_scores(ev.targets, ev.targets, ev.seen, ev.mask)
    assert perfect["normal_err_deg"] < 0.05 and perfect["roughness_mae"] == 0 and perfect["albedo_psnr_seen"] > 80
    assert sc["albedo_psnr_seen"] < perfect["albedo_psnr_seen"] and sc["normal_err_deg"] > 0.5
    # the template defaults are what the baseline reports
    assert np.all(fe.baseline_maps(ev)["roughness"] == fe.DEFAULTS["roughness"])


def test_runs_and_checkpoints_are_checked(tiny_run, tmp_path):
    out, s, _ = tiny_run
    with pytest.raises(UsageError, match="not a face models run"):
        fr.load_face_models(tmp_path)
    with pytest.raises(UsageError, match="has no 'nonsense' decomposition"):
        fr.load_face_models(out, "nonsense")
    with pytest.raises(UsageError, match="other settings"):
        fr.train_face_models(out, fr.FaceModelsSettings(data=fd.FaceDataSettings(**{**TINY_DATA, "seed": 4}),
                                                        completion=s.completion, decomposition=s.decomposition,
                                                        superres=s.superres, variants=s.variants), progress=False)
    with pytest.raises(CheckpointError, match="not a face decomposition"):
        fdc.load_decomposer(out / "completion", out / "completion")
    other = fc.CompletionSettings(steps=1, **TINY_COMPLETION)
    fc.train_completion(fd.load_face_dataset(out / "data", "train"), tmp_path / "other", other, show_progress=False)
    with pytest.raises(CheckpointError, match="another completion backbone"):
        fdc.load_decomposer(out / "decomposition_shared", tmp_path / "other")


def test_from_photo_refuses_models_of_another_uv_layout(tiny_run):
    from dataclasses import replace

    out, _, _ = tiny_run
    models = fr.load_face_models(out)
    assert models.layout == "template"
    fr.photo_maps_fn(models)
    with pytest.raises(UsageError, match="'scan' UV layout.*--layout template"):
        fr.photo_maps_fn(replace(models, layout="scan"))


def test_from_photo_refuses_a_missing_run(tmp_path, capsys):
    rc = main(["face", "from-photo", "astronaut", "--out", str(tmp_path / "o"), "--learned", str(tmp_path / "none")])
    assert rc == 2 and "not a face models run" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_scan_registration_lands_the_template_on_the_scan(tiny_run):
    import mitsuba as mi

    from foundation.mesh import load_obj
    from inverse.face import bake_geometry

    out, s, _ = tiny_run
    reg = fd.load_registration(out / "data", "josie")
    assert reg.valid.mean() > 0.4 and reg.landmark_px < 30  # MediaPipe on the frontal render, fitted like a photo
    # oracle: Mitsuba's own parameterisation of the scan at the registered uv lies on the template texel's point,
    # within the cast's reach (0.15 of the face's size) everywhere and much closer at the median
    geo = bake_geometry(load_obj(fd.registration_files(out / "data", "josie")[1]), reg.valid.shape[0])
    scan = mi.load_dict({"type": "obj", "filename": str(fd.scan_path("josie")), "face_normals": False})
    uv = reg.scan_uv[reg.valid]
    p = np.array(scan.eval_parameterization(mi.Point2f(uv[:, 0], uv[:, 1])).p).T
    size = float(np.linalg.norm(np.ptp(reg.vertices, 0)))
    d = np.linalg.norm(p - geo.position[reg.valid], axis=1) / size
    assert d.max() < 0.15 + 1e-3 and np.median(d) < 0.03
    const = np.full((8, 8, 3), 0.25, np.float32)
    np.testing.assert_allclose(reg.to_template(const), 0.25, rtol=1e-6)  # closed form: a constant stays constant


# -- the cross-model benchmark --------------------------------------------------------------------------------------------


def test_key_light_matches_mitsubas_environment_sampling(tmp_path):
    from foundation.assets import envmap
    from foundation.imageio import write_exr
    from inverse.face import key_light

    h, w = 32, 64
    img = np.full((h, w, 3), 1e-4, np.float32)
    img[9, 41] = 1e4  # one bright texel: the key light must point at it
    f = tmp_path / "spot.exr"
    write_exr(f, {"": img})
    for rot in (0.0, 70.0):
        key, irr = key_light(str(f), rot)
        emitter = mi.load_dict(envmap(str(f), to_world=mi.ScalarTransform4f().rotate([0, 1, 0], rot)))
        it = mi.Interaction3f()
        it.p = mi.Point3f(0, 0, 0)
        ds, _ = emitter.sample_direction(it, mi.Point2f(0.5, 0.5))
        d = np.array(ds.d).ravel()
        # oracle: Mitsuba's own importance sampling picks the bright texel; tolerance: one texel (≈ 5.6°)
        assert np.degrees(np.arccos(np.clip(np.dot(d, key), -1, 1))) < 6.0, rot
        assert irr > 0


def test_principled_hdri_benchmark_is_fit_and_scored(tmp_path):
    from inverse.face import (FaceBenchmarkSettings, FaceFitSettings, evaluate_fit, fit_face, load_benchmark,
                              make_benchmark)

    bs = FaceBenchmarkSettings(uv_res=16, n_lights=1, views=((0.0, 0.0),), heldout_hdris=("studio",), render_res=16,
                               render_spp=4, observation_bsdf="principled", lighting="hdri", observation_spp=4,
                               max_depth=3, albedo_blur=1.0)
    d = make_benchmark(fd.scan_path("josie"), tmp_path / "b", bs, show_progress=False)
    b = load_benchmark(d)
    assert b.meta.lights[0].kind == "hdri" and b.meta.lights[0].hdri in bs.lighting_hdris
    sp = b.ground_truth["specular"]
    assert np.ptp(sp) == 0  # principled's specular is a scalar: the truth records what was rendered
    m = evaluate_fit(b, fit_face(b, FaceFitSettings(fit_lights=True, iterations=(2, 2)), show_progress=False))
    assert np.isfinite([m.albedo_psnr, m.normal_err_deg, m.relit_psnr]).all()
    with pytest.raises(UsageError, match="observation_bsdf"):
        FaceBenchmarkSettings(observation_bsdf="lambert")
