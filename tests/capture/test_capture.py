"""Captures: the Mitsuba sensor of a capture camera against its pinhole projection, import round trips of the three
formats (cameras within 1e-6, renders equal), the undistortion against an exact distortion of a known image, and bad
captures refused in one line with nothing written."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from inverse.capture import (Capture, CaptureCamera, CaptureMeta, export_capture, import_capture, load_capture,
                             read_source, render_mesh, sensor, undistort)
from photoreal.cli import main

ROOT = Path(__file__).resolve().parents[2]
ARMADILLO = ROOT / "scenes" / "assets" / "meshes" / "armadillo.ply"


def _look(eye, target) -> list[list[float]]:
    """cam_to_world (COLMAP axes) of a camera at ``eye`` looking at ``target``, y up."""
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, -1.0, 0.0])  # COLMAP: y down, so image right = z × (−up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    m = np.eye(4)
    m[:3, :3] = np.stack([x, y, z], 1)
    m[:3, 3] = eye
    return m.tolist()


def _capture(tmp: Path, n: int = 4, w: int = 40, h: int = 30) -> Capture:
    """An in-memory capture: cameras on a circle with their own focal lengths and off-centre principal points."""
    rng = np.random.default_rng(0)
    cams = []
    for k in range(n):
        a = 2 * np.pi * k / n
        cams.append(CaptureCamera(f"p{k}", w, h, 35.0 + 3 * k, w / 2 + 2.5 - k, h / 2 - 1.5 + 0.5 * k,
                                  _look([3 * np.cos(a), 0.8, 3 * np.sin(a)], [0.0, 0.1, 0.0])))
    meta = CaptureMeta(cams, [c.name for c in cams[:-1]], [cams[-1].name])
    return Capture(tmp, meta, {c.name: rng.uniform(0, 1, (h, w, 3)).astype(np.float32) for c in cams})


def test_the_mitsuba_sensor_sees_what_the_pinhole_projects():
    """Oracle: a world point projected by the pinhole (f, cx, cy, COLMAP axes) lies on Mitsuba's ray through that
    pixel (principal_point_offset = 0.5 − c/size, x and y flipped)."""
    import mi_plugins  # noqa: F401
    import mitsuba as mi

    cam = CaptureCamera("c", 64, 48, 50.0, 36.5, 20.25, _look([1.0, 2.0, 3.0], [0.0, 0.0, 0.0]))
    s = mi.load_dict(sensor(cam))
    pts = np.random.default_rng(1).normal(scale=0.5, size=(20, 3))
    uv, z = cam.project(pts)
    assert (z > 0).all()
    for p, (u, v) in zip(pts, uv):
        ray, _ = s.sample_ray(0.0, 0.5, mi.Point2f(float(u) / cam.width, float(v) / cam.height), mi.Point2f(0.5, 0.5))
        o, d = np.array(ray.o, np.float64).ravel(), np.array(ray.d, np.float64).ravel()
        to, d = (p - o) / np.linalg.norm(p - o), d / np.linalg.norm(d)
        assert np.degrees(np.linalg.norm(np.cross(to, d))) < 1e-4  # the same ray, to float32 precision


@pytest.mark.parametrize("fmt", ["colmap", "colmap-text", "transforms"])
def test_export_then_import_gives_the_same_cameras_and_photos(fmt, tmp_path):
    cap = _capture(tmp_path / "mem")
    exp = export_capture(cap, tmp_path / "exp", fmt)
    # the first photo's EXIF says a flash fired and how it was exposed (PNG's eXIf chunk): 1/250 s at f/13, ISO 200;
    # the import records both (exposure t × ISO / N² = 0.004 × 200 / 169), the others stay unknown
    from PIL import Image

    first = cap.meta.cameras[0].name
    with Image.open(exp / "images" / f"{first}.png") as im:
        exif = Image.Exif()
        exif[0x8769] = {0x9209: 9, 0x829A: 0.004, 0x829D: 13.0, 0x8827: 200}  # Flash (fired), time, f-number, ISO
        im.copy().save(exp / "images" / f"{first}.png", exif=exif)
    src = read_source(exp)
    back = load_capture(import_capture(src, tmp_path / "cap", resolution=None, show_progress=False,
                                       triangulate=False))
    n = len(cap.meta.cameras)
    assert [back.cameras[c.name].flash for c in cap.meta.cameras] == [True] + [None] * (n - 1)
    exposures = [back.cameras[c.name].exposure for c in cap.meta.cameras]
    assert exposures[0] == pytest.approx(0.004 * 200 / 169, rel=1e-6) and exposures[1:] == [None] * (n - 1)
    for c in cap.meta.cameras:
        b = back.cameras[c.name]
        assert (b.width, b.height) == (c.width, c.height)
        assert np.abs(b.matrix - c.matrix).max() < 1e-6 and abs(b.f - c.f) < 1e-6
        assert abs(b.cx - c.cx) < 1e-6 and abs(b.cy - c.cy) < 1e-6
        # photos: 8-bit sRGB PNG in between (half a quantisation step in sRGB), undistortion an identity
        from foundation.imageio import linear_to_srgb

        assert np.abs(linear_to_srgb(back.photo(c.name)) - linear_to_srgb(cap.photo(c.name))).max() < 0.6 / 255 + 2e-3
    assert back.meta.train and back.meta.test and back.meta.source["format"] == fmt.split("-")[0].replace(
        "transforms", "transforms")


@pytest.fixture(scope="module")
def bench(tmp_path_factory):
    from inverse.morph import MorphBenchmarkSettings, benchmark_capture, load_morph_benchmark, make_morph_benchmark

    out = make_morph_benchmark(ARMADILLO, tmp_path_factory.mktemp("cap") / "b",
                               MorphBenchmarkSettings(n_views=4, resolution=32, spp=2, coarse_vertices=300),
                               show_progress=False)
    return benchmark_capture(load_morph_benchmark(out))


@pytest.mark.parametrize("fmt", ["colmap", "transforms", "llff"])
def test_a_benchmark_exported_and_imported_renders_the_same(fmt, bench, tmp_path):
    """The three formats on a morph benchmark (LLFF: one focal length, centred principal points): the cameras come
    back within 1e-6 and a render of the coarse mesh through them equals the render through the originals (same
    seed: within float32 of the camera, far below the Monte-Carlo noise of 4 spp)."""
    from foundation.mesh import read_ply_colours

    src = read_source(export_capture(bench, tmp_path / "exp", fmt))
    back = load_capture(import_capture(src, tmp_path / "cap", resolution=None, mesh=bench.mesh, show_progress=False))
    v, f, col = read_ply_colours(bench.mesh)
    for c in bench.meta.cameras:
        b = back.cameras[c.name]
        assert np.abs(b.matrix - c.matrix).max() < 1e-6 and abs(b.f - c.f) < 1e-6
    c = bench.meta.cameras[0]
    a, b = render_mesh(v, f, col, c, spp=4), render_mesh(v, f, col, back.cameras[c.name], spp=4)
    assert np.abs(a - b).mean() < 1e-4, np.abs(a - b).mean()
    assert back.meta.mesh == "mesh.ply"


def test_undistortion_puts_every_point_back_within_a_pixel(tmp_path):
    """Oracle: bright dots at known pinhole positions, drawn where an OPENCV camera (k1, k2, p1, p2) images them
    (pycolmap's own projection), then undistorted here: each dot's centroid lands within a pixel of where the
    pinhole puts it (measured: 0.06 px at worst; the distortion moves them by up to 6.3 px)."""
    from inverse.capture import camera
    from inverse.capture.build import working_camera

    w, h = 160, 120
    cam = camera("OPENCV", w, h, [100.0, 100.0, 82.0, 58.0, -0.28, 0.09, 0.001, -0.0015], "test")
    _, pin = working_camera("d", cam, np.eye(4), None)
    rays = np.array([[x, y, 1.0] for x in np.linspace(-0.55, 0.55, 6) for y in np.linspace(-0.4, 0.4, 5)])
    dots = cam.img_from_cam(rays, False)
    yy, xx = np.mgrid[0:h, 0:w] + 0.5
    img = np.zeros((h, w, 3), np.float32)
    for u, v in dots:
        img += np.exp(-((xx - u) ** 2 + (yy - v) ** 2) / (2 * 1.2 ** 2))[..., None]
    out, inside = undistort(img, cam, pin)
    assert inside.mean() > 0.9
    want = np.stack([pin.f * rays[:, 0] + pin.cx, pin.f * rays[:, 1] + pin.cy], 1)
    errs = []
    for u, v in want:
        win = (np.abs(xx - u) < 4) & (np.abs(yy - v) < 4)
        wgt = out[..., 0] * win
        errs.append(np.hypot((wgt * xx).sum() / wgt.sum() - u, (wgt * yy).sum() / wgt.sum() - v))
    assert max(errs) < 1.0, max(errs)
    assert max(errs) < 0.2  # bilinear resampling of a 1.2 px blob: a tenth of a pixel, measured 0.06


def test_a_pincushion_lens_is_undistorted_without_blank_pixels():
    """A positive radial term magnifies toward the frame's edges: the pinhole keeps the photo's size and zooms in
    just enough that every pixel has data (COLMAP's undistorter without blank pixels). Oracle: a linear ramp
    (bilinear sampling is exact on it) says where each output pixel sampled the photo, which must be where the source
    model images that pixel's ray. Barrel and no distortion keep the focal length."""
    from inverse.capture import camera
    from inverse.capture.build import working_camera

    w, h = 160, 120
    yy, xx = np.mgrid[0:h, 0:w] + 0.5
    ramp = np.stack([xx, yy, np.ones_like(xx)], -1).astype(np.float32)  # each pixel holds its own centre
    for k1 in (0.1, 0.02, 0.0, -0.1):
        cam = camera("SIMPLE_RADIAL", w, h, [100.0, 80.0, 60.0, k1], "test")
        src, pin = working_camera("d", cam, np.eye(4), None)
        out, inside = undistort(ramp, src, pin)
        assert inside.all()
        assert pin.f > 100.0 if k1 > 0 else pin.f == 100.0
        if k1 > 0:  # the least zoom: a thousandth less leaves the rim without data
            smaller = CaptureCamera("d", w, h, pin.f * 0.999, pin.cx, pin.cy, pin.cam_to_world)
            assert not undistort(ramp, src, smaller)[1].all()
        rays = np.stack([(xx - pin.cx) / pin.f, (yy - pin.cy) / pin.f, np.ones_like(xx)], -1).reshape(-1, 3)
        want = np.asarray(src.img_from_cam(rays, False)).reshape(h, w, 2)
        # inside the half-pixel rim, where bilinear sampling of the ramp is exact
        core = (want[..., 0] > 0.5) & (want[..., 0] < w - 0.5) & (want[..., 1] > 0.5) & (want[..., 1] < h - 0.5)
        assert core.mean() > 0.95 and np.abs(out[..., :2] - want)[core].max() < 1e-3


def _run(argv, capsys) -> tuple[int, str]:
    code = main([str(a) for a in argv])
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return code, err


def test_bad_captures_are_named_and_nothing_is_written(bench, tmp_path, capsys):
    out = tmp_path / "out"

    def fails(source, msg, code=2):
        c, err = _run(["capture", "import", source, "--out", out, "--mesh", bench.mesh], capsys)
        assert c == code and msg in err.strip().splitlines()[-1], err
        assert not out.exists()

    col = export_capture(bench, tmp_path / "col", "colmap")
    (col / "images" / "view01.png").unlink()
    fails(col, f"{col / 'images' / 'view01.png'}: photo missing")
    txt = export_capture(bench, tmp_path / "txt", "colmap-text")
    images = txt / "sparse" / "0" / "images.txt"
    lines = images.read_text().splitlines()
    lines = [(" ".join(ln.split()[:8] + ["99"] + ln.split()[9:]) if ln and not ln.startswith("#") and
              ln.split()[-1].endswith(".png") else ln) for ln in lines]
    images.write_text("\n".join(lines) + "\n")
    fails(txt, "not a readable COLMAP model")  # an image naming a camera the model lacks
    cut = export_capture(bench, tmp_path / "cut", "colmap")
    data = (cut / "sparse" / "0" / "cameras.bin").read_bytes()
    (cut / "sparse" / "0" / "cameras.bin").write_bytes(data[: len(data) // 2])
    fails(cut, f"{cut / 'sparse' / '0'}: not a readable COLMAP model")
    tj = export_capture(bench, tmp_path / "tj", "transforms")
    d = json.loads((tj / "transforms.json").read_text())
    for fr in d["frames"]:
        for k in ("fl_x", "fl_y"):
            fr.pop(k)
    (tj / "transforms.json").write_text(json.dumps(d))
    fails(tj, f"{tj / 'transforms.json'} frame 0: no intrinsics (fl_x/fl_y or camera_angle_x")
    d = json.loads((tj / "transforms.json").read_text())
    for fr in d["frames"]:
        fr["fl_x"] = 30.0
    d["frames"][2]["transform_matrix"][0][3] = float("nan")
    (tj / "transforms.json").write_text(json.dumps(d))
    fails(tj, f"{tj / 'transforms.json'} frame 2: pose has NaN/Inf values")
    ll = export_capture(bench, tmp_path / "ll", "llff")
    (ll / "images" / "view03.png").unlink()
    fails(ll, "4 poses for 3 photos")
    pb = np.load(ll / "poses_bounds.npy")
    shutil.copy(tmp_path / "col" / "images" / "view00.png", ll / "images" / "view03.png")
    pb[1, 3] = np.nan
    np.save(ll / "poses_bounds.npy", pb)
    fails(ll, "row 1 (view01.png): NaN/Inf in the pose")
    fails(tmp_path / "nothing", "no such file or folder")


def test_the_capture_commands_end_to_end(bench, tmp_path, capsys):
    exp = tmp_path / "exp"
    assert _run(["capture", "export", bench.path, "--format", "transforms", "--out", exp], capsys)[0] == 0
    code, _ = _run(["capture", "import", exp, "--out", tmp_path / "cap", "--mesh", bench.mesh, "--resolution",
                    "24"], capsys)
    assert code == 0
    cap = load_capture(tmp_path / "cap")
    assert {(c.width, c.height) for c in cap.meta.cameras} == {(24, 24)}  # longest side 24
    assert abs(cap.meta.cameras[0].f - bench.meta.cameras[0].f * 24 / 32) < 1e-9
    code, _ = _run(["capture", "score", tmp_path / "cap", "--spp", "2", "--json", tmp_path / "s.json"], capsys)
    s = json.loads((tmp_path / "s.json").read_text())
    assert code == 0 and set(s["mean"]) == {"psnr", "ssim", "flip", "perceptual"} and len(s["views"]) == 1
    assert s["mean"]["psnr"] > 10  # the coarse armadillo against its own photo: far from noise
    # the morph takes the capture: a short run writes its mesh, the fitted light and what the cameras did
    run = tmp_path / "morph"
    code, err = _run(["morph", "run", tmp_path / "cap", "--out", run, "--iterations", "3", "--resolution", "24",
                      "--no-early-stop", "--min-vertices", "0", "--lambda-select", "2", "--planarity-select",
                      "--step-select-quantile", "1", "--refine-cameras", "auto", "--json", tmp_path / "m.json"], capsys)
    assert code == 0, err
    m = json.loads((tmp_path / "m.json").read_text())
    assert (run / "morphed.ply").is_file() and (run / "environment.exr").is_file()
    assert m["photo_fit"]["refined_cameras"] and m["photo_fit"]["exposure"] and m["photo_fit"]["fitted_light"]
    assert np.isfinite(m["psnr_heldout_morphed"]) and np.isnan(m["chamfer_morphed"])  # no truth: no Chamfer
    code, err = _run(["morph", "run", tmp_path / "cap", "--gcn", "--out", tmp_path / "g"], capsys)
    assert code == 2 and "--gcn" in err and not (tmp_path / "g").exists()
    bare = tmp_path / "bare"
    assert _run(["capture", "import", exp, "--out", bare, "--resolution", "24"], capsys)[0] == 0
    code, err = _run(["morph", "run", bare, "--out", tmp_path / "b"], capsys)
    assert code == 2 and "no coarse mesh" in err


def test_the_poisson_mesh_of_sparse_points_is_the_surface_they_sample():
    """Oracle: 3000 noisy points (σ 0.5 %) on a unit sphere, cameras around it: the coarse mesh's vertices lie within
    1 % of the radius in the median, 4 % at the 99th percentile, 10 % at worst (measured 2.5 % and 8.8 %, near the
    holes the trimming leaves), the mesh faces outward (normals turned toward the nearest camera), colours come from
    the points; with the side each point was seen from, the untrimmed surface is closed and faces outward everywhere."""
    from foundation.mesh import vertex_normals
    from inverse.capture import coarse_mesh_from_points

    rng = np.random.default_rng(3)
    p = rng.normal(size=(3000, 3))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    pts = p * (1 + rng.normal(scale=0.005, size=(3000, 1)))
    cols = np.repeat((p[:, :1] > 0).astype(np.float64), 3, 1)
    a = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    cams = np.stack([3 * np.cos(a), 0.5 * np.sin(3 * a), 3 * np.sin(a)], 1)
    v, f, c = coarse_mesh_from_points(pts, cols, cams)
    r = np.linalg.norm(v, axis=1)
    e = np.abs(r - 1)
    assert len(f) > 500 and np.median(e) < 0.01 and np.quantile(e, 0.99) < 0.04 and e.max() < 0.1
    assert (np.einsum("ij,ij->i", vertex_normals(v, f), v / r[:, None]) > 0).mean() > 0.95
    assert np.mean((c[:, 0] > 0.5) == (v[:, 0] > 0)) > 0.97
    # with the side each point was seen from (the mean direction to the cameras in front of it), nothing is trimmed:
    # closed, within 1 % of the radius at the 99th percentile and 8 % at worst (measured 0.85 % and 5.5 %), every
    # normal outward
    toward = cams[None] - pts[:, None]
    seen = np.einsum("ncj,nj->nc", toward, p) > 0
    dirs = (toward / np.linalg.norm(toward, axis=2, keepdims=True) * seen[..., None]).sum(1)
    v, f, _ = coarse_mesh_from_points(pts, cols, cams, view_dirs=dirs)
    r = np.linalg.norm(v, axis=1)
    e = np.abs(r - 1)
    assert np.quantile(e, 0.99) < 0.01 and e.max() < 0.08, (np.quantile(e, 0.99), e.max())
    assert (np.einsum("ij,ij->i", vertex_normals(v, f), v / r[:, None]) > 0).all()
    import trimesh

    assert trimesh.Trimesh(v, f, process=False).is_watertight


def test_the_similarity_of_camera_centres_is_recovered_exactly():
    """Oracle: cameras moved by a known similarity (scale 0.37, a rotation, a shift) and back: the fit returns it to
    1e-9 and the errors are zero; a camera displaced by 5 % of the radius shows as such."""
    from scipy.spatial.transform import Rotation

    from inverse.capture import camera_errors, similarity

    rng = np.random.default_rng(4)
    truth = {f"c{k}": np.array(_look(rng.normal(size=3) * 3, rng.normal(size=3) * 0.1)) for k in range(10)}
    rot = Rotation.from_rotvec([0.3, -1.1, 0.4]).as_matrix()
    s, t = 0.37, np.array([1.0, -2.0, 0.5])
    moved = {}
    for n, m in truth.items():  # world' = s·R·world + t, so the recovered frame is the inverse map of the truth
        q = np.eye(4)
        q[:3, :3] = rot.T @ m[:3, :3]
        q[:3, 3] = rot.T @ (m[:3, 3] - t) / s
        moved[n] = q
    s2, r2, t2 = similarity(np.array([moved[n][:3, 3] for n in truth]), np.array([truth[n][:3, 3] for n in truth]))
    assert abs(s2 - s) < 1e-9 and np.abs(r2 - rot).max() < 1e-9 and np.abs(t2 - t).max() < 1e-9
    e = camera_errors(moved, truth, radius=3.0)
    assert e["centre_error_max"] < 1e-9 and e["rotation_error_max_deg"] < 1e-6
    moved["c0"] = moved["c0"].copy()
    moved["c0"][:3, 3] += rot.T @ np.array([0.15, 0.0, 0.0]) / s  # 0.15 = 5 % of the radius, in the truth's frame
    e = camera_errors(moved, truth, radius=3.0)
    assert 0.02 < e["centre_error_max"] < 0.05  # the fit absorbs part of it in scale and rotation (measured 2.6 %)


def _glb(path: Path, pos: np.ndarray, idx: np.ndarray) -> Path:
    """A minimal glTF binary: one primitive (positions, indices)."""
    import struct

    blobs = [pos.astype(np.float32).tobytes(), idx.astype(np.uint32).tobytes()]
    attrs = {"POSITION": 0}
    acc = [{"bufferView": 0, "componentType": 5126, "count": len(pos), "type": "VEC3",
            "min": pos.min(0).tolist(), "max": pos.max(0).tolist()},
           {"bufferView": 1, "componentType": 5125, "count": idx.size, "type": "SCALAR"}]
    views, off = [], 0
    for b in blobs:
        views.append({"buffer": 0, "byteOffset": off, "byteLength": len(b)})
        off += len(b)
    body = b"".join(blobs)
    gltf = {"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}],
            "meshes": [{"primitives": [{"attributes": attrs, "indices": 1}]}], "buffers": [{"byteLength": len(body)}],
            "bufferViews": views, "accessors": acc}
    j = json.dumps(gltf).encode()
    j += b" " * (-len(j) % 4)
    body += b"\0" * (-len(body) % 4)
    path.write_bytes(struct.pack("<III", 0x46546C67, 2, 28 + len(j) + len(body)) + struct.pack("<II", len(j), 0x4E4F534A)
                     + j + struct.pack("<II", len(body), 0x004E4942) + body)
    return path


def test_a_tools_mesh_comes_with_its_colours(tmp_path):
    """OBJ + MTL texture (a real scan) sampled to vertex colours; a GLB's geometry; another format named."""
    from inverse.capture import load_coarse_mesh

    v, f, c = load_coarse_mesh(ROOT / "scenes" / "assets" / "face" / "cyberheads" / "paul.obj")
    assert len(v) == 1600 and c is not None and c.shape == (1600, 3) and 0 <= c.min() and c.max() <= 1
    assert c.std(0).min() > 0.01  # the texture, not one grey
    pos = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float32)
    idx = np.array([0, 2, 1, 0, 3, 2, 0, 1, 3, 1, 2, 3])
    v, f, c = load_coarse_mesh(_glb(tmp_path / "t.glb", pos, idx))
    assert v.shape == (4, 3) and f.shape == (4, 3) and np.allclose(np.sort(v, 0), np.sort(pos, 0))
    (tmp_path / "t.txt").write_text("x")
    with pytest.raises(Exception, match="t.txt: mesh expected as OBJ, PLY, GLB"):
        load_coarse_mesh(tmp_path / "t.txt")
    (tmp_path / "nan.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv nan 1 1\nf 1 2 3\nf 2 4 3\n")
    with pytest.raises(Exception, match="nan.obj: 1 of 4 vertices are NaN/Inf"):  # foundation's loader refuses it
        load_coarse_mesh(tmp_path / "nan.obj")


def test_a_capture_without_points_or_mesh_is_triangulated_with_its_own_cameras(tmp_path):
    """A transforms.json of 20 renders of a speckled bunny with their true cameras, no points, no mesh: the import
    triangulates SIFT matches with the given cameras (pycolmap) and meshes them. Oracle: the points lie on the true
    surface (median distance < 1 % of its size, measured 0.2 %); their normals, turned by the side each was seen from,
    give a mesh whose back faces the cameras see at under 3 % of the hits and half as often as when turned toward the
    nearest camera (measured 2.2 % against 6.1 %)."""
    import mi_plugins  # noqa: F401
    import mitsuba as mi
    from scipy.spatial import cKDTree

    from foundation.mesh import _read_own_ply, sample_surface, write_ply
    from inverse.capture import Capture, CaptureMeta
    from inverse.morph import suite_mesh
    from photoreal.benchmarks.capture import _orbit, _speckled

    v, f, col = _speckled(suite_mesh("bunny", tmp_path), 0, min_vertices=30_000)
    centre = 0.5 * (v.min(0) + v.max(0))
    bound = float(np.linalg.norm(v - centre, axis=1).max())
    cams = _orbit(20, centre, 1.3 * bound / np.tan(np.radians(20.0)), 192)
    ply = write_ply(tmp_path / "truth.ply", v, f, col)
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "path", "max_depth": 2},
                          "sky": {"type": "constant", "radiance": 0.6},
                          "m": {"type": "ply", "filename": str(ply), "bsdf": {"type": "diffuse", "reflectance": {
                              "type": "mesh_attribute", "name": "vertex_color"}}}})
    photos = {c.name: np.array(mi.render(scene, sensor=mi.load_dict(sensor(c)), spp=8, seed=k))[..., :3]
              for k, c in enumerate(cams)}
    cap = Capture(tmp_path, CaptureMeta(cams, [c.name for c in cams[1:]], [cams[0].name]), photos)
    src = read_source(export_capture(cap, tmp_path / "exp", "transforms"))
    assert src.points is None
    out = load_capture(import_capture(src, tmp_path / "cap", resolution=None, show_progress=False))
    assert out.meta.points > 200 and out.meta.mesh == "mesh.ply"
    pts, _, _ = _read_own_ply(out.path / "points.ply", (out.path / "points.ply").read_bytes())
    size = float(np.linalg.norm(v.max(0) - v.min(0)))
    d = cKDTree(sample_surface(v, f, 200_000, np.random.default_rng(0))[0]).query(pts)[0]
    assert np.median(d) < 0.01 * size, np.median(d) / size
    # the mesh was turned by the side each point was seen from: the cameras see its front, not inside-out pockets
    from foundation.mesh import read_ply

    from inverse.capture import coarse_mesh_from_points

    mv, mf, _ = read_ply(out.path / "mesh.ply")
    back, hits = _backfacing(mv, mf, out.meta.cameras, tmp_path)
    nv, nf, _ = coarse_mesh_from_points(pts, None, np.array([c.centre for c in out.meta.cameras]))
    back_near, hits_near = _backfacing(nv, nf, out.meta.cameras, tmp_path)
    print(f"back faces seen: {back / hits:.4f} of the hits; turned by the nearest camera {back_near / hits_near:.4f}")
    assert hits > 1000 and back / hits < 0.03 and back / hits < 0.5 * back_near / hits_near, (back, hits, back_near)


def _backfacing(v, f, cams, tmp_path) -> tuple[int, int]:
    """(pixels whose first hit is a back face, pixels that hit the mesh) over the cameras' views."""
    import drjit as dr
    import mi_plugins  # noqa: F401
    import mitsuba as mi

    from foundation.mesh import write_ply

    scene = mi.load_dict({"type": "scene", "m": {"type": "ply", "filename": str(write_ply(tmp_path / "bf.ply", v, f))}})
    back = hits = 0
    for c in cams:
        x, y = np.meshgrid((np.arange(c.width) + 0.5) / c.width, (np.arange(c.height) + 0.5) / c.height)
        ray, _ = mi.load_dict(sensor(c)).sample_ray(0.0, 0.5, mi.Point2f(x.ravel(), y.ravel()), mi.Point2f(0.5))
        si = scene.ray_intersect(ray)
        hit, cos = np.array(si.is_valid()), np.array(dr.dot(si.n, ray.d))
        hits, back = hits + int(hit.sum()), back + int((hit & (cos > 0)).sum())
    return back, hits


def test_masks_travel_with_their_photos_and_limit_the_scores(tmp_path):
    """A capture with masks exported as transforms.json (mask_path per frame) and imported back: the same masks, and
    their visual hull as the coarse mesh (no points); scores are then taken inside them (a render that differs from the photo only outside the masks scores as exact)."""
    from foundation import imageio
    from inverse.capture import heldout_scores

    cap = _capture(tmp_path / "mem")
    (tmp_path / "mem" / "masks").mkdir(parents=True)
    yy, xx = np.mgrid[0:30, 0:40]
    for k, c in enumerate(cap.meta.cameras):
        m = ((xx - 20) ** 2 + (yy - 15) ** 2 < (8 + k) ** 2).astype(np.float32)
        imageio.write_png(tmp_path / "mem" / "masks" / f"{c.name}.png", np.repeat(m[..., None], 3, -1), linear=False)
    cap.meta.masks = True
    src = read_source(export_capture(cap, tmp_path / "exp", "transforms"))
    assert all(fr.mask is not None for fr in src.frames)
    back = load_capture(import_capture(src, tmp_path / "cap", resolution=None, show_progress=False,
                                       triangulate=False))
    assert back.meta.masks and back.meta.mesh == "mesh.ply"  # no points, masks: the coarse mesh is their hull
    for c in cap.meta.cameras:
        assert np.array_equal(back.mask(c.name), cap.mask(c.name))
    # unlit render of a big quad far behind: black everywhere; the photo made black inside the mask only
    name = back.meta.test[0]
    back.photos[name] = back.photo(name) * ~back.mask(name)[..., None]
    quad_v = np.array([[-50, -50, -40], [50, -50, -40], [50, 50, -40], [-50, 50, -40]], float)
    quad_f = np.array([[0, 1, 2], [0, 2, 3]])
    r = heldout_scores(back, quad_v, quad_f, colours=np.zeros((4, 3), np.float32), spp=1)
    assert r["masked"] and r["views"][name]["psnr"] > 60


def test_sfm_resumes_from_its_last_finished_step(tmp_path):
    """Structure from motion on the vendored ruins (10 real photos) at 256 px: the photos registered below a pixel;
    a second call with the same photos and settings reuses the prepared photos, features and matches and maps
    again; other settings start over."""
    from inverse.capture import SfmSettings, run_sfm

    photos = ROOT / "scenes" / "assets" / "captures" / "ruins" / "images"
    said = []
    s = SfmSettings(max_size=256)
    src = run_sfm(photos, tmp_path / "w", s, progress=said.append)
    fig = src.notes["sfm"]
    # all 10 in every run here; SIFT and matching run multi-threaded, so a photo may come and go between runs
    assert fig["photos"] == 10 and fig["registered"] >= 8 and fig["reprojection_px"] < 1.0 and fig["points"] > 300
    assert fig["cameras"] == "per photo"  # one photo is stored rotated: two sizes, a camera each
    # a phone's lens: the radial term lowers the reprojection errors far beyond what one parameter does by chance
    assert fig["distortion"]["kept"] and fig["distortion"]["fit_gain"] > 3 * fig["distortion"]["penalty"]
    said.clear()
    again = run_sfm(photos, tmp_path / "w", s, progress=said.append)
    assert said == ["10 photos prepared before: reusing them", "incremental mapping",  # no features, no matching
                    "lens distortion: kept only where the points need it"]
    assert again.notes["sfm"]["registered"] >= 8
    said.clear()
    run_sfm(photos, tmp_path / "w", SfmSettings(max_size=256, max_features=2048), progress=said.append)
    assert "SIFT features" in said


def test_the_visual_hull_of_masks_contains_the_object_and_hugs_it():
    """Oracle: exact silhouettes of a unit sphere from 16 cameras on two rings: the hull contains the sphere (every
    vertex at radius ≥ 1 − one voxel) and stays close to it (median radius < 1.1: a hull of 16 views bulges between
    their cones), and faces outward."""
    from foundation.mesh import vertex_normals
    from inverse.capture import visual_hull

    cams = [CaptureCamera(f"c{k}", 64, 48, 60.0, 32.0, 24.0,
                          _look([4 * np.cos(a) * np.cos(e), 4 * np.sin(e), 4 * np.sin(a) * np.cos(e)], [0, 0, 0]))
            for k, (a, e) in enumerate([(2 * np.pi * i / 8, el) for el in (0.3, -0.4) for i in range(8)])]
    masks = {}
    yy, xx = np.mgrid[0:48, 0:64] + 0.5
    for c in cams:
        d = np.stack([(xx - c.cx) / c.f, (yy - c.cy) / c.f, np.ones_like(xx)], -1) @ c.matrix[:3, :3].T
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        o = c.centre
        closest = np.linalg.norm(o - (d @ o)[..., None] * d, axis=-1)  # distance of the ray to the sphere's centre
        masks[c.name] = closest < 1.0
    v, f = visual_hull(cams, masks, res=64, bounds=(np.full(3, -1.5), np.full(3, 1.5)))
    r = np.linalg.norm(v, axis=1)
    voxel = 3.0 / 63
    assert r.min() > 1 - 1.5 * voxel and np.median(r) < 1.1, (r.min(), np.median(r))
    assert (np.einsum("ij,ij->i", vertex_normals(v, f), v / r[:, None]) > 0).mean() > 0.95


def _orbit_reconstruction(k1: float, noise_px: float, seed: int):
    """A pycolmap reconstruction of 300 points seen by 16 cameras on an orbit (two rings, 400 px, f 450) through a
    SIMPLE_RADIAL lens with radial term ``k1``, observations with Gaussian noise of ``noise_px``: the exact poses,
    points and lens as the start."""
    import pycolmap

    rng = np.random.default_rng(seed)
    cam = pycolmap.Camera(model="SIMPLE_RADIAL", width=400, height=400, params=[450.0, 200.0, 200.0, k1], camera_id=1)
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(cam)
    pts = rng.uniform(-1, 1, (300, 3))
    tracks = [pycolmap.Track() for _ in pts]
    for i in range(16):
        az, el = 2 * np.pi * i / 16, np.radians(15.0 if i % 2 else 35.0)
        eye = 4.0 * np.array([np.cos(el) * np.cos(az), np.sin(el), np.cos(el) * np.sin(az)])
        rot = np.asarray(_look(eye, [0.0, 0.0, 0.0]))[:3, :3].T  # world to camera
        uv = np.asarray(cam.img_from_cam(pts @ rot.T - rot @ eye)) + rng.normal(0, noise_px, (len(pts), 2))
        im = pycolmap.Image(name=f"v{i:02d}.png", points2D=[pycolmap.Point2D(p) for p in uv], camera_id=1,
                            image_id=i + 1)
        rec.add_image_with_trivial_frame(im, pycolmap.Rigid3d(pycolmap.Rotation3d(rot), -rot @ eye))
        for j in range(len(pts)):
            tracks[j].add_element(i + 1, j)
    for p, t in zip(pts, tracks):
        rec.add_point3D(p, t)
    return rec


def test_the_lens_distortion_is_kept_only_where_the_points_need_it():
    """The Bayesian information criterion of ``choose_distortion`` on synthetic orbits with 0.3 px noise: a pinhole's
    fitted radial term is noise and goes (three seeds; by chance it would stay in 0.25 % of them), the focal length of
    the refit within 0.1 % of the truth; a real radial term of −0.05 or +0.02 (0.3 % of magnification at the frame's
    edge) stays, recovered within 0.005; ``force_off`` drops it whatever the criterion says."""
    from foundation.errors import UsageError
    from inverse.capture import SfmSettings
    from inverse.capture.sfm import choose_distortion

    with pytest.raises(UsageError, match="distortion must be one of auto, on, off"):
        SfmSettings(distortion="maybe")
    for seed in range(3):
        rec, fig = choose_distortion(_orbit_reconstruction(0.0, 0.3, seed))
        assert not fig["kept"] and fig["fit_gain"] < fig["penalty"], fig
        assert rec.cameras[1].params[3] == 0.0 and abs(rec.cameras[1].params[0] / 450.0 - 1) < 1e-3
    for k1 in (-0.05, 0.02):
        rec, fig = choose_distortion(_orbit_reconstruction(k1, 0.3, 0))
        assert fig["kept"] and fig["fit_gain"] > 3 * fig["penalty"], fig
        assert abs(rec.cameras[1].params[3] - k1) < 0.005
        rec, fig = choose_distortion(_orbit_reconstruction(k1, 0.3, 0), force_off=True)
        assert not fig["kept"] and rec.cameras[1].params[3] == 0.0
        assert fig["reprojection_rms_px_without"] > fig["reprojection_rms_px_with"]
