"""`photoreal btf ...` end to end at toy sizes, resume, the plugin in a scene, and `bench btf`'s JSON."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import mi_plugins  # noqa: F401
import mitsuba as mi

from inverse.btf.data import BTFRenderSettings
from mi_plugins.neural_basis import load_basis, load_material
from photoreal.cli import main


def _run(argv, capsys):
    code = main(argv)
    cap = capsys.readouterr()
    return code, cap.out, cap.err


@pytest.fixture(scope="module")
def tiny_data(tmp_path_factory):
    d = tmp_path_factory.mktemp("btf") / "data"
    assert main(["btf", "render-data", "--out", str(d), "--families", "fabric", "leather", "--per-family", "1",
                 "--tex-res", "8", "--slices", "8", "--spp", "2"]) == 0
    return d


def test_render_train_fit_and_use_in_a_scene(tiny_data, tmp_path, capsys):
    files = sorted(p.name for p in tiny_data.glob("*.npz"))
    assert files == ["fabric_000.npz", "leather_000.npz"]
    basis = tmp_path / "basis.npz"
    code, out, err = _run(["btf", "train-basis", str(tiny_data), "--out", str(basis), "--iterations", "30",
                           "--batch", "1024", "--width", "16"], capsys)
    assert code == 0, err
    first = load_basis(basis).arrays()
    assert Path(json.loads(out)["checkpoint"]).is_file()
    # Rerunning a finished run resumes at its end: no new steps, identical weights.
    code, _, err = _run(["btf", "train-basis", str(tiny_data), "--out", str(basis), "--iterations", "30",
                         "--batch", "1024", "--width", "16"], capsys)
    assert code == 0, err
    for k, a in load_basis(basis).arrays().items():
        np.testing.assert_array_equal(a, first[k])

    mat = tmp_path / "fabric.npz"
    code, out, err = _run(["btf", "fit", str(tiny_data / "fabric_000.npz"), "--basis", str(basis), "--out", str(mat),
                           "--iterations", "20", "--batch", "1024", "--json", str(tmp_path / "fit.json")], capsys)
    assert code == 0, err
    m = json.loads((tmp_path / "fit.json").read_text())
    assert np.isfinite(m["psnr_heldout"]) and m["heldout_slices"] == 2
    assert load_material(mat).t_rgb.shape == (8, 8, 8)

    # In a scene: a flat tile under a uniform white sky, seen straight on. Each pixel is the BTF integrated over
    # the light directions, ∫ BTF(u, ω_i, ω_o = n) dω_i (BTF values include cos θ_i), so the image mean is that
    # integral averaged over the tile. Oracle: the same weights evaluated by the training code
    # (inverse.btf.predict) on a 24 × 48 grid uniform in (cos θ_i, φ_i), i.e. equal solid angles 2π/1152.
    # Tolerance 5 %: the render's Monte Carlo noise at 256 spp × 64 pixels is ~1 %, the quadrature's < 1 %.
    scene = mi.load_dict({
        "type": "scene", "integrator": {"type": "path", "max_depth": 2},
        "sensor": {"type": "orthographic", "to_world": mi.ScalarTransform4f().look_at([0, 0, 3], [0, 0, 0], [0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 8, "height": 8, "rfilter": {"type": "box"}}},
        "light": {"type": "constant", "radiance": 1.0},
        "tile": {"type": "rectangle", "bsdf": {"type": "neural_btf", "basis": str(basis), "material": str(mat)}},
    })
    img = mi.render(scene, spp=256, seed=3).numpy()[..., :3]
    assert np.isfinite(img).all()
    from types import SimpleNamespace

    from inverse.btf import predict

    nt, nphi, r = 24, 48, 8
    cos_t = (np.arange(nt) + 0.5) / nt
    phi = 2 * np.pi * (np.arange(nphi) + 0.5) / nphi
    ct, ph = np.meshgrid(cos_t, phi, indexing="ij")
    st = np.sqrt(1 - ct**2)
    wi = np.stack([st * np.cos(ph), st * np.sin(ph), ct], -1).reshape(-1, 1, 1, 3).astype(np.float32)
    shape = (len(wi), r, r, 3)
    grid = SimpleNamespace(values=np.zeros(shape, np.float16), wi=np.broadcast_to(wi, shape).copy(),
                           wo=np.broadcast_to(np.array([0, 0, 1], np.float32), shape).copy())
    values = np.maximum(predict(load_basis(basis), load_material(mat), grid, np.arange(len(wi))), 0)  # plugin clamps
    expected = values.mean(axis=(1, 2)).sum(0) * (2 * np.pi / len(wi))
    np.testing.assert_allclose(img.mean(axis=(0, 1)), expected, rtol=0.05)
    assert expected.min() > 0.01


def test_errors_name_the_file(tiny_data, tmp_path, capsys):
    code, _, err = _run(["btf", "fit", str(tmp_path / "missing.npz"), "--basis", str(tmp_path / "b.npz"),
                         "--out", str(tmp_path / "m.npz")], capsys)
    assert code == 2 and "b.npz" in err
    code, _, err = _run(["btf", "train-basis", str(tmp_path / "nodata"), "--out", str(tmp_path / "b.npz")], capsys)
    assert code == 2 and "nodata" in err
    assert not (tmp_path / "b.npz").exists()


@pytest.mark.slow
def test_bench_btf_writes_the_promised_json(tmp_path):
    from photoreal.benchmarks import run_benchmark
    from photoreal.benchmarks.btf import BTFBenchSettings

    s = BTFBenchSettings(data_dir=str(tmp_path / "data"), train_per_family=1,
                         render=BTFRenderSettings(tex_res=8, slices=8, spp=2, mesh_res=16),
                         widths=(16, 32), tex_res=(4, 8), default_width=32, train_iterations=15, train_batch=2048,
                         fit_iterations=8, fit_batch=1024, neumip_iterations=8, neumip_batch=1024,
                         render_resolution=16, render_spp=2, render_reps=1, mlp_evals=1 << 12)
    from foundation.pool import PoolSettings

    r = run_benchmark("btf", s, tmp_path / "bench" / "btf.json", pool=PoolSettings(workers=0, threads=0),
                      show_progress=False)
    assert json.loads((tmp_path / "bench" / "btf.json").read_text())["chosen"] == r["chosen"]
    assert (tmp_path / "bench" / "btf_work" / "assets" / "basis.npz").is_file()  # everything kept in its work
    for k in ("psnr_universal_mean", "psnr_per_material_mean", "neural_btf_ms", "principled_ms",
              "neural_btf_vs_principled", "mlp_evals_per_s_drjit", "mlp_evals_per_s_torch"):
        assert np.isfinite(r[k]) and r[k] > 0, k
    assert {(x["width"], x["tex_res"]) for x in r["sweep"]} == {(16, 4), (16, 8), (32, 4), (32, 8)}
    best = max(x["psnr"] for x in r["sweep"])
    assert r["chosen"]["psnr"] >= best - 0.5
    assert all(x["ms"] >= r["chosen"]["ms"] for x in r["sweep"] if x["psnr"] >= best - 0.5)
    assert r["neural_btf_vs_principled"] == pytest.approx(r["neural_btf_ms"] / r["principled_ms"])
    assert len(r["table"]) == 8 and Path(r["chart"]).is_file()
    # same weights, two code paths: CoopVec (plugin) and torch agree
    assert r["mlp"]["max_abs_diff_drjit_vs_torch"] < 1e-3
    json.dumps(r)


def test_fitting_many_materials_is_a_resumable_batch(tiny_data, tmp_path, capsys):
    basis = tmp_path / "basis.npz"
    assert main(["btf", "train-basis", str(tiny_data), "--out", str(basis), "--iterations", "5", "--batch", "512",
                 "--width", "8"]) == 0
    capsys.readouterr()
    argv = ["btf", "fit", str(tiny_data / "fabric_000.npz"), str(tiny_data / "leather_000.npz"), "--basis", str(basis),
            "--out-dir", str(tmp_path / "fitted"), "--iterations", "4", "--batch", "512", "--workers", "0"]
    assert main(argv) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["done"] == 2 and summary["failed"] == []
    assert load_material(tmp_path / "fitted" / "leather_000.npz").t_rgb.shape == (8, 8, 8)
    assert main(argv) == 0 and json.loads(capsys.readouterr().out)["skipped"] == 2  # done before: skipped
