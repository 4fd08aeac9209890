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

    scene = mi.load_dict({
        "type": "scene", "integrator": {"type": "path", "max_depth": 3},
        "sensor": {"type": "perspective", "to_world": mi.ScalarTransform4f().look_at([0, 0, 3], [0, 0, 0], [0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 16, "height": 16}},
        "light": {"type": "constant"},
        "ball": {"type": "sphere", "bsdf": {"type": "neural_btf", "basis": str(basis), "material": str(mat)}},
    })
    img = mi.render(scene, spp=4).numpy()
    assert np.isfinite(img).all() and img.mean() > 0


def test_errors_name_the_file(tiny_data, tmp_path, capsys):
    code, _, err = _run(["btf", "fit", str(tmp_path / "missing.npz"), "--basis", str(tmp_path / "b.npz"),
                         "--out", str(tmp_path / "m.npz")], capsys)
    assert code == 2 and "b.npz" in err
    code, _, err = _run(["btf", "train-basis", str(tmp_path / "nodata"), "--out", str(tmp_path / "b.npz")], capsys)
    assert code == 2 and "nodata" in err
    assert not (tmp_path / "b.npz").exists()


@pytest.mark.slow
def test_bench_btf_writes_the_promised_json(tmp_path):
    from photoreal.benchmarks.btf import BTFBenchSettings, bench_btf

    s = BTFBenchSettings(data_dir=str(tmp_path / "data"), train_per_family=1,
                         render=BTFRenderSettings(tex_res=8, slices=8, spp=2, mesh_res=16),
                         widths=(16, 32), tex_res=(4, 8), default_width=32, train_iterations=15, train_batch=2048,
                         fit_iterations=8, fit_batch=1024, neumip_iterations=8, neumip_batch=1024,
                         render_resolution=16, render_spp=2, render_reps=1, mlp_evals=1 << 12)
    r = bench_btf(s, tmp_path / "bench", show_progress=False)
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
