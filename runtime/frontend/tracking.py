"""KLT feature tracking with forward-backward check, RANSAC and IMU-predicted rotation.

Tracking runs on the raw (distorted) images: undistorting whole images every frame costs more than
undistorting the tracked points (``Camera.pixel_to_normalized``), and the KLT windows see the true texture.
Every track has an id, unique over the run; the SLAM system uses it as the landmark id.

Outlier tests are chi-square tests at a stated pixel sigma (``TrackerConfig.pixel_sigma``, the frame-to-frame
noise of a track on real images): the forward-backward round trip holds two KLT solves, ``|e|^2 / (2 s^2)``
against chi2(2 dof); the epipolar distance between consecutive frames holds two observations,
``d^2 / (2 s^2)`` against chi2(1 dof). The sigma comes from ``benchmarks/bench_frontend.py`` on the real MH_05
excerpt: the epipolar distance of the tracks under the ground-truth relative pose has a robust (MAD) sigma of
0.12 px but a 99th percentile of 0.91 px, a tail far heavier than a Gaussian's; the stated sigma (0.25 px) is
the one whose 99 % bound (3.64 sigma) is that percentile, so that the test keeps 99 % of real tracks. KLT is
photometric: with ``normalize`` it runs on images brought to zero mean and unit spread (gain and bias
compensation), so that an exposure change between frames does not break it.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

from runtime.frontend.features import FeatureConfig, FeatureDetector
from runtime.geometry import Camera

#: chi-square quantiles: ``CHI2_PPF[dof](p)`` without scipy on the hot path (closed forms for 1 and 2 dof)
CHI2_PPF = {
    1: lambda p: 2.0 * float(_erfinv(p)) ** 2,
    2: lambda p: -2.0 * float(np.log1p(-p)),
}


def _erfinv(y: float) -> float:
    """Inverse error function (Newton on ``math.erf``; 1e-12 accurate for 0 <= y < 1)."""
    import math

    if not 0.0 <= y < 1.0:
        raise ValueError(f"erfinv needs 0 <= y < 1, got {y}")
    x = 0.0
    for _ in range(60):
        err = math.erf(x) - y
        if abs(err) < 1e-14:
            break
        x -= err / (2.0 / math.sqrt(math.pi) * math.exp(-x * x))
    return x


def chi2_bound(sigma: float, prob: float, dof: int, n_terms: int = 1) -> float:
    """The largest error norm [px] that passes a chi-square test: ``sqrt(n_terms * chi2_dof(prob)) * sigma``
    (``n_terms``: how many independent errors of ``sigma`` add up in the tested quantity).

    >>> round(chi2_bound(1.0, 0.99, 2), 3), round(chi2_bound(1.0, 0.95, 1), 3)
    (3.035, 1.96)
    """
    if dof not in CHI2_PPF:
        raise ValueError(f"chi2_bound: dof must be 1 or 2, got {dof}")
    if not 0.0 < prob < 1.0:
        raise ValueError(f"chi2_bound: prob must be in (0, 1), got {prob}")
    return float(np.sqrt(n_terms * CHI2_PPF[dof](prob)) * sigma)


def normalize_image(image: np.ndarray) -> np.ndarray:
    """Gain/bias compensation: (H, W) uint8 -> uint8 of mean 128 and standard deviation 48 (a 4x subsampled
    estimate; the same scene under ``a * I + b`` maps to the same image up to clipping and rounding).

    >>> img = (np.arange(64 * 64) % 97).reshape(64, 64).astype(np.uint8) + 40
    >>> a, b = normalize_image(img), normalize_image((1.5 * img + 20).astype(np.uint8))
    >>> int(np.abs(a.astype(int) - b.astype(int)).max()) <= 1
    True
    """
    sub = image[::4, ::4]
    mean, std = float(sub.mean()), float(sub.std())
    gain = 48.0 / max(std, 1.0)
    return cv2.convertScaleAbs(image, alpha=gain, beta=128.0 - gain * mean)

log = logging.getLogger(__name__)


@dataclass
class TrackerConfig:
    """KLT and outlier-rejection settings."""

    win_size: int = 15  # px, KLT window
    pyr_levels: int = 3  # pyramid levels above the base
    max_iter: int = 20
    eps: float = 0.03
    pixel_sigma: float = 0.25  # px, frame-to-frame noise of a track on real images (bench_frontend.py)
    chi2_prob: float = 0.99  # acceptance probability of the chi-square tests (forward-backward, epipolar)
    ransac: bool = True  # fundamental-matrix RANSAC between consecutive frames
    ransac_confidence: float = 0.99
    normalize: bool = True  # gain/bias compensation: KLT on images of fixed mean and spread (exposure changes)
    use_imu_rotation: bool = True  # predict the flow from the gyro rotation (infinite-depth homography)
    line_delay_s: float | None = None  # s between rows of a rolling shutter (None: the camera's sensor.yaml; 0: global)

    def __post_init__(self) -> None:
        if self.line_delay_s is not None and not self.line_delay_s >= 0.0:
            raise ValueError(f"tracker.line_delay_s={self.line_delay_s}: must be >= 0 (0 = global shutter)")

    @property
    def fb_threshold_px(self) -> float:
        """Forward-backward round-trip bound: two KLT solves, 2 dof."""
        return chi2_bound(self.pixel_sigma, self.chi2_prob, 2, n_terms=2)

    @property
    def ransac_threshold_px(self) -> float:
        """Epipolar distance bound between consecutive frames: two observations, 1 dof."""
        return chi2_bound(self.pixel_sigma, self.chi2_prob, 1, n_terms=2)


@dataclass
class FrameFeatures:
    """Features of one frame.

    Attributes:
        ids: (N,) int64 track ids.
        uv: (N, 2) raw (distorted) pixels.
        xn: (N, 2) undistorted normalised coordinates (x/z, y/z in the camera frame).
        uv_u: (N, 2) pixels of the undistorted pinhole image (same K).
        flow_px: median displacement of the tracks since the previous frame [px] (0 for a first frame).
        n_lost: tracks dropped this frame (KLT failure, forward-backward, RANSAC, border).
    """

    ts: int
    ids: np.ndarray
    uv: np.ndarray
    xn: np.ndarray
    uv_u: np.ndarray
    flow_px: float = 0.0
    n_lost: int = 0
    n_ransac_out: int = 0


class FeatureTracker:
    """Keeps the current set of tracks; ``track`` follows them into a new image, ``replenish`` adds corners.

    Args:
        camera: the raw camera (with distortion) the images come from.
        T_b_c: (4, 4) camera-to-body transform (for the gyro rotation prediction).
    """

    def __init__(
        self,
        camera: Camera,
        T_b_c: np.ndarray,
        feat_cfg: FeatureConfig | None = None,
        cfg: TrackerConfig | None = None,
    ) -> None:
        self.camera = camera
        self.cfg = cfg or TrackerConfig()
        self.detector = FeatureDetector(camera.width, camera.height, feat_cfg)
        self.R_b_c = np.asarray(T_b_c, dtype=np.float64)[:3, :3]
        self.K = camera.K
        self.line_delay_s = float(camera.line_delay_s if self.cfg.line_delay_s is None else self.cfg.line_delay_s)
        self._crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, self.cfg.max_iter, self.cfg.eps)
        self._dist = np.asarray(camera.dist, dtype=np.float64)
        self._und_crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 1e-10)
        self._win = (self.cfg.win_size, self.cfg.win_size)
        self.next_id = 0
        self.last_stats: dict = {}  # counts of the last ``track`` call by rejection cause, FB errors of the kept
        self.reset()

    def reset(self) -> None:
        """Forget all tracks (ids keep increasing)."""
        self.prev_pyr = None
        self.prev_image: np.ndarray | None = None
        self.ids = np.zeros(0, np.int64)
        self.uv = np.zeros((0, 2), np.float32)
        self.vel = np.zeros((0, 2), np.float32)  # px/s of each track over the last frame interval (rolling shutter)
        self._prev_ts: int | None = None
        self._last_motion: tuple[float, np.ndarray | None] | None = None  # (interval [s], gyro rotation R_b0_b1)

    @property
    def n_tracks(self) -> int:
        return int(self.ids.size)

    def _pyramid(self, image: np.ndarray):
        # OpenCV 5's Python binding no longer accepts prebuilt pyramids in calcOpticalFlowPyrLK: keep the
        # (gain/bias compensated) image
        return normalize_image(image) if self.cfg.normalize else image

    def normalize(self, uv: np.ndarray) -> np.ndarray:
        """Raw pixels (N, 2) -> undistorted normalised coordinates (N, 2); OpenCV's iteration, same result as
        ``Camera.pixel_to_normalized`` (to 1e-9 px) at a sixth of the cost."""
        if uv.shape[0] == 0:
            return np.zeros((0, 2))
        if not self.camera.has_distortion:
            return self.camera.pixel_to_normalized(uv)
        I3 = np.eye(3)
        out = cv2.undistortPoints(
            np.ascontiguousarray(uv, dtype=np.float64).reshape(-1, 1, 2),
            self.K,
            self._dist,
            R=I3,
            P=I3,
            criteria=self._und_crit,
        )
        return out.reshape(-1, 2)

    def rolling_shutter_pixels(self) -> np.ndarray:
        """The tracks' pixels (N, 2) moved to where they were at the frame's stamp (the middle row's time).

        A rolling shutter reads row ``v`` at ``(v - (H - 1) / 2) * line_delay_s`` after the stamp, so a point moving
        at ``vel`` px/s is seen that far along its motion; first order: ``uv - vel * dt(v)``. A track's velocity is
        its displacement over the last frame interval; a track born this frame takes the flow of the gyro
        rotation there (:meth:`predict`). With ``line_delay_s`` 0 the pixels are returned as they are. The KLT keeps
        the image's pixels (``uv``); the normalised coordinates that the estimator uses (``xn``, ``uv_u``) are
        these."""
        uv = self.uv.astype(np.float64)
        if self.line_delay_s <= 0.0 or uv.shape[0] == 0:
            return uv
        dt_row = (uv[:, 1] - 0.5 * (self.camera.height - 1)) * self.line_delay_s
        return uv - self.vel.astype(np.float64) * dt_row[:, None]

    def _gyro_velocity(self, uv: np.ndarray) -> np.ndarray:
        """Pixel velocity (N, 2) [px/s] of far points under the last interval's gyro rotation (0 before one, and
        without a rolling shutter, where nothing reads it)."""
        if self.line_delay_s <= 0.0 or self._last_motion is None or self._last_motion[1] is None or uv.shape[0] == 0:
            return np.zeros((uv.shape[0], 2), np.float32)
        dt, R = self._last_motion
        return ((self.predict(uv, R) - uv) / dt).astype(np.float32)

    def _features(self, ts: int, flow: float = 0.0, lost: int = 0, ransac_out: int = 0) -> FrameFeatures:
        uv = self.uv.astype(np.float64)
        xn = self.normalize(self.rolling_shutter_pixels())
        uv_u = np.stack(
            [self.camera.fx * xn[:, 0] + self.camera.cx, self.camera.fy * xn[:, 1] + self.camera.cy], -1
        )
        return FrameFeatures(ts, self.ids.copy(), uv, xn, uv_u, flow, lost, ransac_out)

    def predict(self, uv: np.ndarray, R_b0_b1: np.ndarray | None) -> np.ndarray:
        """Where pixels (N, 2) of the previous image land after the body rotation ``R_b0_b1`` (far points)."""
        if R_b0_b1 is None or uv.shape[0] == 0:
            return uv.copy()
        R_c1_c0 = self.R_b_c.T @ R_b0_b1.T @ self.R_b_c
        xn = self.normalize(uv.astype(np.float64))
        f1 = np.concatenate([xn, np.ones((xn.shape[0], 1))], 1) @ R_c1_c0.T
        pred, ok = self.camera.project(f1)
        ok &= self.camera.in_image(pred, 0.0)
        return np.where(ok[:, None], pred, uv).astype(np.float32)

    def track(self, ts: int, image: np.ndarray, R_b0_b1: np.ndarray | None = None) -> FrameFeatures:
        """Follow the current tracks into ``image`` (H, W) uint8.

        Args:
            ts: ns timestamp of the image.
            image: grey image of the raw camera.
            R_b0_b1: gyro-integrated body rotation from the previous image to this one (None: no prediction).

        Returns:
            The surviving tracks in this image.
        """
        c = self.cfg
        if image.shape[:2] != (self.camera.height, self.camera.width):
            raise ValueError(
                f"image is {image.shape[1]}x{image.shape[0]}, "
                f"camera is {self.camera.width}x{self.camera.height}"
            )
        pyr = self._pyramid(image)
        dt = (ts - self._prev_ts) * 1e-9 if self._prev_ts is not None else 0.0
        self._prev_ts = ts
        self._last_motion = (dt, R_b0_b1) if dt > 0 else None
        if self.prev_pyr is None or self.ids.size == 0:
            self.prev_pyr, self.prev_image = pyr, image
            self.vel = np.zeros((self.ids.size, 2), np.float32)
            return self._features(ts)
        p0 = self.uv.reshape(-1, 1, 2).astype(np.float32)
        init = self.predict(self.uv, R_b0_b1 if c.use_imu_rotation else None).reshape(-1, 1, 2)
        p1, st, _ = cv2.calcOpticalFlowPyrLK(
            self.prev_pyr,
            pyr,
            p0,
            init.copy(),
            winSize=self._win,
            maxLevel=c.pyr_levels,
            criteria=self._crit,
            flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
        )
        p0r, st_b, _ = cv2.calcOpticalFlowPyrLK(
            pyr,
            self.prev_pyr,
            p1,
            p0.copy(),
            winSize=self._win,
            maxLevel=c.pyr_levels,
            criteria=self._crit,
            flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
        )
        p1 = p1.reshape(-1, 2)
        fb = np.linalg.norm(p0r.reshape(-1, 2) - p0.reshape(-1, 2), axis=1)
        klt_ok = (st.reshape(-1) == 1) & (st_b.reshape(-1) == 1)
        ok = klt_ok & (fb < c.fb_threshold_px)
        n_fb = int((klt_ok & ~ok).sum())
        inside = self.camera.in_image(p1, float(self.detector.cfg.border) * 0.5)
        n_border = int((ok & ~inside).sum())
        ok &= inside
        n_ransac_out = self._ransac(p0.reshape(-1, 2), p1, ok) if c.ransac else 0
        self.last_stats = {
            "n_in": int(self.ids.size),
            "klt_failed": int((~klt_ok).sum()),
            "fb_rejected": n_fb,
            "border": n_border,
            "ransac_rejected": n_ransac_out,
            "fb_px_kept": fb[ok],
        }
        flow = float(np.median(np.linalg.norm(p1[ok] - p0.reshape(-1, 2)[ok], axis=1))) if ok.any() else 0.0
        n_lost = int(self.ids.size - ok.sum())
        self.ids = self.ids[ok]
        self.vel = ((p1[ok] - p0.reshape(-1, 2)[ok]) / dt).astype(np.float32) if dt > 0 else self.vel[ok]
        self.uv = p1[ok].astype(np.float32)
        self.prev_pyr, self.prev_image = pyr, image
        return self._features(ts, flow, n_lost, n_ransac_out)

    def _ransac(self, p0: np.ndarray, p1: np.ndarray, ok: np.ndarray) -> int:
        """Fundamental-matrix RANSAC on the undistorted pixels of the tracks still ``ok`` (N,) between the
        previous (N, 2) and the current (N, 2) image; clears ``ok`` of the outliers and returns their count."""
        c = self.cfg
        idx = np.nonzero(ok)[0]
        if idx.size < 12:
            return 0
        f, cc = np.array([self.camera.fx, self.camera.fy]), np.array([self.camera.cx, self.camera.cy])
        a = self.normalize(p0[idx].astype(np.float64)) * f + cc  # undistorted pixels
        b = self.normalize(p1[idx].astype(np.float64)) * f + cc
        if np.median(np.linalg.norm(a - b, axis=1)) <= 0.5:  # no motion: epipolar geometry undefined
            return 0
        _, inl = cv2.findFundamentalMat(a, b, cv2.FM_RANSAC, c.ransac_threshold_px, c.ransac_confidence)
        if inl is None:
            return 0
        bad = idx[inl.reshape(-1) == 0]
        ok[bad] = False
        return int(bad.size)

    def current(self, ts: int) -> FrameFeatures:
        """The current tracks (after any :meth:`drop`) as features of the image at ``ts``."""
        return self._features(ts)

    def replenish(self, ts: int, image: np.ndarray) -> FrameFeatures:
        """Detect new corners in ``image`` (the image last tracked) away from the current tracks; new ids."""
        new = self.detector.detect(image, self.uv)
        if new.shape[0]:
            ids = np.arange(self.next_id, self.next_id + new.shape[0], dtype=np.int64)
            self.next_id += new.shape[0]
            self.ids = np.concatenate([self.ids, ids])
            self.vel = np.concatenate([self.vel, self._gyro_velocity(new.astype(np.float64))], 0)
            self.uv = np.concatenate([self.uv, new.astype(np.float32)], 0)
        if self.prev_pyr is None:
            self.prev_pyr, self.prev_image = self._pyramid(image), image
        return self._features(ts)

    def rename(self, old: np.ndarray, new: np.ndarray) -> np.ndarray:
        """Give tracks new ids (a track re-associated with an old map point takes the point's id).

        Ids stay unique: a pair whose new id another track keeps, or that an earlier pair already gives, is
        skipped. Returns the mask of the pairs applied."""
        old, new = np.asarray(old, np.int64).reshape(-1), np.asarray(new, np.int64).reshape(-1)
        applied = np.zeros(old.size, dtype=bool)
        kept = set(self.ids.tolist()) - set(old.tolist())
        m = {}
        for n, (a, b) in enumerate(zip(old.tolist(), new.tolist(), strict=True)):
            if a in m or b in kept:
                continue
            m[a] = b
            kept.add(b)
            applied[n] = True
        if m:
            self.ids = np.array([m.get(int(j), int(j)) for j in self.ids], dtype=np.int64)
        return applied

    def drop(self, ids: np.ndarray) -> None:
        """Stop tracking the given ids (e.g. landmarks the backend rejected as outliers)."""
        if ids.size == 0 or self.ids.size == 0:
            return
        keep = ~np.isin(self.ids, ids)
        self.ids, self.uv, self.vel = self.ids[keep], self.uv[keep], self.vel[keep]
