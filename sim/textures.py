"""Procedural surface textures rich in corners, packed into one flat atlas for vectorised bilinear look-ups.

Every face of every box gets its own texture image, generated once per scene from a seeded generator: a base
colour modulated by multi-octave value noise, then rectangles (filled and outlined), ellipses and small blobs
at several scales (their corners and junctions are what FAST and KLT track), plus a tile grid on floors and
ceilings. The ``plain`` style is a uniform colour with very faint low-frequency noise (the textureless "white
wall").

Texel ``(i, j)`` (row, column) of a face covers ``[j * texel, (j + 1) * texel) x [i * texel, (i + 1) *
texel)`` in the face's ``(u, v)`` coordinates [m]; its value is the texel-centre colour, looked up bilinearly.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["STYLES", "value_noise", "make_texture", "TextureAtlas"]

STYLES = ("wall", "floor", "ceiling", "object", "plain")


def value_noise(
    rng: np.random.Generator, h: int, w: int, cell: float, octaves: int = 3, gain: float = 0.5
) -> np.ndarray:
    """Multi-octave value noise (bicubic-interpolated random lattices), zero mean, roughly in [-1, 1].

    Args:
        rng: seeded generator.
        h, w: output size [texels].
        cell: lattice spacing of the first octave [texels]; each octave halves it.
        octaves: number of octaves.
        gain: amplitude factor between octaves.

    Returns:
        (h, w) float32.
    """
    out = np.zeros((h, w), np.float32)
    amp, total = 1.0, 0.0
    for _ in range(octaves):
        gh = max(2, int(np.ceil(h / cell)) + 1)
        gw = max(2, int(np.ceil(w / cell)) + 1)
        grid = rng.uniform(-1.0, 1.0, (gh, gw)).astype(np.float32)
        out += amp * cv2.resize(grid, (w, h), interpolation=cv2.INTER_CUBIC)
        total += amp
        amp *= gain
        cell = max(cell / 2.0, 2.0)
    return out / np.float32(total)


def _jitter(rng: np.random.Generator, color: np.ndarray, amount: float) -> tuple[float, float, float]:
    c = np.clip(color + rng.uniform(-amount, amount, 3), 0.02, 0.98)
    return (float(c[0]), float(c[1]), float(c[2]))


def _shapes(
    rng: np.random.Generator,
    img: np.ndarray,
    texel: float,
    scales_m: tuple[float, ...],
    per_m2: tuple[float, ...],
    palette: np.ndarray,
    jitter: float,
) -> None:
    """Draw rectangles, outlines and ellipses of several sizes in place (cv2 drawing, no per-texel loops)."""
    h, w = img.shape[:2]
    area = h * w * texel * texel
    for scale, density in zip(scales_m, per_m2, strict=True):
        n = int(rng.poisson(density * area))
        if n == 0:
            continue
        s = scale / texel  # texels
        cx = rng.uniform(-0.1 * w, 1.1 * w, n)
        cy = rng.uniform(-0.1 * h, 1.1 * h, n)
        sx = s * rng.uniform(0.4, 1.6, n)
        sy = s * rng.uniform(0.4, 1.6, n)
        kind = rng.uniform(0.0, 1.0, n)
        col = rng.integers(0, len(palette), n)
        thick = rng.integers(1, 4, n)
        for i in range(n):
            color = _jitter(rng, palette[col[i]], jitter)
            p0 = (int(cx[i] - sx[i] / 2), int(cy[i] - sy[i] / 2))
            p1 = (int(cx[i] + sx[i] / 2), int(cy[i] + sy[i] / 2))
            if kind[i] < 0.55:  # filled rectangle: four corners
                cv2.rectangle(img, p0, p1, color, -1)
            elif kind[i] < 0.75:  # outlined rectangle: corners and line junctions
                cv2.rectangle(img, p0, p1, color, int(thick[i]))
            elif kind[i] < 0.92:  # filled ellipse / blob
                axes = (max(1, int(sx[i] / 2)), max(1, int(sy[i] / 2)))
                cv2.ellipse(img, (int(cx[i]), int(cy[i])), axes, 0.0, 0.0, 360.0, color, -1)
            else:  # stripes (a row of thin bars)
                k = int(rng.integers(3, 7))
                bw = max(1, int(sx[i] / (2 * k)))
                for j in range(k):
                    x0 = p0[0] + 2 * j * bw
                    cv2.rectangle(img, (x0, p0[1]), (x0 + bw - 1, p1[1]), color, -1)


def _grid(img: np.ndarray, texel: float, pitch_m: float, color: tuple[float, float, float], rng) -> None:
    """Tile grid lines (floors, ceilings) with per-tile brightness variation."""
    h, w = img.shape[:2]
    p = max(4, int(round(pitch_m / texel)))
    ny, nx = h // p + 2, w // p + 2
    tiles = rng.uniform(0.9, 1.1, (ny, nx)).astype(np.float32)
    img *= np.repeat(np.repeat(tiles, p, 0), p, 1)[:h, :w, None]
    lw = max(1, int(round(0.006 / texel)))
    for x in range(0, w, p):
        cv2.rectangle(img, (x, 0), (x + lw - 1, h - 1), color, -1)
    for y in range(0, h, p):
        cv2.rectangle(img, (0, y), (w - 1, y + lw - 1), color, -1)


def make_texture(
    rng: np.random.Generator, width_m: float, height_m: float, texel: float, style: str, base: np.ndarray
) -> np.ndarray:
    """Texture image of one face.

    Args:
        rng: seeded generator (consumed deterministically).
        width_m, height_m: face extent along its u and v axes [m].
        texel: texel size [m].
        style: one of :data:`STYLES`.
        base: (3,) base RGB colour in [0, 1].

    Returns:
        (h, w, 3) float32 RGB albedo in [0, 1], ``h = ceil(height_m / texel) + 1 >= 2`` (same for w).
    """
    if style not in STYLES:
        raise ValueError(f"unknown texture style {style!r}; expected one of {STYLES}")
    if texel <= 0:
        raise ValueError(f"texel must be positive, got {texel}")
    w = max(2, int(np.ceil(width_m / texel)) + 1)
    h = max(2, int(np.ceil(height_m / texel)) + 1)
    base = np.asarray(base, np.float32)
    if style == "plain":
        n = value_noise(rng, h, w, cell=0.8 / texel, octaves=2)
        return np.clip(base[None, None, :] * (1.0 + 0.006 * n[..., None]), 0.0, 1.0).astype(np.float32)

    noise = value_noise(rng, h, w, cell=0.6 / texel, octaves=4)
    img = base[None, None, :] * (1.0 + 0.18 * noise[..., None])
    img = np.ascontiguousarray(img, dtype=np.float32)
    # a palette of colours around (and away from) the base colour
    palette = np.concatenate(
        [
            np.clip(base[None] * rng.uniform(0.35, 1.5, (4, 1)), 0, 1),
            rng.uniform(0.05, 0.95, (4, 3)),
            np.array([[0.08, 0.08, 0.08], [0.92, 0.92, 0.9]]),
        ]
    ).astype(np.float32)
    if style == "wall":
        _shapes(rng, img, texel, (0.5, 0.18, 0.06), (0.8, 7.0, 35.0), palette, 0.05)
    elif style == "floor":
        _grid(img, texel, float(rng.uniform(0.3, 0.6)), _jitter(rng, base * 0.5, 0.03), rng)
        _shapes(rng, img, texel, (0.15, 0.05), (2.5, 14.0), palette, 0.05)
    elif style == "ceiling":
        _grid(img, texel, 0.6, _jitter(rng, base * 0.6, 0.02), rng)
        _shapes(rng, img, texel, (0.2, 0.06), (1.0, 8.0), palette, 0.05)
    else:  # object
        _shapes(rng, img, texel, (0.25, 0.09, 0.03), (5.0, 30.0, 90.0), palette, 0.08)
    fine = value_noise(rng, h, w, cell=0.02 / texel, octaves=2)
    img *= 1.0 + 0.1 * fine[..., None]
    img = cv2.GaussianBlur(img, (0, 0), 0.6)  # band-limit: fewer aliasing artefacts when minified
    return np.clip(img, 0.0, 1.0).astype(np.float32)


@dataclass
class TextureAtlas:
    """All face textures of a scene in one flat array (bilinear look-ups by flat index).

    Attributes:
        data: (N, C) float32 texels (C = 3 RGB or 1 grey), rows of all faces concatenated.
        offset: (F,) int64 first row of each face in ``data``.
        width, height: (F,) int32 texture size of each face [texels].
        texel: texel size [m].
    """

    data: np.ndarray
    offset: np.ndarray
    width: np.ndarray
    height: np.ndarray
    texel: float

    @staticmethod
    def pack(images: list[np.ndarray], texel: float, grey: bool) -> TextureAtlas:
        """Pack per-face (h, w, 3) images; ``grey`` keeps only the luminance (ITU-R BT.601 weights)."""
        offs, ws, hs, flat = [], [], [], []
        n = 0
        for im in images:
            h, w = im.shape[:2]
            px = im.reshape(-1, 3)
            if grey:
                px = (px @ np.array([0.299, 0.587, 0.114], np.float32))[:, None]
            flat.append(px.astype(np.float32))
            offs.append(n)
            ws.append(w)
            hs.append(h)
            n += h * w
        data = np.ascontiguousarray(np.concatenate(flat, 0))
        return TextureAtlas(
            data, np.asarray(offs, np.int64), np.asarray(ws, np.int32), np.asarray(hs, np.int32), texel
        )

    @property
    def channels(self) -> int:
        return int(self.data.shape[1])

    def lookup(self, face: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Bilinear look-up.

        Args:
            face: (P,) int face indices.
            u, v: (P,) float32 face coordinates [m] from the face's origin corner.

        Returns:
            (P, C) float32 albedo.
        """
        if not hasattr(self, "_umax"):  # per-face clamp limits, and a 1-D copy of grey data (faster gathers)
            self._umax = (self.width - 1).astype(np.float32) - np.float32(1e-3)
            self._vmax = (self.height - 1).astype(np.float32) - np.float32(1e-3)
            self._flat = np.ascontiguousarray(self.data[:, 0]) if self.channels == 1 else None
        inv = np.float32(1.0 / self.texel)
        w = self.width[face]
        fu = np.clip(u * inv - np.float32(0.5), np.float32(0.0), self._umax[face])
        fv = np.clip(v * inv - np.float32(0.5), np.float32(0.0), self._vmax[face])
        iu = fu.astype(np.int32)  # floor (non-negative)
        iv = fv.astype(np.int32)
        fu -= iu
        fv -= iv
        idx = self.offset[face] + iv.astype(np.int64) * w + iu
        if self._flat is not None:
            d = self._flat
            c00, c01 = np.take(d, idx), np.take(d, idx + 1)
            idx += w
            c10, c11 = np.take(d, idx), np.take(d, idx + 1)
        else:
            fu, fv = fu[:, None], fv[:, None]
            d = self.data
            c00, c01 = np.take(d, idx, axis=0), np.take(d, idx + 1, axis=0)
            idx += w
            c10, c11 = np.take(d, idx, axis=0), np.take(d, idx + 1, axis=0)
        c01 -= c00
        c01 *= fu
        c00 += c01  # top row
        c11 -= c10
        c11 *= fu
        c10 += c11  # bottom row
        c10 -= c00
        c10 *= fv
        c00 += c10
        return c00 if c00.ndim == 2 else c00[:, None]
