"""`photoreal bench capture`: the vendored real captures (scenes/assets/captures: a skull, stone ruins) through
structure from motion on the CPU, and the held-out-photo scores of the coarse mesh it gives.

Per capture: photos registered / total, the number of models, points, mean reprojection error and the seconds of each
step (``capture sfm``), then PSNR, SSIM, ꟻLIP and the MobileNetV2 distance of the unlit render of the Poisson mesh,
coloured from the training photos, at every held-out photo (``capture score``): the first baseline a morph of a
real capture has to beat. Targets (issue "Real captures in"): ≥ 90 % of the skull's photos registered, mean
reprojection error ≤ 1 px.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from foundation import validate
from foundation.assets import ROOT

CAPTURES = ROOT / "scenes" / "assets" / "captures"


@dataclass
class CaptureBenchSettings:
    captures: tuple[str, ...] = ("skull", "ruins")  #: folders of scenes/assets/captures
    resolution: int = 512  #: longest side of the working photos
    max_size: int = 1024  #: longest side the SIFT features are found at (the vendored photos are smaller)
    spp: int = 16  #: samples per pixel of the held-out renders
    min_registered: float = 0.9  #: target: fraction of the photos registered
    max_reprojection_px: float = 1.0  #: target: mean reprojection error
    seed: int = 0

    def __post_init__(self):
        self.captures = tuple(self.captures)
        for c in self.captures:
            if not (CAPTURES / c / "images").is_dir():
                from foundation.errors import UsageError

                raise UsageError(f"captures: {c!r} is not a folder of {CAPTURES} with images/")
        validate.integer("resolution", self.resolution, 16, 8192)
        validate.integer("spp", self.spp, 1, 4096)
        validate.in_range("min_registered", self.min_registered, 0.0, 1.0)
        validate.positive("max_reprojection_px", self.max_reprojection_px)
        validate.seed("seed", self.seed)


def _one(name: str, s: CaptureBenchSettings, work: Path, show_progress: bool) -> dict:
    from foundation.mesh import read_ply
    from inverse.capture import SfmSettings, heldout_scores, import_capture, load_capture, run_sfm

    out = work / name / "capture"
    if not (out / "capture.json").is_file():  # a finished capture is reused: a rerun scores again only
        src = run_sfm(CAPTURES / name / "images", work / name / "sfm",
                      SfmSettings(max_size=s.max_size, seed=s.seed),
                      progress=(lambda m: print(f"{name}: {m}", flush=True)) if show_progress else None)
        import_capture(src, out, s.resolution, show_progress=show_progress)
    cap = load_capture(out)
    sfm = dict(cap.meta.sfm or {})
    row = {"sfm": sfm, "photos_in_capture": len(cap.meta.cameras), "held_out": cap.meta.test}
    if cap.mesh is None:
        row["scores"] = None
        row["scores_skipped"] = "no mesh: too few triangulated points"
    else:
        v, f, _ = read_ply(cap.mesh)
        r = heldout_scores(cap, v, f, spp=s.spp, seed=s.seed)
        r.pop("renders")
        row["mesh"] = {"vertices": int(len(v)), "faces": int(len(f))}
        row["scores"] = r
    reg = sfm.get("registered", 0) / max(1, sfm.get("photos", 1))
    row["registered_fraction"] = reg
    row["targets"] = {f"registered_at_least_{s.min_registered}": reg >= s.min_registered,
                      f"reprojection_at_most_{s.max_reprojection_px}_px":
                          sfm.get("reprojection_px", float("inf")) <= s.max_reprojection_px}
    return row


def run(s: CaptureBenchSettings, work: Path, pool, show_progress: bool) -> dict:
    return {"captures": {name: _one(name, s, Path(work), show_progress) for name in s.captures},
            "settings": {"resolution": s.resolution, "max_size": s.max_size, "spp": s.spp}}


def summary(result: dict) -> dict:
    out = {}
    for name, r in result["captures"].items():
        sfm = r["sfm"]
        out[name] = {"registered": f"{sfm.get('registered')}/{sfm.get('photos')}", "models": sfm.get("models"),
                     "points": sfm.get("points"), "reprojection_px": sfm.get("reprojection_px"),
                     "seconds": sfm.get("seconds"),
                     "heldout_mean": (r["scores"] or {}).get("mean"), "targets": r["targets"]}
    return out


SETTINGS = CaptureBenchSettings
