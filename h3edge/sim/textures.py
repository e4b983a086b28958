"""Procedural texture images for the simulated room, one pure function per texture kind.

The kinds cover the texture classes H3-Mapping distinguishes: weak texture (flat colour + faint
noise), stripes with a dominant low-frequency direction (planks, blinds, grout lines, book
spines) and unstructured rich texture (CC0 / public-domain photographs that scikit-image ships
inside its wheel, so they load offline). Every function takes an explicit ``numpy`` Generator
and returns uint8 RGB (H, W, 3); same generator state -> same bytes.
"""

from __future__ import annotations

import cv2
import numpy as np


def _smooth_noise(rng: np.random.Generator, h: int, w: int, scale_px: float) -> np.ndarray:
    """Zero-mean, unit-std band-limited noise (H, W) with features of about ``scale_px`` texels."""
    gh, gw = max(2, int(np.ceil(h / scale_px)) + 2), max(2, int(np.ceil(w / scale_px)) + 2)
    coarse = rng.standard_normal((gh, gw)).astype(np.float32)
    n = cv2.resize(coarse, (w, h), interpolation=cv2.INTER_CUBIC)
    return (n - n.mean()) / max(float(n.std()), 1e-6)


def _to_u8(img: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def weak(rng: np.random.Generator, h: int, w: int, color: tuple[int, int, int], amp: float = 2.5) -> np.ndarray:
    """Painted plaster: flat colour, a faint large-scale shading and fine grain (a few grey levels)."""
    base = np.asarray(color, np.float32)[None, None, :]
    n = 0.6 * _smooth_noise(rng, h, w, 40.0) + 0.4 * _smooth_noise(rng, h, w, 3.0)
    return _to_u8(base + amp * n[..., None])


def planks(rng: np.random.Generator, h: int, w: int, plank_px: int = 36) -> np.ndarray:
    """Wooden floor planks running along x (the low-frequency direction), dark seams between them."""
    img = np.empty((h, w, 3), np.float32)
    ys = np.arange(h)
    for y0 in range(0, h, plank_px):
        tone = np.array([150, 105, 65], np.float32) * rng.uniform(0.8, 1.15)
        rows = slice(y0, min(h, y0 + plank_px))
        nrows = rows.stop - rows.start
        # grain: streaks stretched along x
        grain = cv2.resize(rng.standard_normal((max(2, nrows), max(2, w // 60))).astype(np.float32),
                           (w, nrows), interpolation=cv2.INTER_CUBIC)
        img[rows] = tone + 14.0 * grain[..., None]
    seam = (ys % plank_px) < 2
    img[seam] *= 0.45
    # staggered butt joints
    for y0 in range(0, h, plank_px):
        x = int(rng.uniform(0.2, 0.8) * w)
        img[y0:y0 + plank_px, max(0, x - 1):x + 1] *= 0.5
    return _to_u8(img)


def blinds(rng: np.random.Generator, h: int, w: int, slat_px: int = 12) -> np.ndarray:
    """Horizontal window blinds: bright slats with a shading ramp and thin dark gaps."""
    ys = np.arange(h)[:, None]
    phase = (ys % slat_px) / slat_px
    shade = 225 - 40 * phase - 60 * (phase > 0.88)
    img = np.repeat(shade, w, axis=1)[..., None] * np.array([1.0, 0.98, 0.93], np.float32)
    img = img + 2.0 * _smooth_noise(rng, h, w, 20.0)[..., None]
    return _to_u8(img)


def tiles(rng: np.random.Generator, h: int, w: int, tile_px: int = 40, grout_px: int = 3,
          base: tuple[int, int, int] = (200, 215, 225)) -> np.ndarray:
    """Glazed square tiles with grout lines (two low-frequency directions)."""
    base = np.asarray(base, np.float32)
    img = np.empty((h, w, 3), np.float32)
    for y0 in range(0, h, tile_px):
        for x0 in range(0, w, tile_px):
            img[y0:y0 + tile_px, x0:x0 + tile_px] = base * rng.uniform(0.93, 1.05)
    img += 3.0 * _smooth_noise(rng, h, w, 8.0)[..., None]
    yy, xx = np.arange(h)[:, None], np.arange(w)[None, :]
    grout = ((yy % tile_px) < grout_px) | ((xx % tile_px) < grout_px)
    img[grout] = np.array([95, 90, 85], np.float32)
    return _to_u8(img)


def book_spines(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """A row of book spines: vertical bands of varied colour and width, title bands across them."""
    img = np.empty((h, w, 3), np.float32)
    x = 0
    while x < w:
        bw = int(rng.integers(max(4, w // 60), max(6, w // 20)))
        col = rng.uniform(30, 230, size=3).astype(np.float32)
        img[:, x:x + bw] = col
        ty = int(rng.uniform(0.15, 0.6) * h)
        img[ty:ty + max(2, h // 12), x + 1:x + bw - 1] = 255 - col  # title band
        img[:, x:x + 1] *= 0.4  # gap between books
        x += bw
    return _to_u8(img + 2.0 * _smooth_noise(rng, h, w, 6.0)[..., None])


def photo_tiles(rng: np.random.Generator, h: int, w: int, names: list[str], per_row: int,
                grout_px: int = 4) -> np.ndarray:
    """Square tiles printed with random crops of photographs (``per_row`` across), grout between."""
    tile = max(8, w // per_row)
    img = np.full((h, w, 3), 80, np.uint8)
    sources = [photo(n, 2 * tile, 2 * tile) for n in names]
    for y0 in range(0, h, tile):
        for x0 in range(0, w, tile):
            src = sources[int(rng.integers(len(sources)))]
            oy, ox = rng.integers(0, tile, size=2)
            th, tw = min(tile, h - y0) - grout_px, min(tile, w - x0) - grout_px
            if th > 0 and tw > 0:
                img[y0:y0 + th, x0:x0 + tw] = src[oy:oy + th, ox:ox + tw]
    return img


def photo(name: str, h: int, w: int) -> np.ndarray:
    """A scikit-image sample photograph, resized to (H, W); grayscale ones are tinted warm
    (``motorcycle``: the left view of ``stereo_motorcycle``)."""
    from skimage import data as skdata

    img = skdata.stereo_motorcycle()[0] if name == "motorcycle" else getattr(skdata, name)()
    if img.ndim == 2:
        img = np.stack([img * 1.0, img * 0.9, img * 0.75], axis=-1)
    img = img[..., :3].astype(np.float32)
    return _to_u8(cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA))


def tinted(rng: np.random.Generator, name: str, h: int, w: int, tint: tuple[float, float, float],
           tile_px: int) -> np.ndarray:
    """A grayscale scikit-image texture (brick, gravel, grass), tiled at ``tile_px`` and tinted."""
    from skimage import data as skdata

    g = getattr(skdata, name)().astype(np.float32)
    g = cv2.resize(g, (tile_px, tile_px), interpolation=cv2.INTER_AREA)
    reps = (int(np.ceil(h / tile_px)), int(np.ceil(w / tile_px)))
    oy, ox = rng.integers(0, tile_px, size=2)
    big = np.tile(g, (reps[0] + 1, reps[1] + 1))[oy:oy + h, ox:ox + w]
    return _to_u8(big[..., None] * np.asarray(tint, np.float32)[None, None, :])
