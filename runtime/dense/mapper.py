"""Tight coupling of the depth network with the sliding window (Sec. 3.3, 5.2-5.3, Eq. 2, 13-17).

:class:`DenseMapper` is a :class:`runtime.backend.graph.FactorProvider` registered with the backend when
``dit-slam dense=true``:

* **Network in the loop** (:meth:`DenseMapper.on_keyframe`): for each new keyframe the cam0 image is
  undistorted, mapped to the network size (``NetworkMapping``), and the sparse depth image of the map points
  the keyframe observes (projected with their current metric depth) is the ``grays`` sparse channel;
  ``prior.onnx`` runs once per keyframe.
* **Depth codes** (:meth:`DenseMapper.add_factors`, called by the backend before each LM run): ``C(k)`` in
  R^C for the newest keyframe and its ``n_code_keyframes - 1`` most co-visible active keyframes (Sec. 5.3,
  "five most co-visible keyframes"), each with the CVAE prior ``N(0, I)`` (``PriorFactorVector``); Eq. 13
  factors per code keyframe (landmarks as variables; ``geo_fixed_landmarks`` holds them fixed, which made the
  ``whitewall`` run diverge, seed 0, 30 s); Eq. 14
  factors from the newest code keyframe to every other code keyframe on the Sec. 5.2 samples (``n_consis``
  per keyframe). Factors are rebuilt at every optimisation (their noise models are evaluated at the current
  estimate).
* **Decoder cache and its approximation** (:class:`LinearizedDepth`): the exact decoder and its FD Jacobian
  (Eq. 17, one batch of C+1 codes) are evaluated when the factors are built, at each code keyframe's current
  code (not again when the code did not change: per-code cache), and during LM only when a code moved more
  than ``relin_threshold`` (Euclidean norm, code units) from that linearisation point; in between, the depth
  map is the first-order expansion ``D(c0) + J(c0) (c - c0)`` (so LM runs Gauss-Newton steps on the
  linearised decoder, and the next keyframe's optimisation relinearises exactly). ``relin_threshold=0``
  evaluates the network at every new code LM tries (exact, about 8x more decoder runs). The approximation's
  error is measured with ``measure_approx_error`` (one extra decode at the final code of each optimisation,
  ``approx_error_mean_m`` / ``approx_error_max_m`` in ``metrics.json``). Measured on a 10 s textured sequence
  at 376x240 (shipped model, 21 keyframes): once per optimisation (the default) 163 decoder runs, mean |error|
  2.3 cm, max 0.50 m at the final codes; ``relin_threshold=0.5``: 650 runs, mean 0.8 mm, max 0.11 m, the same
  optimised-code depth RMSE (0.279 vs 0.276 m) and 4x the time; ``0.05``: 824 runs, mean 0.002 mm, max 2.7 mm.
  The exact decoder is always used for the outputs and the depth metrics. Observed: the codes move by 1-3
  units from one optimisation to the next (the window's landmarks change and the code directions are weakly
  determined), so relinearising at every build is needed; ``build_relin_threshold`` > 0 saved nothing there.
* **Coast bridge** (:meth:`DenseMapper.bridge_factors`, ``bridge_span`` > 0): when a relocalisation
  re-estimates a coasted stretch (:meth:`runtime.backend.graph.SlidingWindowBackend.bridge`), Eq. 14 factors on
  the keyframes' final depth maps (codes fixed) join the IMU links; marginalised keyframes keep their final
  depth and uncertainty maps (float32) as long as the backend keeps their states. Off by default: on a blank
  wall the network's depth is a guess that does not follow the distance (``docs/PITFALLS.md``).
* **Outputs** (:meth:`DenseMapper.finish`): ``dense_map.ply`` (the window's keyframes' decoded depths,
  uncertainty-filtered and fused, :func:`runtime.dense_map.fuse_depth_maps`), per-keyframe depth and
  uncertainty maps in ``keyframe_depth/``, and with ground-truth depth (``mav0/depth0``) the Table 2 metrics
  of (a) the sparse map points, (b) the prior at c = 0, (c) the optimised code, on every keyframe that held a
  code, each evaluated when the keyframe left the window (or at the end).

This module never imports torch.
"""

from __future__ import annotations

import logging
import time
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from runtime.backend.depth_factors import (
    DepthFactorConfig,
    make_consistency_factor,
    make_geometric_depth_factors,
)
from runtime.dense_map import (
    DenseMapConfig,
    depth_metrics,
    fuse_depth_maps,
    gt_depth_to_network,
    mean_metrics,
    save_keyframe_maps,
    sparse_depth_image,
    write_dense_map,
)
from runtime.geometry import Camera, NetworkMapping, inv_T
from runtime.sampling import sample_consistency_pixels

log = logging.getLogger(__name__)


@dataclass
class DenseConfig:
    """Settings of the dense (tightly coupled) system (Hydra ``dense_settings`` in ``conf/slam.yaml``).

    Attributes:
        n_code_keyframes: keyframes of the window with a depth code (the newest + its most co-visible ones).
        use_depth_residual: Eq. 13 factors.
        use_consistency: Eq. 14 factors.
        n_consis: ``N_consis``, Eq. 14 samples per keyframe pair (Sec. 5.2 sampler).
        code_prior_sigma: sigma of the ``N(0, I)`` code prior (1: the CVAE prior).
        build_relin_threshold: when the factors are built, relinearise a code keyframe's decoder only when
            its code moved more than this from the last linearisation point (0: whenever it moved).
        relin_threshold: during LM, relinearise the decoder only when a code moved more than this from
            the code the factors were built at (norm, code units); 0: exact (the network runs at every new
            code).
        measure_approx_error: decode the final codes once more to measure the approximation's error.
        geo_eff_rows, consis_eff_rows: effective independent rows of one keyframe's Eq. 13 rows and of one
            pair's Eq. 14 rows (:class:`runtime.backend.depth_factors.DepthFactorConfig`; None: independent).
        start_after_s: seconds after the first keyframe (the initialisation) before codes and depth factors
            join the window's optimisations (0: from the first one); a re-initialisation after a reset
            waits again. While the visual-inertial scale and gravity are still converging, a biased depth
            network pulls them, and that early error stays in the trajectory (marginalised keyframes are not
            revisited); the network's sparse-depth input, the map points at their current scale, is least
            reliable then too. Chosen on seeds 0-4 of the 60 s
            sequences (AMD EPYC, with ``edge_rel=0.05``), mean ATE textured / whitewall: 0 s 4.94 / 8.94 mm,
            5 s 4.08 / 7.32 mm, 10 s 4.32 / 7.64 mm (sparse 4.29 / 7.38 mm); with 0 s the largest excess over
            sparse was in the first 5 s of the trajectory (seed 4 textured: 14.9 against 7.2 mm there).
        fill_recent: when fewer than ``n_code_keyframes`` keyframes are co-visible with the newest (visual
            tracking lost on a textureless stretch), fill the code keyframes with the most recent ones.
        bridge_span: the relocalisation's coast bridge (:meth:`runtime.backend.graph.SlidingWindowBackend.bridge`)
            gets Eq. 14 factors between each keyframe of the bridged stretch and its next ``bridge_span`` ones,
            on their final depth maps (codes fixed; the depth maps of marginalised keyframes are kept as long
            as their states, ``backend.archive_s``); 0: the bridge is inertial only.
        depth_source: ``"network"``, or ``"ground_truth"``: a diagnostic upper bound (needs ``mav0/depth0``),
            where a keyframe's depth is the rendered depth plus the network's code-dependent part,
            ``D(c) = D_gt + D_net(c) - D_net(0)`` (so the codes and the code Jacobian are the network's), with
            the uncertainty ``oracle_b`` everywhere; it tells what a perfect depth network would buy.
        oracle_b: Laplace scale ``B`` [m] of the ground-truth depth source.
        consis_poses: Eq. 14 acts on the poses and the codes of a pair (the paper); False: on the codes only,
            the poses held at the window's estimates when the factors are built (a diagnostic: does Eq. 14
            move the trajectory through the poses or through the depth maps).
        consis_offset: an Eq. 14 pair's common depth offset is a nuisance, eliminated from its rows
            (:class:`runtime.backend.depth_factors.DepthFactorConfig`): the pair constrains the shape its two
            maps agree on, not their absolute depth.
        geo_fixed_landmarks: Eq. 13 with the landmarks held at their current estimates (keys ``X(k), C(k)``,
            the "fixed sparse map points" variant); False: the landmarks are variables too.
        sigma_per_b: row sigma per unit of the predicted Laplace scale ``B``. The Laplace value is
            ``sqrt(2)``; the default is 8x that. Measured on the 60 s sequences (frames every 2 s, c = 0 and
            a code fitted to 150 true sparse depths), the shipped model's ``B`` is calibrated on average
            (mean |error| / mean ``B``: 0.7-0.8 textured, 1.0-1.3 whitewall), but a depth map's errors are
            one smooth field, so hundreds of rows on a map are worth a handful of independent ones; treated
            as independent they pull the trajectory. ATE, 60 s, seed 0 whitewall / mean of seeds 0-2
            textured: 4x ``sqrt(2)`` 0.118 m / 0.0056 m, 8x 0.037 m / 0.0043 m (sparse 0.028 m / 0.0043 m).
            ``geo_eff_rows`` / ``consis_eff_rows`` scale by the row count instead. With ``edge_rel`` and
            ``start_after_s`` in place, 4x ``sqrt(2)`` gave better optimised depth on every run but no
            consistent ATE change over 8 seeds (``benchmarks/results/dense_ablations/``).
        min_sigma, geo_huber_k, consis_huber_k, chunk_size, edge_rel: depth factor settings
            (:class:`runtime.backend.depth_factors.DepthFactorConfig`; ``edge_rel``: rows on a depth edge of
            the decoded map are not used; 0.05 was chosen from the rendered depth at the true poses, where
            it removes the Eq. 14 rows off by decimetres, not by ATE; with the rendered depth and Eq. 14 alone
            it took textured seeds 0-4 from 6.07 to 3.96 mm, sparse 3.95 mm, on an Intel Xeon).
        max_rel_uncertainty, voxel, max_depth: dense map filter (:class:`runtime.dense_map.DenseMapConfig`).
        save_maps: write per-keyframe depth / uncertainty maps.
        seed: sampler seed (combined with the keyframe id).
    """

    n_code_keyframes: int = 5
    use_depth_residual: bool = True
    use_consistency: bool = True
    n_consis: int = 300
    code_prior_sigma: float = 1.0
    relin_threshold: float = 1.0e6
    build_relin_threshold: float = 0.0
    measure_approx_error: bool = False
    sigma_per_b: float = float(8.0 * np.sqrt(2.0))
    min_sigma: float = 0.02
    geo_huber_k: float = 1.5
    consis_huber_k: float = 1.5
    chunk_size: int = 32
    geo_eff_rows: float | None = None
    consis_eff_rows: float | None = None
    edge_rel: float | None = 0.05
    start_after_s: float = 5.0
    fill_recent: bool = False
    bridge_span: int = 0
    depth_source: str = "network"
    oracle_b: float = 0.02
    geo_fixed_landmarks: bool = False
    consis_poses: bool = True
    consis_offset: bool = False
    max_rel_uncertainty: float = 0.1
    voxel: float = 0.02
    max_depth: float = 10.0
    save_maps: bool = True
    seed: int = 0

    def __post_init__(self) -> None:
        if self.n_code_keyframes < 1:
            raise ValueError(f"n_code_keyframes={self.n_code_keyframes}: must be >= 1")
        if self.bridge_span < 0:
            raise ValueError(f"bridge_span={self.bridge_span}: must be >= 0")
        if not self.start_after_s >= 0:
            raise ValueError(f"start_after_s={self.start_after_s}: must be >= 0")
        if self.n_consis < 1:
            raise ValueError(f"n_consis={self.n_consis}: must be >= 1")
        if self.relin_threshold < 0:
            raise ValueError(f"relin_threshold={self.relin_threshold}: must be >= 0")
        if not self.code_prior_sigma > 0:
            raise ValueError(f"code_prior_sigma={self.code_prior_sigma}: must be > 0")
        if self.depth_source not in ("network", "ground_truth"):
            raise ValueError(f"depth_source={self.depth_source!r}: expected 'network' or 'ground_truth'")
        if not self.oracle_b > 0:
            raise ValueError(f"oracle_b={self.oracle_b}: must be > 0")

    @classmethod
    def from_dict(cls, d: dict | None) -> DenseConfig:
        """Build from a mapping; unknown keys raise naming the key."""
        from runtime.slam import _dataclass_from_dict

        return _dataclass_from_dict(cls, d or {}, "dense_settings")

    def factor_config(self) -> DepthFactorConfig:
        return DepthFactorConfig(
            sigma_per_b=self.sigma_per_b,
            min_sigma=self.min_sigma,
            geo_huber_k=self.geo_huber_k,
            consis_huber_k=self.consis_huber_k,
            chunk_size=self.chunk_size,
            check_shapes=False,
            geo_eff_rows=self.geo_eff_rows,
            consis_eff_rows=self.consis_eff_rows,
            edge_rel=self.edge_rel,
            consis_offset=self.consis_offset,
        )


class LinearizedDepth:
    """A keyframe's depth provider with the decoder relinearised only when the code moved (see module doc).

    Wraps :class:`runtime.network.KeyframeDepth` (``uncertainty``, ``net``, ``depth``, ``jacobian``).
    """

    def __init__(self, kd, threshold: float) -> None:
        self.kd = kd
        self.net = kd.net
        self.code_dim = kd.net.code_dim
        self.uncertainty = kd.uncertainty
        self.threshold = float(threshold)
        self.c0: np.ndarray | None = None
        self.D0: np.ndarray | None = None
        self.J0: np.ndarray | None = None
        self.n_relin = 0

    def _relin(self, code: np.ndarray) -> None:
        self.D0, self.J0 = self.kd.jacobian(code)
        self.D0 = self.D0.astype(np.float64)
        self.J0 = self.J0.astype(np.float64)
        self.c0 = np.asarray(code, np.float32).astype(np.float64)
        self.n_relin += 1

    def _near(self, code: np.ndarray) -> bool:
        if self.c0 is None:
            return False
        d = float(np.linalg.norm(np.asarray(code, np.float64) - self.c0))
        return d == 0.0 or d <= self.threshold

    def jacobian(self, code: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if not self._near(code):
            self._relin(code)
        dc = np.asarray(code, np.float64) - self.c0
        if not dc.any():
            return self.D0, self.J0
        return self.D0 + self.J0 @ dc, self.J0

    def depth(self, code: np.ndarray) -> np.ndarray:
        return self.jacobian(code)[0]

    def relinearize(self, code: np.ndarray, threshold: float = 0.0) -> None:
        """Exact decoder and Jacobian at ``code`` unless it is within ``threshold`` (norm) of the current
        linearisation point (0: unless it is that point)."""
        c = np.asarray(code, np.float32).astype(np.float64)
        if (
            self.c0 is None
            or float(np.linalg.norm(c - self.c0)) > threshold
            or not (threshold > 0 or np.array_equal(c, self.c0))
        ):
            self._relin(code)

    def exact(self, code: np.ndarray) -> np.ndarray:
        return self.kd.depth(code)


class GroundTruthDepth:
    """A keyframe's depth with the rendered ground truth in place of the prior (``depth_source="ground_truth"``).

    ``D(c) = D_gt + D_net(c) - D_net(0)`` where ``D_gt`` is valid (the network's depth elsewhere), the network's
    code Jacobian, uncertainty ``b`` everywhere. Same interface as :class:`runtime.network.KeyframeDepth`.
    """

    def __init__(self, kd, gt_net: np.ndarray, b: float) -> None:
        self.kd = kd
        self.net = kd.net
        d0 = np.asarray(kd.depth(np.zeros(kd.net.code_dim)), np.float64)
        gt = np.asarray(gt_net, np.float64)
        if gt.shape != d0.shape:
            raise ValueError(f"ground-truth depth {gt.shape} does not match the network's {d0.shape}")
        self.offset = np.where(gt > 0, gt - d0, 0.0)
        self.uncertainty = np.full(np.shape(kd.uncertainty), b, np.float32)

    def depth(self, code: np.ndarray) -> np.ndarray:
        return np.asarray(self.kd.depth(code), np.float64) + self.offset

    def jacobian(self, code: np.ndarray, delta: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        d, J = self.kd.jacobian(code) if delta is None else self.kd.jacobian(code, delta)
        return np.asarray(d, np.float64) + self.offset, J


@dataclass
class _KfDense:
    kf_id: int
    frame_idx: int
    provider: LinearizedDepth
    feat_uv: np.ndarray  # (F, 2) network pixels of the keyframe's tracked features
    image: np.ndarray  # (H, W) uint8 grey at network size
    code: np.ndarray  # (C,) current code
    had_code: bool = False
    evaluated: bool = False


@dataclass
class _FixedDepth:
    """A keyframe's final depth map, kept for the coast bridge (a depth provider whose code is fixed)."""

    depth_map: np.ndarray  # (H, W) float32 [m]
    uncertainty: np.ndarray  # (H, W) float32 Laplace scale [m]
    feat_uv: np.ndarray  # (F, 2) network pixels of the keyframe's tracked features

    def depth(self, code=None) -> np.ndarray:
        return self.depth_map.astype(np.float64)


@dataclass
class _Stats:
    n_optim: int = 0
    n_skipped: int = 0  # optimisations before start_after_s
    n_bridge_factors: int = 0
    n_code_kfs: list = field(default_factory=list)
    n_geo_rows: list = field(default_factory=list)
    n_consis_rows: list = field(default_factory=list)
    approx_err_mean: list = field(default_factory=list)
    approx_err_max: list = field(default_factory=list)


class DenseMapper:
    """Depth codes ``C(k)``, Eq. 13-14 factors and the local dense map (module doc).

    Args:
        net: :class:`runtime.network.DepthNetwork` (``grays`` or ``gray`` modality).
        camera: raw cam0 model (distorted); images are undistorted with it.
        T_b_c: (4, 4) cam0-to-body.
        cfg: settings.
        depth_gt: optional ``frame_idx -> (H, W) metres or None`` (ground truth on cam0's grid).
        timers: dict to accumulate seconds in (``dense_network``, ``dense_factors``); the optimisation's
            time is in the system's ``optimize`` timer.
    """

    def __init__(
        self,
        net,
        camera: Camera,
        T_b_c: np.ndarray,
        cfg: DenseConfig | None = None,
        depth_gt=None,
        timers: dict | None = None,
    ) -> None:
        self.cfg = cfg or DenseConfig()
        self.net = net
        self.camera = camera
        self.T_b_c = np.asarray(T_b_c, np.float64)
        self.T_c_b = inv_T(self.T_b_c)
        self.mapping = NetworkMapping.fit(camera.width, camera.height, net.width, net.height)
        self.net_cam = self.mapping.camera(camera.pinhole())
        self.K_net = self.net_cam.intrinsics
        self.fcfg = self.cfg.factor_config()
        self.depth_gt = depth_gt
        if self.cfg.depth_source == "ground_truth" and depth_gt is None:
            raise ValueError("depth_source='ground_truth' needs a sequence with ground-truth depth (mav0/depth0)")
        self.timers = timers if timers is not None else defaultdict(float)
        self.kfs: dict[int, _KfDense] = {}
        self.code_kfs: list[int] = []
        self.per_kf_metrics: dict[int, dict] = {}
        self.archive: dict[int, _FixedDepth] = {}  # marginalised keyframes' final depths (coast bridge)
        self.stats = _Stats()
        self.t_first_ns: int | None = None  # the window's first keyframe's time (start_after_s counts from it)
        self.armed_for: int | None = None  # the backend's init_kf_id that t_first_ns belongs to
        self.dense_map: tuple[np.ndarray, np.ndarray | None] | None = None  # (xyz, rgb) once finish() ran

    # ------------------------------------------------------------------ keyframes
    def on_keyframe(self, backend, kf_id: int, frame_idx: int, image: np.ndarray, feat_uv_u: np.ndarray) -> None:
        """Run the network prior for a new keyframe.

        Args:
            backend: the :class:`SlidingWindowBackend` (the keyframe and its observations are in it).
            kf_id, frame_idx: the keyframe.
            image: (H, W) uint8 distorted cam0 image.
            feat_uv_u: (F, 2) undistorted pixels of the keyframe's tracked features (for the sampler).
        """
        t0 = time.perf_counter()
        self._arm_start(backend, kf_id)
        for k in [k for k in self.kfs if k not in backend.keyframes]:  # a reset cleared the window
            del self.kfs[k]
        und = self.camera.undistort_image(image)
        img_net = self.mapping.image_to_network(und)
        sparse = None
        if self.net.uses_sparse:
            uv, z = self._observed_points(backend, kf_id)
            sparse = sparse_depth_image(self.mapping.points_to_network(uv), z, (self.net.height, self.net.width))
        kd = self.net.prior(img_net, sparse)
        if self.cfg.depth_source == "ground_truth":
            gt = self.depth_gt(frame_idx) if self.depth_gt is not None else None
            if gt is None:
                raise ValueError(f"depth_source='ground_truth' but frame {frame_idx} has no ground-truth depth")
            kd = GroundTruthDepth(kd, gt_depth_to_network(gt, self.camera, self.mapping), self.cfg.oracle_b)
        C = self.net.code_dim
        feat = self.mapping.points_to_network(np.asarray(feat_uv_u, np.float64).reshape(-1, 2))
        self.kfs[kf_id] = _KfDense(
            kf_id, frame_idx, LinearizedDepth(kd, self.cfg.relin_threshold), feat, img_net, np.zeros(C)
        )
        self.timers["dense_network"] += time.perf_counter() - t0

    def _observed_points(self, backend, kf_id: int) -> tuple[np.ndarray, np.ndarray]:
        """Undistorted pixels (N, 2) and depths (N,) of the valid landmarks observed by ``kf_id``, projected
        with their current positions."""
        kf = backend.keyframes[kf_id]
        ids = [
            j for j in backend.kf_obs.get(kf_id, ()) if j in backend.landmarks and len(backend.landmarks[j].obs) >= 2
        ]
        if not ids:
            return np.zeros((0, 2)), np.zeros(0)
        X = np.array([backend.landmarks[j].X_w for j in ids])
        T_c_w = self.T_c_b @ inv_T(kf.T_w_b)
        p = X @ T_c_w[:3, :3].T + T_c_w[:3, 3]
        z = p[:, 2]
        ok = z > 0.05
        p, z = p[ok], z[ok]
        fx, fy, cx, cy = self.camera.intrinsics
        uv = np.stack([fx * p[:, 0] / z + cx, fy * p[:, 1] / z + cy], -1)
        return uv, z

    # ------------------------------------------------------------------ FactorProvider
    def _select(self, backend) -> list[int]:
        newest = backend.active[-1]
        cand = [newest] + backend.covisible_keyframes(newest, len(backend.active))
        out = [k for k in cand if k in self.kfs][: self.cfg.n_code_keyframes]
        if self.cfg.fill_recent and len(out) < self.cfg.n_code_keyframes:
            # too few co-visible keyframes (textureless stretch, visual tracking lost): the most recent ones
            # overlap the newest by motion continuity
            for k in reversed(backend.active):
                if len(out) >= self.cfg.n_code_keyframes:
                    break
                if k in self.kfs and k not in out:
                    out.append(k)
        return out

    def _arm_start(self, backend, kf_id: int) -> None:
        """Start the ``start_after_s`` wait at ``kf_id`` when it is the first keyframe after an initialisation
        (the first of the run, or a re-initialisation after a reset: the backend's ``init_kf_id`` changed)."""
        init_id = getattr(backend, "init_kf_id", None)
        if self.t_first_ns is None or init_id != self.armed_for:
            self.t_first_ns = int(backend.keyframes[kf_id].ts)
            self.armed_for = init_id

    def _started(self, backend) -> bool:
        newest = backend.keyframes[backend.active[-1]]
        return self.t_first_ns is not None and (newest.ts - self.t_first_ns) * 1e-9 >= self.cfg.start_after_s

    def add_factors(self, backend, graph, values) -> None:
        import gtsam
        from gtsam.symbol_shorthand import C, L, X

        t0 = time.perf_counter()
        cfg = self.cfg
        if cfg.start_after_s > 0 and not self._started(backend):
            self.code_kfs = []
            self.stats.n_skipped += 1
            return
        self.code_kfs = sel = self._select(backend)
        Cd = self.net.code_dim
        prior_noise = gtsam.noiseModel.Isotropic.Sigma(Cd, cfg.code_prior_sigma)
        n_geo = n_con = 0
        for k in sel:
            d = self.kfs[k]
            d.had_code = True
            d.provider.relinearize(d.code, cfg.build_relin_threshold)
            values.insert(C(k), np.asarray(d.code, np.float64))
            graph.push_back(gtsam.PriorFactorVector(C(k), np.zeros(Cd), prior_noise))
            if cfg.use_depth_residual:
                ids, uv = [], []
                for j in backend.kf_obs.get(k, ()):
                    lm = backend.landmarks.get(j)
                    if lm is None or k not in lm.obs or not values.exists(L(j)):
                        continue
                    ids.append(j)
                    uv.append(lm.obs[k])
                if ids:
                    uvn = self.mapping.points_to_network(np.array(uv))
                    if cfg.geo_fixed_landmarks:
                        where = {"landmarks_w": np.array([backend.landmarks[j].X_w for j in ids])}
                    else:
                        where = {"landmark_keys": [L(j) for j in ids]}
                    if cfg.edge_rel is not None:
                        where["depth_map"] = d.provider.depth(d.code)
                    facs = make_geometric_depth_factors(X(k), C(k), uvn, d.provider, self.T_b_c, cfg=self.fcfg, **where)
                    for f in facs:
                        graph.push_back(f)
                        n_geo += f.dim()
        if cfg.use_consistency and len(sel) >= 2:
            k1 = sel[0]
            d1 = self.kfs[k1]
            for k2 in sel[1:]:
                d2 = self.kfs[k2]
                f = self._consistency_factor(
                    (k1, k2),
                    (d1.provider, d2.provider),
                    d2.feat_uv,
                    (backend.keyframes[k1].T_w_b, backend.keyframes[k2].T_w_b),
                    (d1.code, d2.code),
                )
                if f is not None:
                    graph.push_back(f)
                    n_con += f.dim()
        self.stats.n_optim += 1
        self.stats.n_code_kfs.append(len(sel))
        self.stats.n_geo_rows.append(n_geo)
        self.stats.n_consis_rows.append(n_con)
        self.timers["dense_factors"] += time.perf_counter() - t0

    def _consistency_factor(self, kfs, providers, feat_uv2, poses, codes=None):
        """Eq. 14 factor of the pair ``kfs = (k1, k2)`` on the Sec. 5.2 samples of k2 (``feat_uv2``: its
        features), at ``poses`` (``T_w_b``); ``codes`` None: fixed depth maps (pose keys only). None when no
        sample is usable."""
        from gtsam.symbol_shorthand import C, X

        k1, k2 = kfs
        rng = np.random.default_rng([self.cfg.seed, k1, k2])
        s = sample_consistency_pixels(feat_uv2, self.net.width, self.net.height, self.cfg.n_consis, rng=rng, margin=2)
        try:
            return make_consistency_factor(
                (X(k1), X(k2)) if codes is None or self.cfg.consis_poses else None,
                None if codes is None else (C(k1), C(k2)),
                providers,
                s.uv,
                self.K_net,
                self.T_b_c,
                poses,
                (None, None) if codes is None else codes,
                self.fcfg,
            )
        except ValueError as e:
            log.info("dense: no consistency factor %d-%d (%s)", k1, k2, e)
            return None

    def on_optimized(self, backend, result) -> None:
        from gtsam.symbol_shorthand import C

        for k in self.code_kfs:
            if result.exists(C(k)):
                self.kfs[k].code = np.asarray(result.atVector(C(k)), np.float64).copy()
        if self.cfg.measure_approx_error:
            t0 = time.perf_counter()
            errs = []
            for k in self.code_kfs:
                d = self.kfs[k]
                approx = d.provider.depth(d.code)
                errs.append(np.abs(approx - d.provider.exact(d.code)))
            if errs:
                e = np.concatenate([x.ravel() for x in errs])
                self.stats.approx_err_mean.append(float(e.mean()))
                self.stats.approx_err_max.append(float(e.max()))
            self.timers["dense_approx_check"] += time.perf_counter() - t0

    def on_marginalize(self, backend, kf_id: int) -> None:
        """A keyframe leaves the window: evaluate its depth (final code), free its network state."""
        d = self.kfs.get(kf_id)
        if d is None:
            return
        self._evaluate(backend, d)
        if self.cfg.bridge_span > 0:
            for k in [k for k in self.archive if k not in backend.archived_states]:
                del self.archive[k]
            self.archive[kf_id] = self._fixed(d)
        del self.kfs[kf_id]

    def _fixed(self, d: _KfDense) -> _FixedDepth:
        return _FixedDepth(
            self.final_depth(d).astype(np.float32), np.asarray(d.provider.uncertainty, np.float32), d.feat_uv
        )

    def bridge_factors(self, backend, poses: dict[int, np.ndarray]) -> list:
        """Eq. 14 factors on the poses of a coast bridge: each keyframe of ``poses`` (``kf_id -> T_w_b``, the
        bridge's start values) with its next ``bridge_span`` ones, on fixed final depth maps (samples by the
        Sec. 5.2 strategy in the older keyframe). With depth maps that follow the surface they hold the
        distance to it and the tilt against it on a textureless stretch, which the IMU alone lets drift (the
        shipped network's do not on a blank wall: module doc)."""
        if self.cfg.bridge_span <= 0:
            return []
        t0 = time.perf_counter()
        maps = {}
        for k in sorted(poses):
            if k in self.kfs:
                maps[k] = self._fixed(self.kfs[k])
            elif k in self.archive:
                maps[k] = self.archive[k]
        ks = list(maps)
        out = []
        for i, k2 in enumerate(ks):
            for k1 in ks[i + 1 : i + 1 + self.cfg.bridge_span]:
                f = self._consistency_factor((k1, k2), (maps[k1], maps[k2]), maps[k2].feat_uv, (poses[k1], poses[k2]))
                if f is not None:
                    out.append(f)
        self.stats.n_bridge_factors += len(out)
        self.timers["dense_factors"] += time.perf_counter() - t0
        return out

    # ------------------------------------------------------------------ evaluation and outputs
    def final_depth(self, d: _KfDense) -> np.ndarray:
        return np.asarray(d.provider.exact(d.code), np.float64)

    def _evaluate(self, backend, d: _KfDense) -> None:
        if d.evaluated or not d.had_code or self.depth_gt is None:
            return
        d.evaluated = True
        gt = self.depth_gt(d.frame_idx)
        if gt is None:
            return
        gt_net = gt_depth_to_network(gt, self.camera, self.mapping)
        uv, z = self._observed_points(backend, d.kf_id)
        sp = sparse_depth_image(self.mapping.points_to_network(uv), z, gt_net.shape)
        C = self.net.code_dim
        self.per_kf_metrics[d.kf_id] = {
            "sparse": depth_metrics(sp, gt_net) if (sp > 0).any() and (gt_net[sp > 0] > 0).any() else None,
            "prior": depth_metrics(np.asarray(d.provider.exact(np.zeros(C)), np.float64), gt_net),
            "optimised": depth_metrics(self.final_depth(d), gt_net),
        }

    def finish(self, backend, out_dir: str | Path) -> dict:
        """Write ``dense_map.ply`` and per-keyframe maps; return the dense metrics for ``metrics.json``."""
        out = Path(out_dir)
        active = [k for k in backend.active if k in self.kfs]
        for k in active:
            self._evaluate(backend, self.kfs[k])
        depths, poses, uncs, imgs = [], [], [], []
        for k in active:
            d = self.kfs[k]
            depth = self.final_depth(d)
            depths.append(depth)
            poses.append(backend.keyframes[k].T_w_b)
            uncs.append(d.provider.uncertainty)
            imgs.append(d.image)
            if self.cfg.save_maps:
                save_keyframe_maps(out / "keyframe_depth", f"kf{k:05d}", depth, d.provider.uncertainty)
        mcfg = DenseMapConfig(
            max_rel_uncertainty=self.cfg.max_rel_uncertainty,
            voxel=self.cfg.voxel,
            max_depth=self.cfg.max_depth,
        )
        xyz, rgb = fuse_depth_maps(depths, poses, self.net_cam, self.T_b_c, uncs, imgs, mcfg)
        write_dense_map(out / "dense_map.ply", xyz, rgb)
        self.dense_map = (xyz, rgb)  # for the Rerun recording
        st = self.stats
        res = {
            "dense_map_points": int(xyz.shape[0]),
            "dense_window_keyframes": len(active),
            "dense_optimisations": st.n_optim,
            "dense_optimisations_before_start": st.n_skipped,
            "dense_mean_code_keyframes": float(np.mean(st.n_code_kfs)) if st.n_code_kfs else 0.0,
            "dense_mean_geo_rows": float(np.mean(st.n_geo_rows)) if st.n_geo_rows else 0.0,
            "dense_mean_consis_rows": float(np.mean(st.n_consis_rows)) if st.n_consis_rows else 0.0,
            "dense_bridge_factors": st.n_bridge_factors,
            "decoder_calls": int(self.net.decoder_calls),
            "dense_config": {k: getattr(self.cfg, k) for k in self.cfg.__dataclass_fields__},
        }
        if st.approx_err_mean:
            res["approx_error_mean_m"] = float(np.mean(st.approx_err_mean))
            res["approx_error_max_m"] = float(np.max(st.approx_err_max))
        if self.per_kf_metrics:
            res["depth_metrics"] = {
                stage: mean_metrics([m[stage] for m in self.per_kf_metrics.values() if m[stage] is not None])
                for stage in ("sparse", "prior", "optimised")
            }
            res["depth_metrics_keyframes"] = len(self.per_kf_metrics)
            res["depth_metrics_unit"] = "m (RMSE, MAE), 1/m (iRMSE)"
        return res
