"""`photoreal export`: a result as a model other tools open — a morph run, a face avatar or a neural material —
told apart by what the folder or file holds (:func:`result_kind`)."""

from __future__ import annotations

from pathlib import Path

from foundation.errors import UsageError

KINDS = ("morph", "face", "material")


def result_kind(path: str | Path) -> str:
    """'morph' (a run folder: metrics.json + morphed.ply), 'face' (a from-photo folder, a face fit's fit.json or its
    maps folder) or 'material' (a neural material .npz); anything else is named."""
    from inverse.btf import is_neural_material

    p = Path(path)
    if not p.exists():
        raise UsageError(f"{p}: no such file or folder")
    if p.is_dir() and (p / "metrics.json").is_file() and (p / "morphed.ply").is_file():
        return "morph"
    if p.is_dir() and ((p / "photo_face.json").is_file() or (p / "fit.json").is_file()
                       or ((p / "maps.exr").is_file() and (p.parent / "fit.json").is_file())):
        return "face"
    if p.is_file() and p.name.endswith(".json") and p.name != "metrics.json":
        from foundation.files import read_json

        if {"benchmark", "metrics"} <= set(read_json(p, "face fit")):
            return "face"
    if is_neural_material(p):
        return "material"
    raise UsageError(f"{p}: not a result photoreal exports (a morph run folder with metrics.json and morphed.ply, a "
                     "`face from-photo` folder, a `face fit` fit.json or its maps folder, or a neural material .npz)")


def export_result(path: str | Path, out: str | Path, s=None, input_path: str | Path | None = None,
                  basis: str | Path | None = None, show_progress: bool = True):
    """Export ``path`` into the folder ``out`` (its record: ``out/export.json``)."""
    kind = result_kind(path)
    if input_path is not None and kind == "material":
        raise UsageError("--input names a morph run's capture or a face fit's benchmark; a material needs none")
    if basis is not None and kind != "material":
        raise UsageError(f"--basis is for neural materials; {path} is a {kind} result")
    if kind == "morph":
        from inverse.morph import export_morph

        return export_morph(path, out, s, input_path=input_path)
    if kind == "face":
        from inverse.face import export_face

        return export_face(path, out, s, input_path=input_path)
    from inverse.btf import export_material

    return export_material(path, out, s, basis=basis, show_progress=show_progress)
