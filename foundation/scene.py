"""Load and render Mitsuba scenes (XML files or dicts) with clear errors, progress and atomic output.

Also the intrinsic layers of seed 000: :func:`split_intrinsics` (I = D / A) and :func:`recompose`
(R = A·I + S), used by the demo, the CLI and the diffusion stages.
"""

from __future__ import annotations

import contextlib
import math
import os
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np

import mi_plugins  # noqa: F401  (variant + plugin registration)
import mitsuba as mi

from mi_plugins.integrators.intrinsic import AOV_GROUPS

from . import imageio
from .errors import UsageError
from .files import check_output_file
from .progress import progress_bar
from .threads import exr_safe
from .validate import SEED_MAX

MAX_SIDE = 16384  #: largest film side accepted (a 100000² film would need ~120 GB before the first sample)


class SceneError(UsageError):
    """A scene file could not be parsed or loaded; the message names the file."""


@contextlib.contextmanager
def mitsuba_log_level(level) -> Iterator[None]:
    """Run with Mitsuba's log level set to ``level`` (e.g. ``mi.LogLevel.Error``), restoring it afterwards.

    Remeshed or decimated meshes often have a few non-manifold vertices; Mitsuba (and its projective
    integrators, at the first render) warns about each with a full mesh dump. Where that is expected,
    only errors are worth showing.
    """
    logger = mi.logger() if hasattr(mi, "logger") else mi.Thread.thread().logger()
    old = logger.log_level()
    logger.set_log_level(level)
    try:
        yield
    finally:
        logger.set_log_level(old)


@dataclass
class RenderSettings:
    spp: int | None = None  #: samples per pixel; None = the scene's sampler
    resolution: tuple[int, int] | None = None  #: (width, height); None = the scene's film
    aovs: bool = False  #: swap in the ``intrinsic`` integrator and write A, I, S, ...
    seed: int = 0
    pass_spp: int = 16  #: samples per progress step
    sensor: int = 0  #: which of the scene's sensors (cameras, frames) to render

    def __post_init__(self):
        if self.spp is not None and self.spp < 1:
            raise UsageError(f"spp must be >= 1, got {self.spp}")
        if self.resolution is not None and (len(self.resolution) != 2 or min(self.resolution) < 1
                                            or max(self.resolution) > MAX_SIDE):
            raise UsageError(f"resolution must be two integers in [1, {MAX_SIDE}], got {self.resolution}")
        if not 0 <= self.seed <= SEED_MAX:
            raise UsageError(f"seed must be in [0, {SEED_MAX}], got {self.seed}")
        if self.pass_spp < 1:
            raise UsageError(f"pass_spp must be >= 1, got {self.pass_spp}")
        if self.sensor < 0:
            raise UsageError(f"sensor must be >= 0, got {self.sensor}")


def _set_child(parent: ET.Element, tag: str, name: str, value: str) -> None:
    for child in parent:
        if child.tag == tag and child.get("name") == name:
            child.set("value", value)
            return
    ET.SubElement(parent, tag, {"name": name, "value": value})


def prepare_scene_xml(path: Path, settings: RenderSettings) -> str:
    """Parse a scene file and apply the overrides; errors name the file and line."""
    if not path.is_file():
        raise SceneError(f"{path}: scene file not found")
    try:
        tree = ET.parse(path)
    except ET.ParseError as exc:
        line, col = exc.position
        raise SceneError(f"{path}:{line}:{col}: malformed XML ({exc.msg if hasattr(exc, 'msg') else exc})") from exc
    root = tree.getroot()
    if root.tag != "scene":
        raise SceneError(f"{path}: root element is <{root.tag}>, expected <scene>")
    sensors = root.findall("sensor")
    if settings.resolution is not None:
        if not sensors:
            raise SceneError(f"{path}: --resolution given but the scene has no <sensor>")
        for sensor in sensors:
            film = sensor.find("film")
            if film is None:
                film = ET.SubElement(sensor, "film", {"type": "hdrfilm"})
            _set_child(film, "integer", "width", str(settings.resolution[0]))
            _set_child(film, "integer", "height", str(settings.resolution[1]))
    if settings.aovs:
        old = root.find("integrator")
        depth = None
        if old is not None:
            for child in old:
                if child.get("name") == "max_depth":
                    depth = child.get("value")
            root.remove(old)
        integ = ET.Element("integrator", {"type": "intrinsic"})
        if depth is not None:
            ET.SubElement(integ, "integer", {"name": "max_depth", "value": depth})
        root.insert(0, integ)
    return ET.tostring(root, encoding="unicode")


_EXR_CACHE: dict[tuple[str, float, int], "mi.Bitmap"] = {}


def _exr_as_pfm(exr: Path, folder: Path) -> str:
    """Write a lossless float32 PFM copy of an EXR (read by Mitsuba itself) into ``folder``; the decoded EXR
    is cached for this process.

    Mitsuba's EXR reader hangs with one Dr.Jit thread (:mod:`foundation.assets`), and loading a scene with more
    threads is not reproducible: under load, 2 of ~100 loads of the armadillo scene rendered differently
    (the parser instantiates objects in parallel). PFM goes through no thread pool, so scenes load with the
    caller's thread count; the radiance is bit-identical (tested). The copy lives only while the scene loads
    (:func:`load_scene`): a process-long temporary folder leaked 6 MB per worker process, since pool workers
    end without running ``atexit``.
    """
    st = exr.stat()
    key = (str(exr.resolve()), st.st_mtime, st.st_size)
    if key not in _EXR_CACHE:
        with exr_safe():
            _EXR_CACHE[key] = mi.Bitmap(str(exr))
    target = folder / f"{len(list(folder.iterdir()))}_{exr.stem}.pfm"
    _EXR_CACHE[key].write(str(target))
    return str(target)


def _substitute_exr(root: ET.Element, folder: Path, tmp: Path) -> None:
    """Point every ``filename`` ending in .exr at a PFM copy in ``tmp`` (see :func:`_exr_as_pfm`)."""
    for el in root.iter("string"):
        value = el.get("value", "")
        if el.get("name") == "filename" and value.lower().endswith(".exr"):
            exr = Path(value) if Path(value).is_absolute() else folder / value
            if exr.is_file():
                el.set("value", _exr_as_pfm(exr, tmp))


def load_scene(path: str | os.PathLike, settings: RenderSettings | None = None) -> mi.Scene:
    """Load an XML scene (relative asset paths resolve against its folder)."""
    path = Path(path)
    settings = settings or RenderSettings()
    root = ET.fromstring(prepare_scene_xml(path, settings))
    import tempfile

    with tempfile.TemporaryDirectory(prefix="photoreal-pfm-") as tmp:
        try:
            _substitute_exr(root, path.parent.resolve(), Path(tmp))
        except Exception as exc:  # a damaged EXR: name it
            raise SceneError(f"{path}: {' '.join(str(exc).split())[:200]}") from None
        xml = ET.tostring(root, encoding="unicode")
        resolver = mi.file_resolver()
        saved = [resolver[i] for i in range(len(resolver))]
        resolver.prepend(str(path.parent.resolve()))
        try:
            scene = mi.load_string(xml)
        except Exception as exc:
            msg = str(exc).strip()
            # Python plugin constructors report through a traceback; keep its last line.
            last = msg.splitlines()[-1] if msg else type(exc).__name__
            detail = last if "Traceback" in msg else msg
            raise SceneError(f"{path}: {detail}") from exc
        finally:
            resolver.clear()
            for p in saved:
                resolver.append(p)
    if not scene.sensors():
        raise SceneError(f"{path}: the scene has no <sensor> (a camera to render from)")
    if scene.integrator() is None:
        raise SceneError(f"{path}: the scene has no <integrator>")
    return scene


def _channel_split(img: np.ndarray, aov_names: list[str]) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Main RGB and {aov group: (H, W, C)} from a developed film tensor."""
    n_aov = len(aov_names)
    base = img.shape[-1] - n_aov
    rgb = img[..., :3]
    groups: dict[str, list[np.ndarray]] = {}
    for i, name in enumerate(aov_names):
        groups.setdefault(name.split(".")[0], []).append(img[..., base + i])
    return rgb, {k: np.stack(v, axis=-1) for k, v in groups.items()}


def split_intrinsics(aovs: dict[str, np.ndarray], eps: float = 1e-6) -> dict[str, np.ndarray]:
    """Add irradiance I = D / A (seed 000 eq. 3) so that A·I + S reproduces the render."""
    out = dict(aovs)
    a, d = aovs["albedo"], aovs["diffuse"]
    out["irradiance"] = np.where(a > eps, d / np.maximum(a, eps), 0.0).astype(np.float32)
    return out


def recompose(layers: dict[str, np.ndarray]) -> np.ndarray:
    """R = A·I + S (seed 000, eq. 4), in linear space."""
    return layers["albedo"] * layers["irradiance"] + layers["specular"]


def render_scene(scene: mi.Scene, settings: RenderSettings, show_progress: bool = True, label: str = "render"):
    """Render in passes of ``pass_spp`` (for progress), averaging them.

    Returns (rgb (H, W, 3), {aov group: (H, W, C)}) as float32 numpy arrays.
    """
    sensors = scene.sensors()
    if settings.sensor >= len(sensors):
        raise SceneError(f"{label}: sensor {settings.sensor} asked for, the scene has {len(sensors)}")
    sensor = sensors[settings.sensor]
    spp = settings.spp or sensor.sampler().sample_count()
    n_pass = max(1, math.ceil(spp / settings.pass_spp))
    per = [spp // n_pass + (1 if i < spp % n_pass else 0) for i in range(n_pass)]
    acc = None
    integrator = scene.integrator()
    aov_names = list(integrator.aov_names()) if hasattr(integrator, "aov_names") else []
    from mi_plugins.bsdfs.neural_btf import evaluated_mode, uses_neural_btf

    # neural_btf's MLPs run ~15× faster outside Mitsuba's symbolic megakernel (bench btf).
    with progress_bar(total=spp, desc=label, unit="spp", disable=not show_progress) as bar, \
            evaluated_mode(uses_neural_btf(scene)):
        for i, k in enumerate(per):
            # The sampler seed is 32-bit: wrap (seeds < 42950 give the same passes as before the wrap).
            seed = (settings.seed * 100_003 + i) % 2**32
            try:
                img = np.array(mi.render(scene, sensor=settings.sensor, spp=k, seed=seed), dtype=np.float64)
            except RuntimeError as exc:  # Ctrl-C inside a Python plugin arrives wrapped by Dr.Jit
                if "KeyboardInterrupt" in str(exc):
                    raise KeyboardInterrupt from None
                raise
            acc = img * k if acc is None else acc + img * k
            bar.update(k)
    img = (acc / spp).astype(np.float32)
    rgb, aovs = _channel_split(img, aov_names)
    if not np.isfinite(rgb).all():
        raise FloatingPointError(f"{label}: render contains NaN/Inf ({int((~np.isfinite(rgb)).sum())} values)")
    if "albedo" in aovs and "diffuse" in aovs:
        aovs = split_intrinsics(aovs)
    return rgb, aovs


def render_file(
    scene_path: str | os.PathLike, out: str | os.PathLike, settings: RenderSettings, show_progress: bool = True
) -> dict:
    """Render a scene file to ``out`` (EXR with AOV layers) plus ``out`` with .png; returns a summary."""
    out = Path(out)
    if out.suffix.lower() != ".exr":
        raise UsageError(f"{out}: output must be an .exr file")
    check_output_file(out, "output")
    check_output_file(out.with_suffix(".png"), "preview")
    scene = load_scene(scene_path, settings)
    rgb, aovs = render_scene(scene, settings, show_progress, label=Path(scene_path).name)
    layers = {"": rgb, **{k: v for k, v in aovs.items()}}
    png = out.with_suffix(".png")
    imageio.write_png(png, rgb)
    imageio.write_exr(out, layers)  # last: the EXR's presence marks a finished render (batches resume on it)
    return {"exr": str(out), "png": str(png), "shape": list(rgb.shape), "layers": sorted(aovs),
            "sensor": settings.sensor}


def sensor_count(scene_path: str | os.PathLike) -> int:
    """How many sensors (cameras, frames) a scene file has (parsed, not loaded)."""
    root = ET.fromstring(prepare_scene_xml(Path(scene_path), RenderSettings()))
    return len(root.findall("sensor"))


def render_item(scene_path: str, out: str, settings: RenderSettings) -> dict:
    """One scene, or one of its sensors, to ``out`` (EXR + PNG): the unit a batch of renders fans out."""
    return render_file(scene_path, out, settings, show_progress=False)


__all__ = [
    "AOV_GROUPS",
    "RenderSettings",
    "SceneError",
    "load_scene",
    "recompose",
    "render_file",
    "render_item",
    "render_scene",
    "sensor_count",
    "split_intrinsics",
]
