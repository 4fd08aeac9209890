"""The cases of a new user's bad-input probe (findings 1–18, in the order listed there), each as it was run: every
one ends with one line naming the file or the flag, exit 2 for a bad argument (1 for a failure), nothing half-written
and nothing the user had overwritten or removed. Fixtures: ``afile`` a regular file; ``thesis`` folders holding the
user's ``metrics.json`` and ``errors.json``."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from photoreal.cli import main

ROOT = Path(__file__).resolve().parents[2]
ASSETS = ROOT / "scenes" / "assets"
ARMADILLO = ASSETS / "meshes" / "armadillo.ply"
PAUL = ASSETS / "face" / "cyberheads" / "paul.obj"
USERS = '{"the user\'s": "results"}'


def run(argv, capsys) -> tuple[int, str]:
    code = main([str(a) for a in argv])
    err = capsys.readouterr().err
    assert "Traceback" not in err, err
    if code not in (0, 130):
        assert err.strip().splitlines()[-1].startswith(("photoreal: error:", "photoreal ")), err
    return code, err


@pytest.fixture(scope="module")
def bench(tmp_path_factory):
    """`morph make-benchmark --views 4 --resolution 32` and a 2-step `morph run` on it (the probe's `bench/arm`)."""
    from inverse.morph import MorphBenchmarkSettings, MorphSettings, load_morph_benchmark, make_morph_benchmark
    from inverse.morph import run_morph

    out = tmp_path_factory.mktemp("findings") / "arm"
    make_morph_benchmark(ARMADILLO, out, MorphBenchmarkSettings(n_views=4, resolution=32, spp=2, coarse_vertices=300),
                         show_progress=False)
    run_morph(load_morph_benchmark(out), out / "morph", MorphSettings(iterations=2, min_vertices=None),
              show_progress=False)
    return out


@pytest.fixture
def fx(tmp_path):
    (tmp_path / "afile").write_text("x")
    for name, file in (("thesis", "metrics.json"), ("thesis2", "errors.json"), ("thesis3", "metrics.json")):
        (tmp_path / name).mkdir()
        (tmp_path / name / file).write_text(USERS)
    return tmp_path


def _untouched(fx: Path) -> None:
    for name, file in (("thesis", "metrics.json"), ("thesis2", "errors.json"), ("thesis3", "metrics.json")):
        assert sorted(p.name for p in (fx / name).iterdir()) == [file] and (fx / name / file).read_text() == USERS


# -- data loss / silently wrong ------------------------------------------------------------------------------------


def test_1_to_3_a_users_folder_is_never_written_into(bench, fx, capsys):
    cases = [(["diffrender", "train", bench, "--out", fx / "thesis", "--steps", "2", "--seconds", "5", "--batch", "2",
               "--crop", "16", "--widths", "8", "16", "--threads", "1"], "thesis", "metrics.json"),
             (["btf", "train-diffusion", fx / "md" / "data16", "--out", fx / "thesis3", "--seconds", "5", "--steps",
               "2", "--batch", "2", "--widths", "8", "16", "--train-crop", "8"], "thesis3", "metrics.json"),
             (["morph", "errors", bench, bench / "morph", "--out", fx / "thesis2"], "thesis2", "errors.json")]
    for argv, folder, file in cases:
        code, err = run(argv, capsys)
        assert code == 2 and f"--out: {fx / folder}: holds files" in err and f"did not write ({file})" in err, err
    _untouched(fx)


def test_4_a_16_bit_exemplar_keeps_its_values(tmp_path):
    import cv2

    from generative.btf.sample import read_exemplar

    cv2.imwrite(str(tmp_path / "g16.png"), np.full((8, 8), 32768, np.uint16))  # grey 0.5 in sRGB, 16 bits
    ex = read_exemplar(tmp_path / "g16.png")
    assert ex.shape == (8, 8, 3) and abs(float(ex.mean()) - 0.21404) < 1e-4  # sRGB 0.5 decoded (not clipped to 1)


def test_5_a_material_size_of_0_is_refused(tmp_path, capsys):
    for size in ("0", "-4", "6"):
        code, err = run(["btf", "generate", "--run", tmp_path / "run", "--keywords", "red leather", "--size", size,
                         "--out", tmp_path / "d.npz"], capsys)
        assert code == 2 and "--size" in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_6_a_black_or_negative_hdri_is_refused(tmp_path, capsys):
    from foundation.imageio import write_exr

    write_exr(tmp_path / "zero.exr", {"": np.zeros((8, 16, 3), np.float32)})
    neg = np.full((8, 16, 3), 0.5, np.float32)
    neg[:4] = -1.0  # half the sky below zero: a wrong sign, not resampling ringing
    write_exr(tmp_path / "neg.exr", {"": neg})
    for name, msg in (("zero.exr", "HDRI is black everywhere"), ("neg.exr", "HDRI has negative radiance (down to -1")):
        code, err = run(["morph", "make-benchmark", "--mesh", ARMADILLO, "--views", "4", "--resolution", "16",
                         "--spp", "4", "--out", tmp_path / "z", "--hdri", tmp_path / name], capsys)
        assert code == 2 and f"{tmp_path / name}: {msg}" in err, err
        assert not (tmp_path / "z").exists()


def test_7_a_dataset_with_no_training_materials_is_refused_at_count(tmp_path, capsys):
    code, err = run(["btf", "dataset", "--out", tmp_path / "d", "--count", "8", "--tex-res", "8", "--slices", "4",
                     "--spp", "1", "--fit-iterations", "2", "--workers", "0"], capsys)
    assert code == 2 and "--count" in err and not (tmp_path / "d").exists(), err


# -- hangs (8: tests/foundation/test_pool.py, an unreachable --ray within 3 s) ----------------------------------------


def test_9_a_bad_ray_address_is_refused_before_any_data(tmp_path, capsys):
    code, err = run(["face", "train-models", "--out", tmp_path / "r", "--uv-res", "64", "--spp", "1",
                     "--train-instances", "2", "--eval-instances", "1", "--ray", "nonsense"], capsys)
    assert code == 2 and "--ray nonsense" in err and not (tmp_path / "r").exists()


# -- messages and exit codes ---------------------------------------------------------------------------------------


def test_10_to_12_outputs_at_a_file_or_nowhere_name_the_flag(bench, fx, capsys):
    for out, msg in ((fx / "afile", f"--out: {fx / 'afile'}: is a file, expected a folder"),
                     (Path("/proc/x"), "--out: /proc/x: cannot write into /proc")):
        for argv in (["diffrender", "train", bench, "--out", out, "--steps", "2"],
                     ["btf", "train-diffusion", fx / "data", "--out", out, "--steps", "2"],
                     ["btf", "dataset", "--out", out, "--count", "16"],
                     ["face", "train-models", "--out", out],
                     ["morph", "errors", bench, bench / "morph", "--out", out]):
            code, err = run(argv, capsys)
            assert code == 2 and msg in err, (argv, err)
    assert (fx / "afile").read_text() == "x"


def test_13_14_nested_settings_and_sizes_name_their_flags(tmp_path, capsys):
    base = ["face", "train-models", "--out", tmp_path / "r"]
    for argv, msg in ((["--completion-seconds", "nan"], "--completion-seconds must be a finite number"),
                      (["--decomp-seconds", "-5"], "--decomp-seconds must be"),
                      (["--superres-seconds", "inf"], "--superres-seconds must be a finite number"),
                      (["--uv-res", "16"], "argument --uv-res: invalid choice: 16 (choose from 64, 128)")):
        code, err = run([*base, *argv], capsys)
        assert code == 2 and msg in err and "max_seconds" not in err, (argv, err)
    assert not (tmp_path / "r").exists()


def test_15_a_bad_crop_is_named_and_leaves_no_folder(bench, tmp_path, capsys):
    code, err = run(["diffrender", "train", bench, "--out", tmp_path / "dr" / "s1", "--crop", "9", "--widths", "8", "16",
                     "16", "--steps", "2", "--threads", "1"], capsys)
    assert code == 2 and "--crop 9 must divide by 4" in err, err
    assert not (tmp_path / "dr").exists()


def test_16_a_run_folder_of_another_kind_is_bad_input(bench, tmp_path, capsys):
    code, err = run(["diffrender", "render", bench, "--run", bench / "morph", "--out", tmp_path / "o"], capsys)
    assert code == 2 and "morph/checkpoint.npz: a MorphStage checkpoint, not a diffusion renderer's" in err, err
    code, err = run(["btf", "generate", "--run", bench / "morph", "--keywords", "red", "--out", tmp_path / "g.npz"],
                    capsys)
    assert code == 2 and "not a material diffusion model's" in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == []


# 17 (SIGINT to the driver of a pool): tests/foundation/test_pool.py::test_ctrl_c_to_the_driver_stops_its_workers_at_once


def test_18_user_hdri_files_light_a_face_benchmark(tmp_path):
    from foundation.assets import HDRI_DIR
    from inverse.face import FaceBenchmarkSettings, load_benchmark, make_benchmark

    for name, src in (("park", "sunset"), ("hall", "studio")):
        shutil.copyfile(HDRI_DIR / f"{src}.exr", tmp_path / f"{name}.exr")
    s = FaceBenchmarkSettings(uv_res=16, n_lights=2, views=((0.0, 0.0),), render_res=8, render_spp=1,
                              heldout_hdris=("sunset",), lighting="hdri",
                              lighting_hdris=(str(tmp_path / "park.exr"), str(tmp_path / "hall.exr")))
    b = load_benchmark(make_benchmark(PAUL, tmp_path / "b", s, show_progress=False))
    assert [light.hdri for light in b.meta.lights] == ["hdri/park.exr", "hdri/hall.exr"]
    assert (tmp_path / "b" / "hdri" / "park.exr").is_file() and (tmp_path / "b" / "hdri" / "hall.exr").is_file()
