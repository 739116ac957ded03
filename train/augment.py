"""Training augmentation and the validation resize + crop (paper Sec. 6.1), numpy/cv2.

Geometry. Validation maps a frame to the network with :class:`runtime.geometry.NetworkMapping` (resize so the
frame covers ``height x width``, then centre-crop): a source pixel ``p`` lands at ``c_out + a * (p - c_src)``
with ``a`` the mapping's scale and ``c`` the pixel centres of the two images. Training draws, per sample,

* a scale ``s`` in [1, 1.5]: the image is zoomed by ``s`` and the depth divided by ``s`` (a camera ``s`` times
  closer sees the same picture at ``1/s`` the depth),
* a rotation ``alpha`` in [-10, 10] degrees about the image centre,
* a horizontal flip with probability 0.5,

and warps image and depth with ONE affine map ``p -> c_out + R(alpha) F diag(a s, a s) (p - c_src)`` followed
by the same centre crop, so that they stay aligned pixel for pixel; with ``s = 1, alpha = 0`` and no flip this
is exactly the validation mapping. The image is first shrunk with area filtering to ``a * 1.5`` of its size
(when that is a reduction) so that the final bilinear warp does not alias; the depth is warped from full
resolution with nearest-neighbour sampling (no mixing of depths across edges, 0 stays invalid). Pixels rotated
in from outside the frame have depth 0 (invalid) and reflected image content.

Photometry. Colour jitter multiplies brightness, contrast and saturation by factors in [0.8, 1.2]
(torchvision's definitions: contrast and saturation blend with the grey mean / grey image), in that order, on
the float image in [0, 1]. Grey modalities convert (ITU-R 601 luma, as ``cv2.cvtColor``) after the jitter.

Sparse depth (``*s`` modalities) comes from FAST corners of the final grey image, see :mod:`train.sparse`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from runtime.densify import network_fill
from runtime.geometry import NetworkMapping
from train.sparse import SparseConfig, sample_sparse_depth

__all__ = [
    "AugmentConfig",
    "FrameTransform",
    "MODALITIES",
    "affine_matrix",
    "color_jitter",
    "to_gray",
    "warp_frame",
]

#: Input channels per modality: (grey?, sparse?).
MODALITIES: dict[str, tuple[bool, bool]] = {
    "rgb": (False, False),
    "rgbs": (False, True),
    "gray": (True, False),
    "grays": (True, True),
}

_LUMA = np.array([0.299, 0.587, 0.114], np.float32)


@dataclass(frozen=True)
class AugmentConfig:
    """Ranges of the random training transforms (defaults: the paper's).

    Attributes:
        scale: (min, max) zoom ``s``; depth is divided by ``s``.
        rotation_deg: maximum absolute rotation [deg].
        color_jitter: brightness/contrast/saturation factors are drawn in ``[1 - j, 1 + j]``.
        hflip_p: probability of a horizontal flip.
    """

    scale: tuple[float, float] = (1.0, 1.5)
    rotation_deg: float = 10.0
    color_jitter: float = 0.2
    hflip_p: float = 0.5

    def __post_init__(self) -> None:
        lo, hi = self.scale
        if not 0 < lo <= hi:
            raise ValueError(f"scale={self.scale} must satisfy 0 < min <= max")
        if self.rotation_deg < 0 or not 0 <= self.color_jitter < 1 or not 0 <= self.hflip_p <= 1:
            raise ValueError(
                f"bad augmentation rotation_deg={self.rotation_deg}, color_jitter={self.color_jitter}, "
                f"hflip_p={self.hflip_p}"
            )


def affine_matrix(
    in_hw: tuple[int, int], out_hw: tuple[int, int], scale: float, angle_deg: float = 0.0, flip: bool = False
) -> np.ndarray:
    """(2, 3) affine map from source pixels to output pixels (cv2 convention, pixel centres at integers).

    ``p_out = c_out + R(angle) F diag(scale, scale) (p_src - c_src)``, ``c = ((W - 1) / 2, (H - 1) / 2)``,
    ``F`` = horizontal mirror when ``flip``. Positive angles turn the picture clockwise on screen (y down).

    >>> A = affine_matrix((480, 640), (224, 224), 224 / 480)
    >>> np.allclose(A @ [319.5, 239.5, 1], [111.5, 111.5])
    True
    """
    (hi, wi), (ho, wo) = in_hw, out_hw
    t = math.radians(angle_deg)
    c, s = math.cos(t), math.sin(t)
    f = -1.0 if flip else 1.0
    m = scale * np.array([[c * f, -s], [s * f, c]])
    c_src = np.array([(wi - 1) / 2.0, (hi - 1) / 2.0])
    c_out = np.array([(wo - 1) / 2.0, (ho - 1) / 2.0])
    return np.concatenate([m, (c_out - m @ c_src)[:, None]], axis=1)


def warp_frame(
    rgb: np.ndarray, depth: np.ndarray, A: np.ndarray, out_hw: tuple[int, int], prescale: float | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Warp an image and its depth with the same affine map ``A`` (source -> output pixels).

    Args:
        rgb: (H, W, 3) uint8.
        depth: (H, W) float32 [m], 0 = invalid.
        A: (2, 3) map from source to output pixel coordinates.
        out_hw: output (height, width).
        prescale: when < 1, the image is first area-resized by this factor (anti-aliasing); ``A`` is
            adjusted so that the result is the same geometric mapping.

    Returns:
        rgb (h, w, 3) uint8 and depth (h, w) float32 [m] (nearest-neighbour; outside the frame 0).
    """
    h, w = out_hw
    d = cv2.warpAffine(
        depth, A, (w, h), flags=cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0
    )
    img, Ai = rgb, A
    if prescale is not None and prescale < 1.0:
        hi, wi = rgb.shape[:2]
        rw, rh = max(1, int(round(wi * prescale))), max(1, int(round(hi * prescale)))
        img = cv2.resize(rgb, (rw, rh), interpolation=cv2.INTER_AREA)
        px, py = rw / wi, rh / hi
        # resized pixel q -> source pixel p = (q + 0.5) / px - 0.5, then A
        D = np.array([[1.0 / px, 0.0, 0.5 / px - 0.5], [0.0, 1.0 / py, 0.5 / py - 0.5], [0.0, 0.0, 1.0]])
        Ai = A @ D
    out = cv2.warpAffine(img, Ai, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT_101)
    return out, d


def to_gray(img: np.ndarray) -> np.ndarray:
    """(H, W, 3) float RGB -> (H, W) float grey (0.299 R + 0.587 G + 0.114 B)."""
    return img @ _LUMA


def color_jitter(img: np.ndarray, brightness: float, contrast: float, saturation: float) -> np.ndarray:
    """torchvision-style jitter of a float RGB image (H, W, 3) in [0, 1]; returns a clipped float32 copy.

    >>> x = np.full((2, 2, 3), 0.5, np.float32)
    >>> round(float(color_jitter(x, 1.2, 1.0, 1.0)[0, 0, 0]), 6)
    0.6
    """
    x = np.clip(img * np.float32(brightness), 0.0, 1.0)
    m = np.float32(to_gray(x).mean())
    x = np.clip((x - m) * np.float32(contrast) + m, 0.0, 1.0)
    g = to_gray(x)[..., None]
    return np.clip((x - g) * np.float32(saturation) + g, 0.0, 1.0).astype(np.float32, copy=False)


class FrameTransform:
    """One NYU frame (RGB 480x640 + depth) -> network input for a modality.

    Args:
        height, width: network input size [px].
        modality: ``rgb | rgbs | gray | grays``.
        train: random augmentation + noisy training sparse depth, or resize + centre crop + 125 clean samples.
        augment: augmentation ranges (training only); None = the paper's.
        sparse: sparse sampling parameters (``*s`` modalities); None = the defaults (125 at evaluation).
        with_fill: also return ``fill`` (1, h, w) [m], the relative network's interpolated sparse input
            (:func:`runtime.densify.network_fill`), so that it is computed in the data loader's workers rather
            than in the training step (``*s`` modalities only).

    ``__call__(rgb (H, W, 3) uint8, depth (H, W) float32 [m], rng)`` returns a dict of float32 arrays:
    ``image`` (Cin, h, w): image channels in [0, 1] (grey or RGB), then the sparse depth [m] for ``*s``;
    ``depth`` (1, h, w) [m], 0 = invalid; ``params`` (7,) the drawn ``(s, alpha_deg, flip, brightness,
    contrast, saturation, n_sparse)`` (identity values at evaluation); ``fill`` (1, h, w) [m] when asked for.
    """

    def __init__(
        self,
        height: int,
        width: int,
        modality: str,
        train: bool,
        augment: AugmentConfig | None = None,
        sparse: SparseConfig | None = None,
        with_fill: bool = False,
    ):
        if modality not in MODALITIES:
            raise ValueError(f"modality={modality!r} not in {sorted(MODALITIES)}")
        if height <= 0 or width <= 0:
            raise ValueError(f"network size {height}x{width} must be positive")
        self.out_hw = (int(height), int(width))
        self.modality = modality
        self.gray, self.use_sparse = MODALITIES[modality]
        self.train = bool(train)
        self.augment = augment if augment is not None else AugmentConfig()
        self.sparse = sparse if sparse is not None else SparseConfig()
        self.with_fill = bool(with_fill) and self.use_sparse
        self._maps: dict[tuple[int, int], NetworkMapping] = {}

    def mapping(self, in_hw: tuple[int, int]) -> NetworkMapping:
        """The validation mapping (resize + centre crop) for frames of size ``in_hw``."""
        if in_hw not in self._maps:
            self._maps[in_hw] = NetworkMapping.fit(in_hw[1], in_hw[0], self.out_hw[1], self.out_hw[0])
        return self._maps[in_hw]

    def __call__(self, rgb: np.ndarray, depth: np.ndarray, rng: np.random.Generator) -> dict[str, np.ndarray]:
        if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
            raise ValueError(f"rgb must be (H, W, 3) uint8, got shape {rgb.shape} dtype {rgb.dtype}")
        if depth.shape != rgb.shape[:2]:
            raise ValueError(f"depth has shape {depth.shape}, rgb has {rgb.shape[:2]}")
        depth = depth.astype(np.float32, copy=False)
        m = self.mapping(rgb.shape[:2])
        s, angle, flip = 1.0, 0.0, False
        bcs = np.ones(3)
        if self.train:
            a = self.augment
            s = float(rng.uniform(a.scale[0], a.scale[1]))
            angle = float(rng.uniform(-a.rotation_deg, a.rotation_deg))
            flip = bool(rng.random() < a.hflip_p)
            A = affine_matrix(rgb.shape[:2], self.out_hw, m.scale * s, angle, flip)
            img_u8, d = warp_frame(rgb, depth, A, self.out_hw, prescale=m.scale * a.scale[1])
            d = d / np.float32(s)
            j = a.color_jitter
            bcs = rng.uniform(1.0 - j, 1.0 + j, size=3)
            img = color_jitter(img_u8.astype(np.float32) / 255.0, *bcs)
        else:
            img = m.image_to_network(rgb).astype(np.float32) / 255.0
            d = m.image_to_network(depth, nearest=True)
        gray = to_gray(img)
        chans = [gray[None]] if self.gray else [img.transpose(2, 0, 1)]
        n_sparse = 0
        if self.use_sparse:
            g8 = np.clip(gray * 255.0 + 0.5, 0, 255).astype(np.uint8)
            sp, uv = sample_sparse_depth(g8, d, rng, self.train, self.sparse)
            chans.append(sp[None])
            n_sparse = len(uv)
        image = np.ascontiguousarray(np.concatenate(chans, axis=0), dtype=np.float32)
        out = {
            "image": image,
            "depth": np.ascontiguousarray(d[None], dtype=np.float32),
            "params": np.array([s, angle, float(flip), *bcs, n_sparse], np.float32),
        }
        if self.with_fill:
            out["fill"] = network_fill(image[-1])[None]
        return out
