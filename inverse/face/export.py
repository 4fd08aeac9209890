"""A face avatar as a model other tools open: the mesh with its own UVs and the fitted maps as a glTF
metallic-roughness material (base colour, tangent-space normal, roughness in G of ``metallicRoughnessTexture``,
specular through ``KHR_materials_specular``), displacement as its own texture beside it.

Two results are read: a ``face from-photo`` folder (``photo_face.json``: the fitted template and ``maps.exr``) and a
``face fit`` (its ``fit.json`` or the ``--maps`` folder, with the benchmark it names: its scan and UV layout)."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from foundation.errors import UsageError
from foundation.export import (ExportMaterial, ExportMesh, ExportSettings, outward, reimport_check, similarity,
                               split_uv_mesh, write_model)
from foundation.mesh import load_obj

from .benchmark import _layers
from .photo import TEMPLATE, PhotoFitSettings

PHOTO_MARKER = "photo_face.json"
#: the MediaPipe template's units: centimetres
TEMPLATE_METRES = 0.01


@dataclass
class FaceExport:
    """``export.json`` of a face avatar."""

    kind: str  #: "face"
    source: str  #: "from-photo" or "fit"
    result: str
    mesh: str
    format: str
    files: list[str]
    maps: list[str]  #: the fitted maps written (the rest: the stated constants)
    constants: dict  #: material values without a map (roughness, specular)
    frame: str
    vertices: int
    exported_vertices: int
    texture_size: list[int]
    turned_winding: bool = False  #: the mesh was wound inside out (normals inward) and is written turned round
    reimport: dict = field(default_factory=dict)
    seconds: float = 0.0


def face_result(path: str | Path, input_path: str | Path | None = None) -> tuple[str, Path, Path, dict]:
    """(source, mesh OBJ, maps.exr, settings) of a face result ``path``; anything else is named."""
    from foundation.files import read_json

    p = Path(path)
    if (p / PHOTO_MARKER).is_file():
        rec = read_json(p / PHOTO_MARKER, "from-photo result")
        s, default = rec.get("settings", {}), PhotoFitSettings()
        return "from-photo", p / "face_fitted.obj", p / "maps.exr", {
            "roughness": s.get("roughness", default.roughness), "specular": s.get("specular", default.specular)}
    fit_json = p if p.is_file() else next((q for q in (p / "fit.json", p.parent / "fit.json") if q.is_file()), None)
    maps = (p / "maps.exr") if p.is_dir() else None
    if fit_json is None and input_path is None:
        raise UsageError(f"{p}: neither a from-photo result ({PHOTO_MARKER}) nor a face fit (fit.json, or a maps "
                         "folder with --input BENCHMARK)")
    bench = Path(input_path) if input_path is not None else Path(read_json(fit_json, "face fit")["benchmark"])
    if maps is None or not maps.is_file():
        maps = next((q / "maps.exr" for q in (fit_json.parent / "maps", fit_json.with_suffix(""))
                     if (q / "maps.exr").is_file()), None) if fit_json is not None else None
    if maps is None:
        raise UsageError(f"{p}: no fitted maps (maps.exr) beside the fit; give the --maps folder of `face fit`")
    return "fit", bench / "mesh.obj", maps, {}


def export_face(result: str | Path, out: str | Path, s: ExportSettings | None = None,
                input_path: str | Path | None = None, stem: str = "model") -> FaceExport:
    """Write the avatar as ``out/stem.{glb,gltf,obj}`` with ``out/export.json``; complete or not at all."""
    from foundation.files import atomic_dir, write_json
    from foundation.records import to_json

    s = s or ExportSettings()
    t0 = time.perf_counter()
    source, mesh_path, maps_path, consts = face_result(result, input_path)
    maps = {k: v for k, v in _layers(maps_path).items() if k}  # named layers only
    if "albedo" not in maps:
        raise UsageError(f"{maps_path}: no 'albedo' map (layers: {', '.join(sorted(maps)) or 'none'})")
    if source == "fit":
        for k in ("normal", "roughness", "specular"):
            if k not in maps:
                raise UsageError(f"{maps_path}: no '{k}' map (a face fit writes albedo, normal, roughness, specular, "
                                 "displacement)")
    if not mesh_path.is_file():
        raise UsageError(f"{mesh_path.parent}: not a face benchmark (no mesh.obj); name the fit's benchmark with "
                         "--input" if source == "fit" else f"{mesh_path}: the avatar's mesh is missing")
    mesh = load_obj(mesh_path)
    faces, uv, vertex_of = split_uv_mesh(mesh.faces, mesh.face_uvs, mesh.uvs)
    v = mesh.vertices[vertex_of]
    lo, hi = v.min(0), v.max(0)
    if source == "from-photo":  # image space (pixels, Y up, Z to the viewer): the template's size, in metres
        tmpl = load_obj(TEMPLATE)
        k = float(np.ptp(tmpl.vertices, axis=0).max() / np.ptp(v, axis=0).max()) * TEMPLATE_METRES
        frame = similarity(np.eye(3), k, (lo + hi) / 2)
        what = ("+Y up, Z towards the photo's camera; scaled to the template's size (a face ~15 cm across: one photo "
                "has no metric scale), metres, origin at the face's bounding-box centre")
    else:
        frame = np.eye(4)
        what = "the scan's own axes and units, read as +Y up and metres (the Cyberware heads are +Y up, in metres)"
    albedo = np.clip(maps["albedo"][..., :3], 0, 1)
    material = ExportMaterial(name="face", base_colour=albedo, metallic_factor=0.0, double_sided=True)  # an open surface
    written = ["albedo"]
    if "normal" in maps:
        material.normal = maps["normal"][..., :3]
        written.append("normal")
    if "roughness" in maps:
        material.roughness = maps["roughness"][..., 0]
        written.append("roughness")
    else:
        material.roughness_factor = float(consts["roughness"])
    if "specular" in maps:
        material.specular = maps["specular"][..., 0]
        written.append("specular")
    else:
        material.specular_factor = float(consts["specular"])
    if "displacement" in maps:
        material.extra_maps["displacement"] = maps["displacement"][..., 0]
        written.append("displacement")
    faces, turned = outward(v, faces)
    # a turned winding flips N and so N × T: w = −1 keeps the map's +y where ggx_uv (two-sided) reads it
    emesh = ExportMesh(v, faces, uv, None, to_gltf=frame, tangent_sign=-1.0 if turned else 1.0)
    with atomic_dir(out, "export.json") as tmp:
        files = write_model(tmp, stem, s.format, emesh, material)
        check = reimport_check(files[0], emesh, material, spp=s.spp)
        rec = FaceExport(kind="face", source=source, result=str(result), mesh=str(mesh_path), format=s.format,
                         files=sorted(p.name for p in files), maps=written,
                         constants={k: consts[k] for k in consts if k not in maps}, frame=what,
                         vertices=int(len(mesh.vertices)), exported_vertices=int(len(v)),
                         texture_size=list(albedo.shape[1::-1]), turned_winding=turned, reimport=check, seconds=time.perf_counter() - t0)
        write_json(tmp / "export.json", to_json(rec))
    return rec
