"""Natural-looking surface textures: 1/f (fractal) noise, wood, fabric, paint, concrete, printed clutter.

Real indoor surfaces are not flat shapes on paper: their brightness has a roughly 1/f amplitude spectrum, large
areas (painted walls, floors) carry almost no texture, and clutter (books, labels, boxes, machines) is where the
corners are. Every style here starts from band-limited 1/f noise; ``clutter`` adds printed marks (labels, text
lines, edges) at a configurable density.

All functions return (h, w, 3) float32 RGB albedo in [0, 1] for a face of ``width_m x height_m`` at ``texel``
metres per texel, deterministic given the generator (same layout as :func:`sim.textures.make_texture`).
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["NATURAL_STYLES", "pink_noise", "make_natural_texture"]

NATURAL_STYLES = ("paint", "concrete", "wood", "fabric", "clutter", "floor", "window", "metal")


def pink_noise(rng: np.random.Generator, h: int, w: int, beta: float = 1.0, min_period: float = 2.0) -> np.ndarray:
    """Zero-mean, unit-std noise with amplitude spectrum ``1 / f^beta`` (beta = 1: natural-image statistics).

    Args:
        rng: seeded generator.
        h, w: size [texels].
        beta: spectral slope of the amplitude.
        min_period: frequencies above ``1 / min_period`` cycles per texel are removed (band limit) [texels].

    Returns:
        (h, w) float32.
    """
    H, W = cv2.getOptimalDFTSize(h), cv2.getOptimalDFTSize(w)
    fy = np.fft.fftfreq(H)[:, None]
    fx = np.fft.rfftfreq(W)[None, :]
    f = np.sqrt(fx * fx + fy * fy)
    f[0, 0] = 1.0
    amp = f ** (-beta)
    amp[0, 0] = 0.0
    amp[f > 1.0 / min_period] = 0.0
    spec = (rng.standard_normal(amp.shape) + 1j * rng.standard_normal(amp.shape)) * amp
    x = np.fft.irfft2(spec, s=(H, W))[:h, :w]
    x -= x.mean()
    return (x / max(float(x.std()), 1e-12)).astype(np.float32)


def _clip(img: np.ndarray) -> np.ndarray:
    return np.clip(img, 0.0, 1.0).astype(np.float32)


def _marks(rng: np.random.Generator, img: np.ndarray, texel: float, per_m2: float, size_m: float) -> None:
    """Printed marks in place: labels, text lines, edges, dots (the corners of real clutter)."""
    h, w = img.shape[:2]
    n = int(rng.poisson(per_m2 * h * w * texel * texel))
    if n == 0:
        return
    s = size_m / texel
    cx, cy = rng.uniform(0, w, n), rng.uniform(0, h, n)
    sx, sy = s * rng.lognormal(0.0, 0.6, n), s * rng.lognormal(-0.5, 0.6, n)
    kind = rng.uniform(0, 1, n)
    shade = rng.uniform(0.05, 0.95, (n, 3))
    for i in range(n):
        col = tuple(float(c) for c in shade[i])
        p0 = (int(cx[i] - sx[i] / 2), int(cy[i] - sy[i] / 2))
        p1 = (int(cx[i] + sx[i] / 2), int(cy[i] + sy[i] / 2))
        if kind[i] < 0.45:  # label / sticker
            cv2.rectangle(img, p0, p1, col, -1)
        elif kind[i] < 0.8:  # a few lines of "text"
            lh = max(1, int(sy[i] / 6))
            for j in range(int(rng.integers(2, 6))):
                y = p0[1] + 2 * j * lh
                x1 = p0[0] + int(sx[i] * rng.uniform(0.4, 1.0))
                cv2.rectangle(img, (p0[0], y), (x1, y + lh - 1), col, -1)
        else:  # a dot / screw head
            cv2.circle(img, (int(cx[i]), int(cy[i])), max(1, int(sy[i] / 3)), col, -1)


def make_natural_texture(
    rng: np.random.Generator,
    width_m: float,
    height_m: float,
    texel: float,
    style: str,
    base: np.ndarray,
    clutter: float = 1.0,
) -> np.ndarray:
    """Texture of one face in a natural style.

    Args:
        rng: seeded generator (consumed deterministically).
        width_m, height_m: face extent along its u and v axes [m].
        texel: texel size [m].
        style: one of :data:`NATURAL_STYLES`.
        base: (3,) base RGB colour in [0, 1].
        clutter: density factor of printed marks (``clutter`` style).

    Returns:
        (h, w, 3) float32 RGB albedo, ``h = ceil(height_m / texel) + 1`` (same for w).
    """
    if style not in NATURAL_STYLES:
        raise ValueError(f"unknown natural texture style {style!r}; expected one of {NATURAL_STYLES}")
    w = max(2, int(np.ceil(width_m / texel)) + 1)
    h = max(2, int(np.ceil(height_m / texel)) + 1)
    base = np.asarray(base, np.float32)[None, None, :]
    if style == "window":  # bright, nearly uniform (an emissive panel)
        return _clip(np.broadcast_to(base, (h, w, 3)) * (1.0 + 0.02 * pink_noise(rng, h, w)[..., None]))
    n = pink_noise(rng, h, w, beta=1.0)[..., None]
    if style == "paint":  # large low-texture areas: faint 1/f mottling
        return _clip(base * (1.0 + 0.025 * n))
    if style == "concrete":
        fine = pink_noise(rng, h, w, beta=0.6)[..., None]
        img = np.ascontiguousarray(base * (1.0 + 0.3 * n + 0.1 * fine), dtype=np.float32)
        _marks(rng, img, texel, 20.0, 0.06)  # stains, bolts, notices
        return _clip(img)
    if style == "metal":  # brushed: anisotropic streaks
        streak = cv2.blur(rng.standard_normal((h, w)).astype(np.float32), (max(3, int(0.3 / texel)), 1))
        streak /= max(float(streak.std()), 1e-6)
        img = np.ascontiguousarray(base * (1.0 + 0.12 * n + 0.05 * streak[..., None]), dtype=np.float32)
        _marks(rng, img, texel, 8.0, 0.05)  # rivets, labels, panel edges
        return _clip(img)
    if style == "wood":
        period = float(rng.uniform(0.008, 0.02)) / texel  # ring spacing [texels]
        v = np.arange(h, dtype=np.float32)[:, None]
        warp = 4.0 * period * pink_noise(rng, h, w, beta=1.5)
        rings = 0.5 + 0.5 * np.sin(2.0 * np.pi * (v + warp) / period)
        grain = cv2.blur(rng.standard_normal((h, w)).astype(np.float32), (max(3, int(0.05 / texel)), 1))
        grain /= max(float(grain.std()), 1e-6)
        img = base * (0.8 + 0.25 * rings[..., None] + 0.04 * grain[..., None] + 0.08 * n)
        return _clip(img)
    if style == "fabric":
        p = max(2.0, float(rng.uniform(0.002, 0.004)) / texel)
        u = np.arange(w, dtype=np.float32)[None, :]
        v = np.arange(h, dtype=np.float32)[:, None]
        weave = np.sin(2 * np.pi * u / p) * np.sin(2 * np.pi * v / p)
        img = base * (1.0 + 0.05 * weave[..., None] + 0.1 * n)
        if rng.uniform() < 0.5:  # a woven pattern (checks / stripes)
            q = float(rng.uniform(0.03, 0.12)) / texel
            stripes = (np.sin(2 * np.pi * u / q) > 0.6) | (np.sin(2 * np.pi * v / q) > 0.6)
            img = img * np.where(stripes[..., None], 0.7, 1.0)
        return _clip(img)
    if style == "floor":  # planks or large tiles with 1/f wear
        img = base * (1.0 + 0.1 * n)
        pitch = max(4, int(float(rng.uniform(0.15, 0.6)) / texel))
        ny = h // pitch + 2
        img *= np.repeat(rng.uniform(0.85, 1.15, ny).astype(np.float32), pitch)[:h, None, None]
        lw = max(1, int(round(0.004 / texel)))
        for y in range(0, h, pitch):
            img[y : y + lw] *= 0.6
        return _clip(img)
    # clutter: 1/f background plus printed marks at two scales
    img = np.ascontiguousarray(base * (1.0 + 0.3 * n), dtype=np.float32)
    _marks(rng, img, texel, 15.0 * clutter, 0.12)
    _marks(rng, img, texel, 90.0 * clutter, 0.03)
    img = cv2.GaussianBlur(img, (0, 0), 0.6)
    return _clip(img)
