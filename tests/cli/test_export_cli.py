"""`photoreal export` of the three kinds of result: a morph run of a capture (the texture baked from its photos and
from its vertex colours, scored on the held-out photos), a face avatar, a neural material (its GGX distillation);
each file through the Khronos validator and a re-import; bad input named in one line with nothing written."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from photoreal.cli import main

ROOT = Path(__file__).resolve().parents[2]
NODE = shutil.which("node")


def _cli(*argv) -> int:
    return main([str(a) for a in argv])


def _validated(path: Path) -> None:
    from foundation.export import validate_gltf

    if NODE is None:
        pytest.skip("node is not installed: the Khronos validator runs under node")
    issues = validate_gltf(path)["issues"]
    assert issues["numErrors"] == 0, issues["messages"]


@pytest.fixture(scope="module")
def capture_run(small_armadillo, tmp_path_factory):
    """The small armadillo benchmark as a capture folder (transforms.json through `capture import` with its coarse
    mesh) and a 4-iteration unlit morph of it with its gains and environment fitted, in CAPTURE/morph."""
    from inverse.capture import export_capture, import_capture, load_capture, read_source
    from inverse.morph import CaptureBenchmark, MorphSettings, benchmark_capture, run_morph

    base = tmp_path_factory.mktemp("export")
    src = read_source(export_capture(benchmark_capture(small_armadillo), base / "src", "transforms"))
    cap_dir = import_capture(src, base / "capture", resolution=None, mesh=small_armadillo.path / "coarse.ply",
                             show_progress=False)
    s = MorphSettings(iterations=4, mode="unlit", lambda_select=(), planarity_select=(), step_select_quantile=1.0,
                      early_stop=False, min_vertices=None, check_every=4, checkpoint_every=4, resolution=32)
    run = cap_dir / "morph"
    run_morph(CaptureBenchmark(load_capture(cap_dir), base / "work"), run, s, show_progress=False)
    return cap_dir, run


def test_a_lit_runs_default_texture_is_its_vertex_colours(capture_run, tmp_path):
    """A capture's run that ended 'lit' (albedo under its fitted light) exports its vertex colours by default: the
    photos' texture holds the light baked in, which a viewer would light again."""
    from inverse.capture import load_capture
    from inverse.morph import CaptureBenchmark, MorphSettings, run_morph

    cap_dir, _ = capture_run
    s = MorphSettings(iterations=2, mode="lit", mode_select=False, lambda_select=(), planarity_select=(),
                      step_select_quantile=1.0, early_stop=False, min_vertices=None, check_every=2, checkpoint_every=2,
                      resolution=32)
    run = tmp_path / "lit"
    run_morph(CaptureBenchmark(load_capture(cap_dir), tmp_path / "work"), run, s, show_progress=False)
    out = tmp_path / "exp"
    assert _cli("export", run, "--input", cap_dir, "--out", out, "--texture-size", 128, "--eval-width", 32,
                "--spp", 2) == 0
    assert json.loads((out / "export.json").read_text())["texture"] == "colours"


def test_morph_export_of_a_capture(capture_run, tmp_path, capsys):
    """The default texture of a capture's run is the photos'; the colours' texture renders as the vertex colours do
    on the held-out photos (within 0.5 dB: the same colours through the atlas); the re-import matches."""
    cap_dir, run = capture_run
    out = tmp_path / "exp"
    assert _cli("export", run, "--out", out, "--texture-size", 256, "--eval-width", 48, "--spp", 4) == 0
    rec = json.loads((out / "export.json").read_text())
    assert rec["kind"] == "morph" and rec["texture"] == "photos" and rec["input"] == str(cap_dir)
    h = rec["heldout"]
    assert set(h) == {"vertex_colours", "colours", "photos"}
    assert abs(h["colours"]["psnr"] - h["vertex_colours"]["psnr"]) < 0.5, h
    assert all(np.isfinite(x["psnr"]) and 0 <= x["flip"] <= 1 for x in h.values())
    assert 0.3 < rec["photo_coverage"] <= 1.0
    assert rec["reimport"]["render_psnr"] >= rec["reimport"]["render_psnr_min"]
    assert rec["reimport"]["vertices"] == rec["exported_vertices"]
    assert "+Y up" in rec["frame"]
    # the viewer's first camera: the benchmark's drone orbit looks down from 15–35° above the horizon
    azimuth, polar = rec["view_orbit_deg"]
    assert -180 <= azimuth <= 180 and 0 < polar < 90
    # the frame: the cameras' mean up becomes +Y (the mesh's extent along it is its extent along Y), the bounding
    # box's centre the origin, the units kept (a rigid map: every edge keeps its length)
    from foundation.export import reimport
    from foundation.mesh import read_ply
    from inverse.capture import load_capture

    cams = load_capture(cap_dir).meta.cameras
    up = -np.mean([np.asarray(c.matrix)[:3, 1] for c in cams], axis=0)
    up /= np.linalg.norm(up)
    v, f, _ = read_ply(run / "morphed.ply")
    back = reimport(out / "model.glb").vertices
    size = float(np.ptp(v, axis=0).max())
    assert abs(np.ptp(back[:, 1]) - np.ptp(v @ up)) < 1e-5 * size
    assert np.abs((back.min(0) + back.max(0)) / 2).max() < 1e-5 * size
    from scipy.spatial.distance import pdist

    assert len(v) < 5000  # the diameter below is quadratic
    assert abs(pdist(back).max() - pdist(np.asarray(v, np.float64)).max()) < 1e-5 * size  # the diameter is kept
    _validated(out / "model.glb")
    printed = json.loads(capsys.readouterr().out)
    assert printed["files"] == ["model.glb"]


def test_morph_export_formats_and_texture_choice(capture_run, tmp_path):
    _, run = capture_run
    for fmt, main_file in (("gltf", "model.gltf"), ("obj", "model.obj")):
        out = tmp_path / fmt
        assert _cli("export", run, "--out", out, "--format", fmt, "--texture", "colours", "--texture-size", 128,
                    "--eval-width", 32, "--spp", 2) == 0
        rec = json.loads((out / "export.json").read_text())
        assert rec["texture"] == "colours" and main_file in rec["files"]
        assert all((out / f).is_file() for f in rec["files"])
        if fmt == "gltf":
            _validated(out / main_file)


def test_face_exports(tmp_path):
    """A `face fit` (its fit.json and its maps folder) and a from-photo folder: the maps as a glTF
    metallic-roughness material with KHR_materials_specular, displacement beside; the validator reports no error."""
    from foundation.export import reimport
    from inverse.face import FaceBenchmarkSettings, FaceFitSettings, fit_benchmark_dir, make_benchmark

    bench = make_benchmark(ROOT / "scenes" / "assets" / "face" / "cyberheads" / "josie.obj", tmp_path / "b",
                           FaceBenchmarkSettings(uv_res=32, render_res=32, render_spp=4, seed=0), show_progress=False)
    fit_benchmark_dir(bench, tmp_path / "fit" / "fit.json", tmp_path / "fit" / "maps",
                      FaceFitSettings(iterations=(10, 20), seed=0), relight=False, show_progress=False)
    for given in (tmp_path / "fit" / "fit.json", tmp_path / "fit" / "maps"):
        out = tmp_path / f"exp_{given.name}"
        assert _cli("export", given, "--out", out) == 0
        rec = json.loads((out / "export.json").read_text())
        assert rec["kind"] == "face" and rec["source"] == "fit"
        assert rec["maps"] == ["albedo", "normal", "roughness", "specular", "displacement"]
        assert (out / "displacement.png").is_file()
        assert rec["reimport"]["render_psnr"] >= rec["reimport"]["render_psnr_min"]
        assert rec["reimport"]["texture_size"] == [32, 32]
        doc = json.loads(reimport(out / "model.glb") and _glb_json(out / "model.glb"))
        m = doc["materials"][0]
        assert {"baseColorTexture", "metallicRoughnessTexture"} <= set(m["pbrMetallicRoughness"])
        assert "normalTexture" in m and "KHR_materials_specular" in m["extensions"]
        assert "TANGENT" in doc["meshes"][0]["primitives"][0]["attributes"]
        _validated(out / "model.glb")


def _glb_json(path: Path) -> str:
    import struct

    data = path.read_bytes()
    n = struct.unpack_from("<I", data, 12)[0]
    return data[20:20 + n].decode()


def test_material_export(tmp_path):
    """The bundled leather: XML snippet loading in Mitsuba, preview, the GGX tile; the per-texel GGX fits the
    training directions better than one GGX over the tile (its mean parameters) does."""
    import mi_plugins  # noqa: F401
    import mitsuba as mi

    from foundation.export import ExportSettings
    from inverse.btf import DistilSettings, export_material

    out = tmp_path / "mat"
    rec = export_material(ROOT / "scenes" / "assets" / "neural" / "leather.npz", out, ExportSettings(spp=4),
                          distil=DistilSettings(iterations=60, train_pairs=24, heldout_pairs=8), show_progress=False)
    assert {"material.xml", "basis.npz", "leather.npz", "preview.png", "model.glb"} <= set(rec.files)
    assert rec.train_psnr > 30 and np.isfinite(rec.ggx_heldout_psnr) and rec.preview_psnr > 20
    # the validation pairs' choice is the one of lower validation MAE, and its held-out figure is the one recorded
    v = rec.validation
    assert rec.model == ("uniform" if v["uniform"]["mae"] < v["per-texel"]["mae"] else "per-texel")
    assert rec.exported_heldout_psnr == (rec.ggx_heldout_psnr if rec.model == "per-texel" else rec.constant_heldout_psnr)
    assert rec.reimport["render_psnr"] >= rec.reimport["render_psnr_min"]
    xml = (out / "material.xml").read_text()
    scene = mi.load_string(f"<scene version='3.0.0'>{xml.split('-->', 1)[1]}</scene>".replace(
        'value="basis.npz"', f'value="{out / "basis.npz"}"').replace('value="leather.npz"',
                                                                     f'value="{out / "leather.npz"}"'))
    assert scene is not None
    _validated(out / "model.glb")


def test_bad_input_is_named_and_nothing_is_written(capture_run, tmp_path, capsys):
    cap_dir, run = capture_run
    # a result folder of another kind: the capture itself
    assert _cli("export", cap_dir, "--out", tmp_path / "a") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(cap_dir) in err[0] and "not a result" in err[0]
    assert not (tmp_path / "a").exists()
    # a missing map: a face fit's maps without the normal layer
    from foundation import imageio

    maps = tmp_path / "fit" / "maps"
    maps.mkdir(parents=True)
    imageio.write_exr(maps / "maps.exr", {"albedo": np.full((8, 8, 3), 0.5, np.float32)})
    (tmp_path / "fit" / "fit.json").write_text(json.dumps({"benchmark": str(tmp_path / "nowhere"), "metrics": {}}))
    assert _cli("export", maps, "--out", tmp_path / "b", "--input", cap_dir) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no 'normal' map" in err[0] and "maps.exr" in err[0]
    assert not (tmp_path / "b").exists()
    # an unwritable path, and a folder of the user's that is not an earlier export
    assert _cli("export", run, "--out", "/proc/photoreal-export") == 2  # argparse's usage, then the one line
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert "--out" in last and "/proc/photoreal-export" in last
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep me")
    assert _cli("export", run, "--out", mine) == 2
    assert "--out" in capsys.readouterr().err and (mine / "notes.txt").read_text() == "keep me"
    assert sorted(p.name for p in mine.iterdir()) == ["notes.txt"]
    # the photos texture of a synthetic benchmark's run
    assert _cli("export", run, "--out", tmp_path / "c", "--input", tmp_path / "nowhere") == 2
    assert "--input" in capsys.readouterr().err
