"""BTF data (seed 002 §4.1): SVBRDF generators, Mitsuba BTF rendering oracles, files and resume."""

import functools
import json
import math

import numpy as np
import pytest

import mitsuba as mi

import inverse.btf.data as btf
import inverse.btf.svbrdf as svbrdf
from conftest import local_si
from inverse.btf.data import (BTFData, BTFDataError, BTFRenderSettings, load_btf, load_dataset, render_btf,
                              render_dataset, save_btf)
from inverse.btf.svbrdf import FAMILIES, constant_svbrdf, make_periodic, make_svbrdf

# Tiny settings: 8² texels, 4 slices, flat plane of 4² quads, directional light (exact oracles).
TINY = BTFRenderSettings(tex_res=8, slices=4, spp=2, max_depth=1, mesh_res=4, sun_diameter_deg=0.0)
# float16 storage rounds to 2^-11 ≈ 4.9e-4 relative; float32 frame transforms add ~1e-6.
RTOL16 = 1e-3


def _ggx_eval(wi: np.ndarray, wo: np.ndarray, albedo, roughness, metallic, specular=0.5, normal=(0, 0, 1)):
    """Closed form from a separate constant ggx_uv: eval(si(wi=view), wo=light) in the identity frame."""
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    b = mi.load_dict({"type": "ggx_uv", "albedo": {"type": "rgb", "value": list(albedo)}, "roughness": roughness,
                      "metallic": metallic, "specular": specular,
                      "normal": {"type": "rgb", "value": (n * 0.5 + 0.5).tolist()}})
    si = local_si(mi.Vector3f(wo.reshape(-1, 3).T))
    return np.array(b.eval(mi.BSDFContext(), si, mi.Vector3f(wi.reshape(-1, 3).T))).T.reshape(wi.shape)


def _f32(d: BTFData) -> np.ndarray:
    return d.values.astype(np.float32)


# -- flat oracles ---------------------------------------------------------------------------------

TILTED = (0.35, -0.25, 0.9)


@pytest.mark.parametrize("max_depth", [1, 3])
@pytest.mark.parametrize("normal", [(0, 0, 1), TILTED])
def test_flat_constant_material_equals_ggx_uv_eval(max_depth, normal):
    # Flat plane, constant maps: every camera ray hits z = 0 with the same material, the sun is a
    # directional light, and BSDF-sampled continuations leave a plane upwards and miss (max_depth 3
    # adds exactly 0). So value == eval(wi=ω_o, wo=ω_i) up to float16 rounding. The tilted normal
    # map also checks the tangent frame (x = +u, y = +v): a flipped axis would change the values.
    albedo, rough, metal = (0.7, 0.5, 0.3), 0.3, 0.2
    sv = constant_svbrdf(16, albedo=albedo, roughness=rough, metallic=metal, normal=normal)
    d = render_btf(sv, BTFRenderSettings(**{**TINY.__dict__, "max_depth": max_depth}), progress=False)
    ref = _ggx_eval(d.wi, d.wo, albedo, rough, metal, normal=normal)
    assert ref.max() > 0.1  # the directions do reach the glossy lobe and the diffuse part
    np.testing.assert_allclose(_f32(d), ref, rtol=RTOL16, atol=1e-6)


def test_flat_lambertian_is_albedo_over_pi_cos():
    albedo = np.array([0.8, 0.5, 0.2])
    sv = constant_svbrdf(16, albedo=albedo, roughness=0.5, metallic=0.0, specular=0.0)
    d = render_btf(sv, TINY, progress=False)
    ref = albedo / np.pi * d.wi[..., 2:3]
    np.testing.assert_allclose(_f32(d), ref, rtol=RTOL16, atol=1e-7)


def test_sun_disk_keeps_unit_irradiance():
    # A 10° sun: each path sees a different light direction; for a flat Lambertian plane the
    # mean over the disk of cos θ_l is cos θ_i·E[cos α], which the 1/E[cos α] normalisation
    # cancels, so the mean value is albedo/π·cos θ_i. Per-path spread is ≤ sin 5°·tan 80° ≈ 0.5
    # relative; averaged over 8²·4·8 = 2048 paths per slice-direction set, 1% is ~4σ.
    sv = constant_svbrdf(16, albedo=(0.6, 0.6, 0.6), specular=0.0)
    s = BTFRenderSettings(**{**TINY.__dict__, "spp": 8, "sun_diameter_deg": 10.0, "max_theta_deg": 70.0})
    d = render_btf(sv, s, progress=False)
    ratio = _f32(d)[..., 0].mean() / (0.6 / np.pi * d.wi[..., 2]).mean()
    assert abs(ratio - 1.0) < 0.01, ratio


# -- geometry: self-shadowing and orientation -------------------------------------------------


def _ridge(axis: str, res: int = 64, h: float = 0.1) -> np.ndarray:
    """Height 0 except a wall of height h over 7/16 ≤ (v or u) < 9/16."""
    band = np.zeros(res, np.float32)
    band[28:36] = h
    return np.repeat(band[:, None], res, 1) if axis == "y" else np.repeat(band[None, :], res, 0)


@pytest.mark.parametrize("axis", ["y", "x"])
@pytest.mark.parametrize("max_depth", [1, 3])
def test_ridge_casts_a_shadow_on_the_side_away_from_the_light(axis, max_depth):
    # Wall across v ∈ [7/16, 9/16), height 0.1 (mesh vertices: top 0.453..0.547, feet at the band
    # edges). Light from +v at θ = 70° (tan = 2.75): the shadow on the ground spans
    # v ∈ [0.453 − 0.275, 0.453] = [0.178, 0.453] → texel rows 3..6 of 16. Rows 10..15 and 0..1 see
    # the light. Viewed from straight above. If the geometry's v ran the other way the shadow would
    # be on rows 9..13 instead; axis "x" checks u the same way.
    t = math.radians(70)
    light = (0.0, math.sin(t), math.cos(t)) if axis == "y" else (math.sin(t), 0.0, math.cos(t))
    sv = constant_svbrdf(albedo=(0.5, 0.5, 0.5), specular=0.0, height=_ridge(axis))
    s = BTFRenderSettings(tex_res=16, slices=1, spp=4, max_depth=max_depth, mesh_res=64, sun_diameter_deg=0.0)
    d = render_btf(sv, s, progress=False, directions=(light, (0.0, 0.0, 1.0)))
    v = _f32(d)[0, ..., 0]
    prof = v.mean(1) if axis == "y" else v.mean(0)  # along the light's axis
    lit_ref = 0.5 / np.pi * math.cos(t)
    shadow, lit = prof[3:7], np.concatenate([prof[10:16], prof[0:2]])
    if max_depth == 1:
        np.testing.assert_allclose(lit, lit_ref, rtol=RTOL16)  # flat lit ground: exactly Lambert
        assert np.all(shadow == 0.0), shadow  # direct light only: a blocked shadow ray gives exactly 0
    else:
        # Interreflection: the wall's lit face brightens the ground in front of it (row 9 is its
        # foot), fading with distance; the shadow only gets light bounced at grazing angles.
        assert np.all(lit >= lit_ref * (1 - RTOL16)) and prof[10] > 1.05 * prof[14], prof
        assert shadow.max() < 0.05 * lit_ref, shadow


def test_albedo_texture_lines_up_with_texels():
    # Bright where v ∈ [1/4, 1/2) or u ∈ [1/2, 3/4); flat plane, light and view from above. Texels
    # not adjacent to a region edge see one albedo only (the bilinear filter blurs half a map texel).
    res = 64
    a = np.full((res, res, 3), 0.1, np.float32)
    a[16:32] = 0.8
    a[:, 32:48] = 0.8
    sv = constant_svbrdf(res, specular=0.0)
    sv.base_color = a
    s = BTFRenderSettings(tex_res=16, slices=1, spp=4, mesh_res=8, sun_diameter_deg=0.0)
    d = render_btf(sv, s, progress=False, directions=((0, 0, 1), (0.1, 0.2, 1.0)))
    v = _f32(d)[0, ..., 1] * np.pi  # = albedo (cos θ_i = 1)
    np.testing.assert_allclose(v[5:7, :7], 0.8, rtol=RTOL16)  # bright rows (v), away from the column
    np.testing.assert_allclose(v[9:15, 9:11], 0.8, rtol=RTOL16)  # bright columns (u), away from the rows
    np.testing.assert_allclose(v[9:15, 0:7], 0.1, rtol=RTOL16)
    np.testing.assert_allclose(v[0:3, 13:15], 0.1, rtol=RTOL16)


# -- tileability and determinism --------------------------------------------------------------


def _seam_ratio(v: np.ndarray, axis: int) -> float:
    """Mean |Δ| across the wrap / mean |Δ| between interior neighbours, along an axis of (H, W)."""
    inner = np.abs(np.diff(v, axis=axis)).mean()
    wrap = np.abs(np.take(v, 0, axis) - np.take(v, -1, axis)).mean()
    return float(wrap / inner)


def _waves(res: int = 64) -> np.ndarray:
    """Smooth periodic relief, peak-to-peak ≈ 0.16 tile units."""
    c = (np.arange(res) + 0.5) / res
    v, u = np.meshgrid(c, c, indexing="ij")
    h = 0.04 * (np.sin(4 * np.pi * u) + np.cos(6 * np.pi * v) + 0.5 * np.sin(2 * np.pi * (u + 2 * v)))
    return (h - h.min()).astype(np.float32)


# 64 spp: MC noise (mostly at shadow edges) ≈ 2% of the mean value per texel, seams are larger.
TILE_SETTINGS = BTFRenderSettings(tex_res=32, slices=1, spp=64, max_depth=1, mesh_res=64, sun_diameter_deg=0.0)
# Grazing-ish light and view with components along u and v: rays and shadows cross the tile border.
SLANTED = ((0.6, 0.45, 0.66), (-0.55, -0.6, 0.58))


def _tile_check(tiles: int) -> tuple[float, list[float]]:
    """(roll error / mean, seam ratios): the BTF of the relief shifted by half a tile vs the shifted BTF."""
    sv = constant_svbrdf(albedo=(0.5, 0.5, 0.5), roughness=0.4, height=_waves())
    shifted = constant_svbrdf(albedo=(0.5, 0.5, 0.5), roughness=0.4, height=np.roll(_waves(), (32, 32), (0, 1)))
    a = _f32(render_btf(sv, TILE_SETTINGS, progress=False, directions=SLANTED))[0].mean(-1)
    b = _f32(render_btf(shifted, TILE_SETTINGS, progress=False, directions=SLANTED))[0].mean(-1)
    roll_err = np.abs(b - np.roll(a, (16, 16), (0, 1))).mean() / a.mean()
    return float(roll_err), [_seam_ratio(a, 0), _seam_ratio(a, 1)]


def test_btf_tiles_across_the_border(monkeypatch):
    # (1) Shifting the relief by half a tile moves the border texels to the middle: with the 3×3
    # copies they must see the same thing, so the shifted BTF equals the rolled BTF up to MC noise
    # (measured 2.2% mean |Δ| / mean; bound 4%). (2) Neighbours across the wrap differ like interior
    # neighbours (measured ratios 1.07, 0.47; bound 1.5). Negative control: one tile without its
    # copies — rays near the border see nothing beyond it (measured roll error 15%, ratios 2.2, 2.1).
    roll_err, ratios = _tile_check(3)
    assert roll_err < 0.04 and max(ratios) < 1.5, (roll_err, ratios)
    monkeypatch.setattr(btf, "height_mesh", functools.partial(btf.height_mesh, tiles=1))
    roll_err1, ratios1 = _tile_check(1)
    assert roll_err1 > 3 * roll_err and min(ratios1) > 1.5, (roll_err1, ratios1)


def test_render_is_deterministic_and_independent_of_chunking(monkeypatch):
    sv = make_svbrdf("leather", 5, 32)
    s = BTFRenderSettings(tex_res=8, slices=3, spp=2, max_depth=3, mesh_res=16)
    a = render_btf(sv, s, progress=False)
    monkeypatch.setattr(btf, "_CHUNK_LANES", 8 * 8 * 2)  # one slice per kernel launch
    b = render_btf(sv, s, progress=False)
    for k in ("values", "wi", "wo"):
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k))
    c = render_btf(sv, BTFRenderSettings(**{**s.__dict__, "seed": 1}), progress=False)
    assert not np.array_equal(a.wi, c.wi) and not np.array_equal(a.values, c.values)
    assert a.values.dtype == np.float16 and a.wi.dtype == np.float32 and a.values.shape == (3, 8, 8, 3)
    assert a.meta["family"] == "leather" and a.meta["settings"]["seed"] == 0 and a.meta["render_seconds"] > 0


def test_directions_are_uniform_on_the_cap():
    s = BTFRenderSettings(tex_res=16, slices=8, max_theta_deg=60.0)
    wi, wo = zip(*(btf._slice_directions(constant_svbrdf(), s, k) for k in range(8)))
    for d in (np.stack(wi), np.stack(wo)):
        np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-6)
        z = d[..., 2].ravel()
        assert z.min() >= 0.5 - 1e-6  # θ ≤ 60°
        # Uniform in solid angle ⇔ cos θ uniform on [cos 60°, 1]: mean 0.75, 4σ ≈ 4·0.144/√2048 = 0.013.
        assert abs(z.mean() - 0.75) < 0.013
        assert abs(np.arctan2(d[..., 1], d[..., 0]).mean()) < 0.25  # φ uniform: mean 0 (4σ = 4·1.81/√2048)
    assert not np.array_equal(wi[0], wo[0]) and not np.array_equal(wi[0], wi[1])


# -- SVBRDF generators --------------------------------------------------------------------------


def _wrap_is_typical(m: np.ndarray, axis: int) -> bool:
    """The wrap neighbour pair is no outlier among the map's neighbour pairs along an axis.

    Per-line mean |Δ| over the other axis; the wrap pair must stay within 1.25× the largest
    interior pair (a periodic map makes the wrap pair just one more interior pair).
    """
    m = m.reshape(m.shape[0], m.shape[1], -1)
    d = np.abs(np.diff(m, axis=axis)).mean(axis=(1 - axis, 2))
    wrap = np.abs(np.take(m, 0, axis) - np.take(m, -1, axis)).mean()
    return bool(wrap <= 1.25 * d.max() + 1e-7)


@pytest.mark.parametrize("family", FAMILIES)
def test_family_maps_are_finite_in_range_periodic_and_seeded(family):
    sv = make_svbrdf(family, 7, 64)
    assert sv.family == family and sv.res == 64
    assert sv.base_color.shape == (64, 64, 3) and sv.normal.shape == (64, 64, 3) and sv.height.shape == (64, 64)
    for k in ("base_color", "normal", "height", "roughness", "metallic"):
        m = getattr(sv, k)
        assert m.dtype == np.float32 and np.isfinite(m).all(), k
        assert _wrap_is_typical(m, 0) and _wrap_is_typical(m, 1), f"{family}: '{k}' does not tile"
    assert 0.0 <= sv.base_color.min() and sv.base_color.max() <= 1.0
    assert 0.05 <= sv.roughness.min() and sv.roughness.max() <= 1.0
    assert 0.0 <= sv.metallic.min() and sv.metallic.max() <= 1.0
    np.testing.assert_allclose(np.linalg.norm(sv.normal, axis=-1), 1.0, atol=1e-5)
    assert 0.01 <= np.ptp(sv.height) <= 0.12
    again = make_svbrdf(family, 7, 64)
    other = make_svbrdf(family, 8, 64)
    for k in ("base_color", "height", "roughness"):
        np.testing.assert_array_equal(getattr(sv, k), getattr(again, k))
    assert not np.array_equal(sv.height, other.height)


def test_families_have_their_character():
    mean = {f: make_svbrdf(f, 11, 64) for f in FAMILIES}
    assert mean["metal"].metallic.mean() > 0.5
    assert all(mean[f].metallic.max() == 0.0 for f in FAMILIES if f != "metal")
    assert mean["metal"].roughness.mean() < mean["plaster"].roughness.mean()
    assert np.ptp(mean["stone"].height) > np.ptp(mean["fabric"].height)


def test_make_periodic_removes_the_seam_of_a_photo_crop():
    crop = svbrdf._photo_crop("gravel", np.random.default_rng(0), 64)
    assert not (_wrap_is_typical(crop, 0) and _wrap_is_typical(crop, 1))  # the check has power
    tiled = make_periodic(crop)
    assert _wrap_is_typical(tiled, 0) and _wrap_is_typical(tiled, 1)
    assert tiled.std() > 0.7 * crop.std()  # the renormalised blend keeps the photo's contrast


def test_bad_family_and_settings_name_the_problem():
    with pytest.raises(ValueError, match="valid: fabric, metal"):
        make_svbrdf("velvet", 0)
    with pytest.raises(ValueError, match="'spp'"):
        BTFRenderSettings(spp=0)
    with pytest.raises(ValueError, match="'max_theta_deg'"):
        BTFRenderSettings(max_theta_deg=90.0)
    with pytest.raises(ValueError, match="'normal'"):
        constant_svbrdf(normal=(0, 0, -1))


# -- files, dataset, resume ---------------------------------------------------------------------


def _small_btf() -> BTFData:
    rng = np.random.default_rng(0)
    d = rng.normal(size=(2, 3, 4, 3))
    d[..., 2] = np.abs(d[..., 2])
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    return BTFData(rng.random((2, 3, 4, 3)).astype(np.float16), d.astype(np.float32), d[::-1].astype(np.float32),
                   {"name": "x", "family": "stone"})


def test_save_load_round_trip(tmp_path):
    a = _small_btf()
    p = save_btf(tmp_path / "a.npz", a)
    b = load_btf(p)
    for k in ("values", "wi", "wo"):
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k))
    assert b.meta == a.meta and b.values.dtype == np.float16
    assert [q.name for q in tmp_path.iterdir()] == ["a.npz"]  # no temporary left behind


def test_load_errors_name_the_file(tmp_path):
    with pytest.raises(BTFDataError, match="no such BTF file"):
        load_btf(tmp_path / "missing.npz")
    bad = tmp_path / "corrupt.npz"
    bad.write_bytes(b"PK\x03\x04 not really a zip")
    with pytest.raises(BTFDataError, match="corrupt.npz.*not a readable"):
        load_btf(bad)
    a = _small_btf()
    a.values[0, 1, 2, 0] = np.nan
    with pytest.raises(BTFDataError, match=r"nan\.npz: 'values' has 1 NaN/Inf"):
        load_btf(save_btf(tmp_path / "nan.npz", a))
    a = _small_btf()
    a.wi = a.wi[:1]
    with pytest.raises(BTFDataError, match="shape.npz: 'wi' has shape"):
        load_btf(save_btf(tmp_path / "shape.npz", a))
    np.savez(tmp_path / "keys.npz", values=a.values)
    with pytest.raises(BTFDataError, match=r"keys.npz: missing arrays \['wi', 'wo', 'meta'\]"):
        load_btf(tmp_path / "keys.npz")


def test_render_dataset_resumes_and_indexes(tmp_path):
    s = BTFRenderSettings(tex_res=4, slices=2, spp=1, max_depth=2, mesh_res=8)
    kw = dict(families=("wood", "metal"), per_family=2, settings=s, progress=False, svbrdf_res=32)
    paths = render_dataset(tmp_path, **kw)
    assert [p.name for p in paths] == ["wood_000.npz", "wood_001.npz", "metal_000.npz", "metal_001.npz"]
    index = json.loads((tmp_path / "index.json").read_text())
    assert [m["file"] for m in index["materials"]] == [p.name for p in paths]
    assert len({m["seed"] for m in index["materials"]}) == 4 and index["settings"] == s.__dict__
    stamps = {p.name: p.stat().st_mtime_ns for p in paths}
    before = load_btf(paths[1])
    paths[1].unlink()  # "killed" before this one was written
    paths[2].write_bytes(b"half-written")  # or mid-write (cannot happen with atomic writes, but still)
    render_dataset(tmp_path, **kw)
    assert paths[0].stat().st_mtime_ns == stamps[paths[0].name]  # skipped: loads fine
    assert paths[3].stat().st_mtime_ns == stamps[paths[3].name]
    np.testing.assert_array_equal(load_btf(paths[1]).values, before.values)  # re-rendered identically
    data = load_dataset(tmp_path)
    assert [d.meta["name"] for d in data] == ["wood_000", "wood_001", "metal_000", "metal_001"]
    with pytest.raises(ValueError, match="other settings"):
        render_dataset(tmp_path, **{**kw, "settings": BTFRenderSettings(**{**s.__dict__, "spp": 2})})


def test_a_second_material_compiles_no_new_kernel():
    # The trace kernel takes the relief height as an opaque input and aligned directions: before, every
    # material compiled its own copy (~1 s each at full size; 885 kernels in the BTF bench test).
    from conftest import compiled_kernels

    s = BTFRenderSettings(tex_res=8, slices=4, spp=2, max_depth=2, mesh_res=8)
    a, b = make_svbrdf("stone", 0, 32), make_svbrdf("stone", 1, 32)
    assert np.ptp(a.height) != np.ptp(b.height)
    render_btf(a, s, progress=False)
    with compiled_kernels() as k:
        render_btf(b, s, progress=False)
    assert k.count == 0, k.count
