"""Cameras of a morph benchmark: a drone-like orbit, the distance that frames an object, Mitsuba sensors."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import mi_plugins  # noqa: F401
import mitsuba as mi


@dataclass(frozen=True)
class Camera:
    """A look-at camera (y up)."""

    eye: tuple[float, float, float]
    target: tuple[float, float, float]


def drone_orbit(n: int, centre: np.ndarray, radius: float, elevation: tuple[float, float], seed: int,
                jitter: float = 0.02) -> list[Camera]:
    """``n`` cameras on a jittered orbit, altitude varying between the elevation bounds (three periods per turn,
    so that neighbouring views differ in height and every quarter of the orbit spans the whole range); the
    look-at target is jittered by ``jitter`` × radius."""
    rng = np.random.default_rng(seed + 5)
    cams = []
    for i in range(n):
        az = 2 * np.pi * i / n + rng.uniform(-0.05, 0.05)
        el = np.radians(elevation[0] + (elevation[1] - elevation[0]) * (0.5 + 0.5 * np.sin(3 * az)))
        eye = centre + radius * np.array([np.cos(el) * np.cos(az), np.sin(el), np.cos(el) * np.sin(az)])
        target = centre + rng.normal(scale=jitter * radius, size=3) if jitter else np.asarray(centre, float)
        cams.append(Camera(tuple(map(float, eye)), tuple(map(float, target))))
    return cams


def framing_distance(v: np.ndarray, centre: np.ndarray, fov: float, margin: float) -> float:
    """Camera distance at which the bounding sphere (radius r about ``centre``) fits inside (1 − margin) of the
    image half-width from any direction. The sphere seen from distance d is a cone of half-angle α = asin(r/d),
    whose image reaches tan α on the image plane: tan α ≤ t = (1 − margin)·tan(fov/2) ⇔ d ≥ r·√(1 + t²)/t."""
    r = float(np.linalg.norm(np.asarray(v) - centre, axis=1).max())
    t = (1.0 - margin) * np.tan(np.radians(fov / 2))
    return r * np.sqrt(1.0 + t * t) / t  # d with r/d = sin(atan(t))


def sensor_dict(cam, res: int, fov: float | None, sample_border: bool = False) -> dict:
    """Perspective camera; ``sample_border`` for shape optimisation (geometry entering the frame). ``cam``: a look-at
    :class:`Camera` (square ``res``² film, ``fov`` degrees) or a capture's pinhole camera (its own intrinsics, resampled
    to ``res`` pixels across)."""
    if not isinstance(cam, Camera):
        from inverse.capture import sensor

        return sensor(cam.scaled(res), sample_border=sample_border)
    return {"type": "perspective", "fov": fov,
            "to_world": mi.ScalarTransform4f().look_at(origin=list(cam.eye), target=list(cam.target), up=[0, 1, 0]),
            "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"},
                     "sample_border": sample_border},
            "sampler": {"type": "independent"}}
