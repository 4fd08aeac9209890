"""Bad input, tried as a new user would (shared/bad-input-findings.md): every case ends with one line that
names the file or the flag, exit code 2 for a bad argument and 1 for a failure, no traceback, and nothing
destroyed or half-written."""

from __future__ import annotations

import os
import shutil
import stat
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from photoreal.cli import main

ROOT = Path(__file__).resolve().parents[2]
ASSETS = ROOT / "scenes" / "assets"
PAUL = ASSETS / "face" / "cyberheads" / "paul.obj"
ARMADILLO = ASSETS / "meshes" / "armadillo.ply"
LANDMARKS = Path(__file__).resolve().parents[1] / "data" / "astronaut_landmarks.npy"


def run(argv, capsys) -> tuple[int, str]:
    code = main([str(a) for a in argv])
    err = capsys.readouterr().err
    assert "Traceback" not in err
    if code not in (0, 130):
        lines = [x for x in err.splitlines() if x.startswith("photoreal: error:") or x.startswith("usage:")]
        assert lines, err
    return code, err


@pytest.fixture
def files(tmp_path):
    """``afile`` (a regular file) and ``adir/`` (an existing folder), as in the findings."""
    (tmp_path / "afile").write_text("x")
    (tmp_path / "adir").mkdir()
    return tmp_path


@pytest.fixture(scope="module")
def tiny_morph(tmp_path_factory):
    from inverse.morph import MorphBenchmarkSettings, make_morph_benchmark

    out = tmp_path_factory.mktemp("bad") / "bench"
    return make_morph_benchmark(ARMADILLO, out, MorphBenchmarkSettings(n_views=4, resolution=32, spp=2,
                                                                       coarse_vertices=300), show_progress=False)


# -- data loss and silently wrong results ------------------------------------------------------------------------


@pytest.mark.parametrize("cmd", [["face", "make-benchmark", "--scan", PAUL, "--uv-res", "16", "--lights", "1"],
                                 ["morph", "make-benchmark", "--mesh", ARMADILLO, "--views", "4", "--resolution", "16"]])
def test_out_never_deletes_a_folder_the_program_did_not_write(cmd, tmp_path, capsys):
    p = tmp_path / "p"
    p.mkdir()
    (p / "thesis.txt").write_text("years of work")
    code, err = run([*cmd, "--out", p], capsys)
    assert code == 2 and f"--out: {p}: holds files `photoreal {' '.join(cmd[:2])}` did not write (thesis.txt)" in err
    assert (p / "thesis.txt").read_text() == "years of work" and sorted(x.name for x in p.iterdir()) == ["thesis.txt"]
    cwd = os.getcwd()
    try:
        os.chdir(p)
        code, err = run([*cmd, "--out", ".."], capsys)
    finally:
        os.chdir(cwd)
    assert code == 2 and "--out: .." in err and (p / "thesis.txt").is_file()


def test_neural_material_of_another_basis_is_refused(tmp_path, capsys):
    from mi_plugins.neural_basis import load_basis, save_basis

    basis = load_basis(ASSETS / "neural" / "basis.npz")
    basis.meta = dict(basis.meta, id="another-basis")
    save_basis(tmp_path / "other_basis.npz", basis)
    scene = tmp_path / "s.xml"
    scene.write_text(f"""<scene version="3.0.0"><integrator type="path"/>
<sensor type="perspective"><film type="hdrfilm"><integer name="width" value="8"/><integer name="height" value="8"/></film></sensor>
<shape type="sphere"><bsdf type="neural_btf"><string name="basis" value="{tmp_path / 'other_basis.npz'}"/>
<string name="material" value="{ASSETS / 'neural' / 'leather.npz'}"/></bsdf></shape>
<emitter type="constant"/></scene>""")
    code, err = run(["render", scene, "-o", tmp_path / "o.exr"], capsys)
    assert code == 2 and "leather.npz was fitted to basis" in err and "other_basis.npz is basis 'another-basis'" in err
    assert not (tmp_path / "o.exr").exists()


@pytest.mark.parametrize("argv,flag", [
    (["--views", "2"], "--views must be ≥ 4"), (["--views", "0"], "--views must be ≥ 4"),
    (["--views", "-3"], "--views must be ≥ 4"), (["--spp", "0"], "--spp must be ≥ 1"),
    (["--spp", "-4"], "--spp must be ≥ 1"), (["--resolution", "0"], "--resolution must be ≥ 16"),
    (["--resolution", "-8"], "--resolution must be ≥ 16"), (["--photo-max-depth", "1"], "--photo-max-depth must be ≥ 2")])
def test_morph_benchmark_settings_are_checked_before_any_work(argv, flag, tmp_path, capsys):
    code, err = run(["morph", "make-benchmark", "--mesh", ARMADILLO, "--out", tmp_path / "b", *argv], capsys)
    assert code == 2 and flag in err and not (tmp_path / "b").exists()


@pytest.mark.parametrize("argv,flag", [
    (["--lambda", "nan"], "--lambda must be a finite number"), (["--lambda", "-1"], "--lambda must be > 0"),
    (["--planarity-weight", "nan"], "--planarity-weight must be a finite number"),
    (["--target-vertices", "-5"], "--target-vertices must be ≥ 100"), (["--resolution", "0"], "--resolution must be ≥ 8"),
    (["--iterations", "-1"], "--iterations must be ≥ 0"), (["--lr", "-0.1"], "--lr must be ≥ 0"),
    (["--lr", "nan"], "--lr must be a finite number"),
    (["--backdrop", "on"], "argument --backdrop: invalid choice")])
def test_morph_run_flags_are_named(argv, flag, tiny_morph, tmp_path, capsys):
    code, err = run(["morph", "run", tiny_morph, "--out", tmp_path / "m", *argv], capsys)
    assert code == 2 and flag in err, err
    assert not (tmp_path / "m").exists()


def test_morph_run_damaged_inputs(tiny_morph, tmp_path, capsys):
    bench = tmp_path / "bench"
    shutil.copytree(tiny_morph, bench)
    out = tmp_path / "m"
    out.mkdir()
    (out / ".photoreal-output.json").write_text('{"command": "morph run"}')  # a previous run's folder
    (out / "checkpoint.npz").write_bytes(b"PK\x03\x04 cut short")
    code, err = run(["morph", "run", bench, "--out", out, "--iterations", "2", "--min-vertices", "0"], capsys)
    assert code == 1 and f"{out / 'checkpoint.npz'}: damaged checkpoint" in err and "delete it to start over" in err
    data = (bench / "coarse.ply").read_bytes()
    (bench / "coarse.ply").write_bytes(data[: len(data) // 2])
    code, err = run(["morph", "run", bench, "--out", tmp_path / "m2"], capsys)
    assert code == 2 and "coarse.ply: truncated or damaged PLY" in err
    (bench / "coarse.ply").unlink()
    code, err = run(["morph", "run", bench, "--out", tmp_path / "m2"], capsys)
    assert code == 2 and "coarse.ply: missing from the benchmark" in err


def test_face_fit_flags_and_benchmark_files(tmp_path, capsys):
    for argv, flag in ((["--iterations", "-1", "-1"], "--iterations must be ≥ 0"),
                       (["--iterations", "3"], "--iterations: one Adam step count per pyramid level"),
                       (["--refine-renders", "-1"], "--iterations must be ≥ 0")):
        code, err = run(["face", "fit", tmp_path, "--json", tmp_path / "m.json", *argv], capsys)
        assert code == 2 and flag in err, err
    bench = tmp_path / "b"
    bench.mkdir()
    for text, msg in (("", "benchmark.json: empty file"), ("[1, 2]", "benchmark.json: expected a JSON object"),
                      ("{", "benchmark.json: not valid JSON (line 1")):
        (bench / "benchmark.json").write_text(text)
        code, err = run(["face", "fit", bench, "--json", tmp_path / "m.json"], capsys)
        assert code == 2 and msg in err, err
    assert not (tmp_path / "m.json").exists()


def test_face_fit_names_a_foreign_exr(tmp_path, capsys):
    from inverse.face import FaceBenchmarkSettings, make_benchmark

    b = make_benchmark(PAUL, tmp_path / "b", FaceBenchmarkSettings(uv_res=16, n_lights=1, views=((0.0, 0.0),),
                                                                   render_res=8, render_spp=1,
                                                                   heldout_hdris=("sunset",)), show_progress=False)
    from foundation import imageio

    imageio.write_exr(b / "observations.exr", {"something_else": np.zeros((16, 16, 3), np.float32)})
    code, err = run(["face", "fit", b, "--json", tmp_path / "m.json"], capsys)
    assert code == 2 and "observations.exr: not this benchmark's layers (missing v0_l0)" in err


def test_btf_fit_heldout_fraction(tmp_path, capsys):
    for value, msg in (("-0.5", "must be in (0, 1), got -0.5"), ("nan", "must be a finite number"),
                       ("1.5", "must be in (0, 1), got 1.5")):
        code, err = run(["btf", "fit", tmp_path / "x.npz", "--basis", ASSETS / "neural" / "basis.npz", "--out",
                         tmp_path / "m.npz", "--heldout-fraction", value], capsys)
        assert code == 2 and f"--heldout-fraction {msg}" in err, err


def test_from_photo_garbage_leaves_no_output(tmp_path, capsys):
    from PIL import Image

    np.save(tmp_path / "zeros.npy", np.zeros((468, 3)))
    np.save(tmp_path / "big.npy", np.load(LANDMARKS) * 100)
    (tmp_path / "obj.json").write_text('[{"x": 1}]')
    Image.fromarray(np.zeros((1, 1, 3), np.uint8)).save(tmp_path / "tiny.png")
    cases = ((["astronaut", "--landmarks", tmp_path / "zeros.npy"], "zeros.npy: landmarks are collapsed"),
             (["astronaut", "--landmarks", tmp_path / "big.npy"], "big.npy: x, y must be normalised"),
             (["astronaut", "--landmarks", tmp_path / "obj.json"], "obj.json: not a readable landmark file"),
             ([tmp_path / "tiny.png", "--landmarks", LANDMARKS], "the photo is 1×1 pixels"))
    for argv, msg in cases:
        code, err = run(["face", "from-photo", *argv, "--out", tmp_path / "out", "--uv-res", "32"], capsys)
        assert code == 2 and msg in err, err
        assert not (tmp_path / "out").exists()


def test_meshes_with_nan_or_no_extent_are_refused_and_cwd_kept(tmp_path, capsys):
    from foundation.mesh import MeshError, load_mesh_any

    nan = tmp_path / "nan.obj"
    nan.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv nan 1 1\nf 1 2 3\nf 2 4 3\n")
    with pytest.raises(MeshError, match="nan.obj: 1 of 4 vertices are NaN/Inf or unreadable"):
        load_mesh_any(nan)
    flat = tmp_path / "point.obj"
    flat.write_text("v 1 1 1\nv 1 1 1\nv 1 1 1\nf 1 2 3\n")
    code, err = run(["morph", "make-benchmark", "--mesh", flat, "--out", tmp_path / "b"], capsys)
    assert code == 2 and "point.obj: degenerate mesh" in err and not (tmp_path / "b").exists()
    bad = tmp_path / "bad.ply"
    bad.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nend_header\n1\n")
    cwd = os.getcwd()
    with pytest.raises(MeshError, match="bad.ply: cannot read mesh"):
        load_mesh_any(bad)
    assert os.getcwd() == cwd


# -- output locations are checked before the work ----------------------------------------------------------------


def test_output_paths_are_checked_first(files, capsys):
    t = files
    scene = ROOT / "scenes" / "material_test.xml"
    (t / "out" / "d.exr").mkdir(parents=True)
    cases = [
        (["render", scene, "-o", t / "out" / "d.exr", "--spp", "1"], "d.exr: is a folder"),
        (["render", scene, "-o", t / "afile" / "x.exr", "--spp", "1"], "afile is a file, not a folder"),
        (["face", "fit", t / "nobench", "--json", t / "adir"], "--json: " + str(t / "adir") + ": is a folder"),
        (["face", "fit", t / "nobench", "--json", t / "m.json", "--maps", t / "afile"], "--maps: " + str(t / "afile")),
        (["btf", "train-basis", t / "nodata", "--out", t / "adir"], "--out: " + str(t / "adir") + ": is a folder"),
        (["btf", "render-data", "--out", t / "afile"], "--out: " + str(t / "afile") + ": is a file"),
        (["demo", "--out", t / "afile"], "--out: " + str(t / "afile") + ": is a file"),
        (["face", "from-photo", "astronaut", "--out", t / "afile"], "--out: " + str(t / "afile") + ": is a file"),
        (["face", "make-benchmark", "--scan", PAUL, "--out", t / "afile"], "--out: " + str(t / "afile") + ": is a file"),
        (["render", scene, "-o", "/proc/x.exr", "--spp", "1"], "/proc/x.exr"),
    ]
    for argv, msg in cases:
        code, err = run(argv, capsys)
        assert code == 2 and msg in err, (argv, err)
        assert ".tmp" not in err and "/proc/.x" not in err


# -- one line instead of a traceback -----------------------------------------------------------------------------


def test_render_seed_resolution_and_scene_without_sensor(tmp_path, capsys):
    scene = ROOT / "scenes" / "material_test.xml"
    code, err = run(["render", scene, "-o", tmp_path / "a.exr", "--spp", "1", "--resolution", "8", "8",
                     "--seed", "50000"], capsys)
    assert code == 0, err  # seeds above 42949 used to overflow the 32-bit sampler seed
    code, err = run(["render", scene, "-o", tmp_path / "b.exr", "--seed", "-5"], capsys)
    assert code == 2 and "seed must be in [0, 2147483647], got -5" in err
    code, err = run(["render", scene, "-o", tmp_path / "b.exr", "--resolution", "100000", "100000"], capsys)
    assert code == 2 and "resolution must be two integers in [1, 16384]" in err
    nosensor = tmp_path / "nosensor.xml"
    nosensor.write_text('<scene version="3.0.0"><shape type="sphere"/></scene>')
    code, err = run(["render", nosensor, "-o", tmp_path / "c.exr"], capsys)
    assert code == 2 and "nosensor.xml: the scene has no <sensor>" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.exr", "a.png", "nosensor.xml"]


def test_neural_material_without_texels_is_named(tmp_path):
    from mi_plugins.neural_basis import NeuralBTFError, NeuralMaterial

    with pytest.raises(NeuralBTFError, match="t_off must be a square"):
        NeuralMaterial(np.zeros((0, 0, 8), np.float32), np.zeros((0, 0, 8), np.float32))


@pytest.mark.parametrize("variant,msg", [("nonsense", "is not a Mitsuba variant"),
                                         ("scalar_rgb", "needs an RGB variant with automatic differentiation")])
def test_unusable_variant_is_one_line(variant, msg, tmp_path):
    env = dict(os.environ, PHOTOREAL_VARIANT=variant)
    r = subprocess.run([sys.executable, "-m", "photoreal.cli", "render", str(ROOT / "scenes" / "material_test.xml"),
                        "-o", str(tmp_path / "o.exr")], env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and msg in r.stderr and "Traceback" not in r.stderr, r.stderr


def test_interrupt_inside_a_python_plugin_exits_130(tmp_path, capsys, monkeypatch):
    import mitsuba as mi

    def interrupted(*a, **k):  # what Dr.Jit raises when Ctrl-C lands inside a Python BSDF's traced code
        raise RuntimeError("drjit.detail.trace_func(): KeyboardInterrupt")

    monkeypatch.setattr(mi, "render", interrupted)
    code, err = run(["render", ROOT / "scenes" / "material_test.xml", "-o", tmp_path / "o.exr", "--spp", "1"], capsys)
    assert code == 130 and "interrupted" in err and not (tmp_path / "o.exr").exists()


def test_truncated_texture_is_named(tmp_path, capsys):
    scan = tmp_path / "scan"
    shutil.copytree(PAUL.parent, scan)
    tex = scan / "paul_tex.png"
    tex.write_bytes(tex.read_bytes()[:2000])
    code, err = run(["face", "make-benchmark", "--scan", scan / "paul.obj", "--out", tmp_path / "b"], capsys)
    assert code == 2 and "paul_tex.png: not a readable image" in err and not (tmp_path / "b").exists()


def test_corrupt_gan_checkpoint_is_named(tiny_morph, tmp_path, capsys):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "checkpoint.npz").write_bytes(b"\x00" * 64)
    code, err = run(["gan", "eval", tiny_morph, "--run", run_dir], capsys)
    assert code == 1 and "checkpoint.npz: damaged checkpoint" in err and "delete it to start over" in err


# -- files --------------------------------------------------------------------------------------------------------


def test_written_files_get_ordinary_permissions(tmp_path):
    from foundation import imageio
    from foundation.files import write_json

    old = os.umask(0o022)
    try:
        import foundation.files as ff

        ff._FILE_MODE = None  # re-read the umask set above
        write_json(tmp_path / "a.json", {"a": 1})
        imageio.write_png(tmp_path / "a.png", np.zeros((2, 2, 3), np.float32))
    finally:
        os.umask(old)
        ff._FILE_MODE = None
    for name in ("a.json", "a.png"):
        assert stat.S_IMODE((tmp_path / name).stat().st_mode) == 0o644, name


def test_flags_a_command_does_not_use_are_refused(capsys):
    """`bench morph --resolution 64` used to be accepted and ignored: each benchmark takes only its own flags."""
    code, err = run(["bench", "morph", "--json", "x.json", "--resolution", "64"], capsys)
    assert code == 2 and "unrecognized arguments: --resolution 64" in err


def test_remaking_a_benchmark_never_takes_a_run_stored_inside_it(tmp_path, capsys):
    argv = ["morph", "make-benchmark", "--mesh", ARMADILLO, "--views", "4", "--resolution", "16", "--spp", "1",
            "--out", tmp_path / "b"]
    assert run(argv, capsys)[0] == 0
    assert run(argv, capsys)[0] == 0  # its own previous output: replaced
    (tmp_path / "b" / "morph").mkdir()
    (tmp_path / "b" / "morph" / "checkpoint.npz").write_bytes(b"hours of work")
    code, err = run(argv, capsys)
    assert code == 2 and "also holds what this command did not write (morph)" in err
    assert (tmp_path / "b" / "morph" / "checkpoint.npz").read_bytes() == b"hours of work"


def test_a_bench_work_folder_made_with_other_photos_is_refused(tiny_morph, tmp_path):
    """The GAN and diffusion-renderer benches reuse their work folders; a benchmark there whose photos had another
    sample count (the diffusion bench's 1024 vs the GAN bench's 64) would mix two benchmarks' results silently."""
    from foundation.errors import UsageError
    from photoreal.benchmarks.gan import GanBenchSettings, prepare_case

    shutil.copytree(tiny_morph, tmp_path / "village" / "benchmark")
    with pytest.raises(UsageError, match=r"village/benchmark: its photos were rendered at 2 spp.*1024 \(photo_spp\)"):
        prepare_case("village", tmp_path, GanBenchSettings(photo_spp=1024), show_progress=False)
    with pytest.raises(UsageError, match="photo_spp"):
        GanBenchSettings(photo_spp=0)
