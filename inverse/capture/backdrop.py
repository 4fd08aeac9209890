"""Masks from a uniform backdrop: for captures without masks whose photos show the object against one plain colour
(a studio sweep, a turntable's cloth, a render's constant background).

A photo's backdrop colour is the median of its border; the backdrop is every pixel within a tolerance of that colour
that is connected to the border (4-neighbours), so a patch of the object that happens to share the colour stays
object unless it touches the backdrop. What the object encloses in the backdrop's colour (a gap between two parts,
or a patch of the object) is marked unsure, for a silhouette loss to leave out. A capture counts as having a
backdrop only where most of its photos' borders are that one colour: a scene (sky above, ground below, the ruins)
fails the test and keeps no masks. Colours are compared in sRGB (γ 2.2), where a tolerance means about the same
thing in the shadows as in the highlights.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: a border pixel belongs to the backdrop within this much of the border's median (sRGB, per channel, max)
BACKDROP_TOLERANCE = 0.06
#: a photo shows a backdrop when this share of its border is backdrop-coloured ...
BORDER_SHARE = 0.9
#: ... and a capture has one when this share of its photos do
PHOTO_SHARE = 0.8
#: the border's width, a share of the photo's smaller side (at least 1 px)
BORDER_WIDTH = 0.02


@dataclass
class BackdropDecision:
    """Whether a capture's photos stand on a uniform backdrop, and what each one showed."""

    uniform: bool
    photos: int  #: photos looked at
    uniform_photos: int  #: of them, those whose border is one colour
    border_share: float  #: the median photo's share of backdrop-coloured border pixels
    colour: tuple[float, float, float]  #: the median photo's backdrop colour (sRGB)

    def to_json(self) -> dict:
        return {"uniform": self.uniform, "photos": self.photos, "uniform_photos": self.uniform_photos,
                "border_share": round(self.border_share, 4), "colour": [round(c, 4) for c in self.colour]}


def _srgb(photo: np.ndarray) -> np.ndarray:
    return np.clip(np.asarray(photo, np.float32)[..., :3], 0.0, 1.0) ** (1.0 / 2.2)


def _border(h: int, w: int) -> np.ndarray:
    b = max(1, int(round(BORDER_WIDTH * min(h, w))))
    m = np.zeros((h, w), bool)
    m[:b], m[-b:], m[:, :b], m[:, -b:] = True, True, True, True
    return m


def _valid(photo: np.ndarray) -> np.ndarray:
    """Pixels with data: undistortion leaves exact black where no source pixel maps (the frame's edge)."""
    return np.asarray(photo)[..., :3].max(axis=-1) > 0


def border_colour(photo: np.ndarray) -> tuple[np.ndarray, float]:
    """(the border's median colour in sRGB, the share of border pixels within :data:`BACKDROP_TOLERANCE` of it);
    pixels without data are left out."""
    c = _srgb(photo)
    ring = c[_border(*c.shape[:2]) & _valid(photo)]
    if not len(ring):
        return np.zeros(3, np.float32), 0.0
    colour = np.median(ring, axis=0)
    share = float(np.mean(np.abs(ring - colour).max(axis=1) <= BACKDROP_TOLERANCE))
    return colour, share


def backdrop_mask(photo: np.ndarray, tolerance: float = BACKDROP_TOLERANCE) -> tuple[np.ndarray, np.ndarray]:
    """(object, unsure): (H, W) bool each. The object is the complement of the border-connected pixels of the
    border's colour (and of pixels without data). Unsure: the object's pixels of the backdrop's colour that the object
    encloses, which are either the backdrop seen through a gap (between an arm and a body) or the object's own
    patch of that colour; a silhouette loss leaves them out."""
    from scipy import ndimage

    c = _srgb(photo)
    colour, _ = border_colour(photo)
    valid = _valid(photo)
    close = np.abs(c - colour).max(axis=-1) <= tolerance
    near = close | ~valid  # no data: neither object nor a wall
    labels, _ = ndimage.label(near)
    touching = np.unique(labels[_border(*near.shape) & near])
    obj = ~np.isin(labels, touching[touching > 0]) & valid
    return obj, obj & close


def decide_backdrop(photos) -> BackdropDecision:
    """Whether the photos (an iterable of linear RGB arrays) share a uniform backdrop (:data:`PHOTO_SHARE` of them
    with :data:`BORDER_SHARE` of their border in one colour)."""
    stats = [border_colour(p) for p in photos]
    if not stats:
        return BackdropDecision(False, 0, 0, 0.0, (0.0, 0.0, 0.0))
    shares = np.array([s for _, s in stats])
    k = int(np.argsort(shares)[len(shares) // 2])
    ok = int(np.sum(shares >= BORDER_SHARE))
    return BackdropDecision(ok >= PHOTO_SHARE * len(stats), len(stats), ok, float(shares[k]),
                            tuple(float(x) for x in stats[k][0]))
