"""Tight coupling of the depth network with the sliding window (Sec. 3.3, 5.2-5.3, Eq. 2, 13-17).

:class:`DenseMapper` is a :class:`runtime.backend.graph.FactorProvider` registered with the backend when
``dit-slam dense=true``. It reads the window only through the backend's public read interface
(``window_ids``, ``has_keyframe``, ``keyframe``, ``observations``, ``covisible_keyframes``, ``latest``,
``init_kf_id``).

* **Network in the loop** (:meth:`DenseMapper.on_keyframe`): for each new keyframe the cam0 image is
  undistorted, mapped to the network size (``NetworkMapping``), and the sparse depth image of the map points
  the keyframe observes (projected with their current metric depth) is the ``grays`` sparse channel;
  ``prior.onnx`` runs once per keyframe, and the decoder is linearised at c = 0. With
  ``DenseConfig.background`` (the default) that network pass runs in a background thread while tracking goes on
  (ONNX Runtime releases the GIL), and the keyframe's code joins from the next keyframe's optimisation. The
  depth source (default: the network's prior as it is) may wrap it, e.g.
  :func:`runtime.diagnostics.oracle_depth.oracle_depth_source`.
* **Depth codes** (:meth:`DenseMapper.add_factors`, called by the backend before each LM run): ``C(k)`` in
  R^C for the newest keyframe and its ``n_code_keyframes - 1`` most co-visible active keyframes (Sec. 5.3,
  "five most co-visible keyframes"), each with the CVAE prior ``N(0, I)`` (``PriorFactorVector``); Eq. 13
  factors per code keyframe (landmarks as variables); Eq. 14 factors from the newest code keyframe to every
  other code keyframe on the Sec. 5.2 samples (``n_consis`` per keyframe). Factors are rebuilt at every
  optimisation (their noise models are evaluated at the current estimate). After an optimisation, a code
  keyframe whose code moved more than ``DenseConfig.relin_tol`` has its decoder relinearised at the new code on
  the network thread, for the next optimisation (:class:`runtime.dense.linearized.LinearizedDepth`).
* **Outputs** (:meth:`DenseMapper.finish`): ``dense_map.ply`` (the run's fused map,
  :class:`runtime.dense.fusion.VoxelMap`: every keyframe's decoded depth (those with
  ``min_sparse_points`` in the network input), uncertainty-filtered and weighted by
  ``1 / B^2``, integrated once when it leaves the window with its map code and final pose, and at the end for
  the keyframes still in the window; points with normals and colours), ``dense_mesh.ply`` (with
  ``DenseMapConfig.mesh``: the same keyframes integrated on the network thread, right after the point map, into
  a :class:`runtime.dense.tsdf.TsdfVolume`, whose surface is extracted at the end; 69-116 ms a keyframe there,
  overlapping tracking, where integrating at the end would add 7-12 s to a 30 s run and keep every keyframe's
  depth until then), per-keyframe depth and
  uncertainty maps in ``keyframe_depth/``, and with ground-truth depth (``mav0/depth0``) the Table 2 metrics
  of (a) the sparse map points, (b) the prior at c = 0, (c) the optimised code (the window's), (d) the map code,
  on every keyframe that held a code, each evaluated when the keyframe left the window (or at the end).
* **Map codes** (:meth:`DenseMapper._refine`, ``DenseConfig.map_codes``): when a keyframe leaves the window (and
  at the end), its code and those of its most co-visible keyframes are fitted jointly to Eq. 14 at the window's
  poses (:mod:`runtime.dense.refine`, on the network thread); the keyframe keeps its fitted code as its map code
  for the outputs above. The window's codes and poses never see it.

This module never imports torch.
"""

from __future__ import annotations

import copy
import dataclasses
import logging
import time
from collections import defaultdict
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from runtime.dense.config import DenseConfig
from runtime.dense.factors import make_consistency_factor, make_geometric_depth_factors
from runtime.dense.fusion import VoxelMap, write_fused_map
from runtime.dense.linearized import ApproxErrorProbe, LinearizedDepth
from runtime.dense.map import (
    depth_metrics,
    gt_depth_to_network,
    mean_metrics,
    sparse_depth_image,
    write_keyframe_maps,
)
from runtime.dense.refine import refine_codes
from runtime.dense.sampling import sample_consistency_pixels
from runtime.dense.tsdf import TsdfVolume, write_mesh_ply
from runtime.dense.worker import PriorityWorker
from runtime.geometry import Camera, NetworkMapping, inv_T, project_pinhole

__all__ = ["DepthSource", "network_depth", "DenseMapper"]

log = logging.getLogger(__name__)

#: Where a keyframe's depth comes from: ``source(kd, frame_idx, camera, mapping) -> provider``, given the
#: network's :class:`runtime.network.KeyframeDepth` ``kd`` of the keyframe, the raw cam0 model and the
#: mapping to network pixels; the provider has ``kd``'s interface (``net``, ``uncertainty``, ``depth``,
#: ``jacobian``).
DepthSource = Callable[[object, int, Camera, NetworkMapping], object]

#: Smallest camera depth [m] of a map point projected into the network's sparse-depth input.
MIN_POINT_DEPTH = 0.05


def network_depth(kd, frame_idx: int, camera: Camera, mapping: NetworkMapping):
    """The default :data:`DepthSource`: the network's prior as it is."""
    return kd


@dataclass
class _KfDense:
    kf_id: int
    frame_idx: int
    job: Future  # -> LinearizedDepth: the network pass (prior, decoder linearised at c = 0)
    feat_uv: np.ndarray  # (F, 2) network pixels of the keyframe's tracked features
    image: np.ndarray  # (H, W) uint8 grey at network size
    code: np.ndarray  # (C,) current code
    had_code: bool = False
    evaluated: bool = False
    fused: bool = False  # integrated into the fused map
    relin: Future | None = None  # the relinearisation submitted after the last optimisation
    lin_code: np.ndarray | None = None  # where the decoder is (or is being) linearised; None: c = 0
    n_sparse: int = -1  # map points in the network's sparse input (-1: the network takes none)
    sparse_points: tuple | None = None  # (uv, z): network pixels and depths of that input's map points
    map_code: Future | None = None  # -> (C,) the code refined at fixed poses for the map (None: the window's)

    @property
    def provider(self) -> LinearizedDepth:
        """The keyframe's depth provider (waits for its network pass; re-raises its error)."""
        return self.job.result()


@dataclass
class _Stats:
    n_optim: int = 0
    n_skipped: int = 0  # optimisations before start_after_s
    n_code_kfs: list = field(default_factory=list)
    n_geo_rows: list = field(default_factory=list)
    n_consis_rows: list = field(default_factory=list)
    n_sparse: list = field(default_factory=list)  # map points in each keyframe's network input


class DenseMapper:
    """Depth codes ``C(k)``, Eq. 13-14 factors and the local dense map (module doc).

    Args:
        net: :class:`runtime.network.DepthNetwork` (``grays`` or ``gray`` modality).
        camera: raw cam0 model (distorted); images are undistorted with it.
        T_b_c: (4, 4) cam0-to-body.
        cfg: settings.
        depth_gt: optional ``frame_idx -> (H, W) metres or None`` (ground truth on cam0's grid), for the depth
            metrics.
        timers: dict to accumulate seconds in (``dense_network``, ``dense_factors``); the optimisation's
            time is in the system's ``optimize`` timer.
        depth_source: :data:`DepthSource` of the keyframes' depth (None: :func:`network_depth`).
        probe: optional :class:`runtime.dense.linearized.ApproxErrorProbe`, called after each optimisation.
    """

    later_peak: int = 0  # most later-work jobs waiting at once on the network thread (metrics.json)
    later_at_drain: int | None = None  # later-work jobs waiting when drain() was called (after the last frame)

    def __init__(
        self,
        net,
        camera: Camera,
        T_b_c: np.ndarray,
        cfg: DenseConfig | None = None,
        depth_gt=None,
        timers: dict | None = None,
        depth_source: DepthSource | None = None,
        probe: ApproxErrorProbe | None = None,
    ) -> None:
        self.cfg = cfg or DenseConfig()
        self.net = net
        self.camera = camera
        self.T_b_c = np.asarray(T_b_c, np.float64)
        self.T_c_b = inv_T(self.T_b_c)
        self.mapping = NetworkMapping.fit(camera.width, camera.height, net.width, net.height)
        self.net_cam = self.mapping.camera(camera.pinhole())
        self.K_net = self.net_cam.intrinsics
        self.depth_gt = depth_gt
        self.depth_source = network_depth if depth_source is None else depth_source
        self.probe = probe
        self.timers = timers if timers is not None else defaultdict(float)
        self.kfs: dict[int, _KfDense] = {}
        self.code_kfs: list[int] = []
        self.per_kf_metrics: dict[int, Future] = {}  # -> the keyframe's Table 2 metrics
        self.stats = _Stats()
        self.t_first_ns: int | None = None  # the window's first keyframe's time (start_after_s counts from it)
        self.armed_for: int | None = None  # the backend's init_kf_id that t_first_ns belongs to
        self.dense_map: tuple[np.ndarray, np.ndarray | None] | None = None  # (xyz, rgb) once finish() ran
        self.depth_views: list[dict] = []  # a few window keyframes' depths once finish() ran (keyframe_depth.png)
        self._pool: PriorityWorker | None = None  # the network thread (DenseConfig.background)
        self.fused_map = VoxelMap.from_config(self.cfg.map)  # the run's dense map (network thread only)
        self.tsdf = TsdfVolume.from_config(self.cfg.map) if self.cfg.map.mesh else None  # its TSDF (same thread)

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
        for k in [k for k in self.kfs if not backend.has_keyframe(k)]:  # a reset cleared the window
            del self.kfs[k]
        und = self.camera.undistort_image(image)
        img_net = self.mapping.image_to_network(und)
        points, sparse, n_sparse = None, None, -1
        if self.net.uses_sparse:
            uv, z = self._observed_points(backend, kf_id)
            points = (self.mapping.points_to_network(uv), z)
            sparse = self._sparse_input(points)
            n_sparse = int((sparse > 0).sum())
        feat = self.mapping.points_to_network(np.asarray(feat_uv_u, np.float64).reshape(-1, 2))
        job = self._submit(self._network_pass, img_net, sparse, frame_idx)
        self.kfs[kf_id] = _KfDense(
            kf_id, frame_idx, job, feat, img_net, np.zeros(self.net.code_dim), n_sparse=n_sparse, sparse_points=points
        )
        self.stats.n_sparse.append(n_sparse)
        self.timers["dense_keyframe"] += time.perf_counter() - t0

    def _sparse_input(self, points: tuple | None) -> np.ndarray | None:
        """The network's sparse depth input (h, w) [m] from its map points ``(uv, z)`` at network pixels (None
        stays None): made once for the network pass, and again from the kept points for the evaluation and the
        picture (a keyframe keeps its points, not the image)."""
        return None if points is None else sparse_depth_image(*points, (self.net.height, self.net.width))

    def _unscaled(self, n_sparse: int) -> bool:
        """A keyframe whose network input held ``n_sparse`` map points (-1: the network takes none) has a depth
        of no metric scale: fewer than ``min_sparse_points``. It takes no code and is not fused."""
        return 0 <= n_sparse < self.cfg.min_sparse_points

    def _submit(self, fn, *args, urgent: bool = True) -> Future:
        """Run ``fn(*args)`` on the network thread (``DenseConfig.background``; one thread, so that the passes
        on one keyframe never overlap) or here; errors are raised where the result is read. ``urgent``: the
        tracking thread will wait for it (a network pass, a relinearisation); the others (map codes, depth
        metrics, fusion) run when no urgent job is queued (:class:`runtime.dense.worker.PriorityWorker`)."""
        if self.cfg.background:
            if self._pool is None:
                self._pool = PriorityWorker("dense-network")
            job = self._pool.submit(fn, *args, urgent=urgent)
            if not urgent:
                self.later_peak = max(self.later_peak, self._pool.pending()[1])
            return job
        job = Future()
        try:
            job.set_result(fn(*args))
        except Exception as e:  # noqa: BLE001 - as from the thread: raised where the result is read
            job.set_exception(e)
        return job

    def _exact(self, d: _KfDense, code: np.ndarray) -> np.ndarray:
        """The exact decoder at ``code`` (on the network thread: the keyframe's cache is not shared)."""
        return np.asarray(self._submit(d.provider.exact, np.asarray(code, np.float64)).result(), np.float64)

    def _network_pass(self, img_net: np.ndarray, sparse: np.ndarray | None, frame_idx: int) -> LinearizedDepth:
        """A keyframe's prior and its decoder linearised at c = 0 (where its code starts); runs in the background
        thread with ``DenseConfig.background`` (ONNX Runtime releases the GIL while tracking goes on)."""
        t0 = time.perf_counter()
        kd = self.depth_source(self.net.prior(img_net, sparse), frame_idx, self.camera, self.mapping)
        provider = LinearizedDepth(kd)
        provider.relinearize(np.zeros(self.net.code_dim))
        self.timers["dense_network"] += time.perf_counter() - t0
        return provider

    def _observed_points(self, backend, kf_id: int) -> tuple[np.ndarray, np.ndarray]:
        """Undistorted pixels (N, 2) and depths (N,) of the landmarks with two or more views observed by
        ``kf_id``, projected with their current positions."""
        _, X, _ = backend.observations(kf_id, min_views=2)
        if X.shape[0] == 0:
            return np.zeros((0, 2)), np.zeros(0)
        T_c_w = self.T_c_b @ inv_T(backend.keyframe(kf_id).T_w_b)
        p = X @ T_c_w[:3, :3].T + T_c_w[:3, 3]
        return project_pinhole(self.camera.intrinsics, p[p[:, 2] > MIN_POINT_DEPTH])

    # ------------------------------------------------------------------ FactorProvider
    def _select(self, backend) -> list[int]:
        """The code keyframes: the newest keyframe and its most co-visible ones. With ``background`` the
        keyframe created just now waits for the next optimisation (its network pass runs meanwhile), so the
        newest keyframe before it anchors the selection; the selection never depends on thread timing."""
        window = backend.window_ids()
        if self.cfg.background:
            window = window[:-1]  # the keyframe created just now
        window = [k for k in window if k in self.kfs and not self._unscaled(self.kfs[k].n_sparse)]
        if not window:
            return []
        newest = window[-1]
        cand = [newest] + [k for k in backend.covisible_keyframes(newest, len(window) + 1) if k in window]
        t0 = time.perf_counter()
        sel = cand[: self.cfg.n_code_keyframes]
        for k in sel:  # done long ago in the usual case
            d = self.kfs[k]
            d.job.result()
            if d.relin is not None:
                d.relin.result()
                d.relin = None
        self.timers["dense_wait"] += time.perf_counter() - t0
        return sel

    def _arm_start(self, backend, kf_id: int) -> None:
        """Start the ``start_after_s`` wait at ``kf_id`` when it is the first keyframe after an initialisation
        (the first of the run, or a re-initialisation after a reset: the backend's ``init_kf_id`` changed)."""
        init_id = backend.init_kf_id
        if self.t_first_ns is None or init_id != self.armed_for:
            self.t_first_ns = int(backend.keyframe(kf_id).ts)
            self.armed_for = init_id

    def _started(self, backend) -> bool:
        newest = backend.latest
        return self.t_first_ns is not None and (newest.ts - self.t_first_ns) * 1e-9 >= self.cfg.start_after_s

    def add_factors(self, backend, graph, values) -> None:
        import gtsam
        from gtsam.symbol_shorthand import C

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
            values.insert(C(k), np.asarray(d.code, np.float64))
            graph.add(gtsam.PriorFactorVector(C(k), np.zeros(Cd), prior_noise))
            if cfg.use_depth_residual:
                for f in self._geometric_factors(backend, k, values):
                    graph.add(f)
                    n_geo += f.dim()
        if cfg.use_consistency and len(sel) >= 2:
            for k2 in sel[1:]:
                f = self._consistency_factor(backend, sel[0], k2)
                if f is not None:
                    graph.add(f)
                    n_con += f.dim()
        self.stats.n_optim += 1
        self.stats.n_code_kfs.append(len(sel))
        self.stats.n_geo_rows.append(n_geo)
        self.stats.n_consis_rows.append(n_con)
        self.timers["dense_factors"] += time.perf_counter() - t0

    def _geometric_factors(self, backend, k: int, values) -> list:
        """Eq. 13 factors of code keyframe ``k`` on its observations of the window's landmarks."""
        from gtsam.symbol_shorthand import C, L, X

        ids, _, uv = backend.observations(k)
        ok = [i for i, j in enumerate(ids) if values.exists(L(int(j)))]
        if not ok:
            return []
        d = self.kfs[k]
        fcfg = self.cfg.factors
        depth_map = d.provider.expansion(d.code) if fcfg.edge_rel is not None else None
        uvn = self.mapping.points_to_network(uv[ok])
        keys = [L(int(j)) for j in ids[ok]]
        return make_geometric_depth_factors(X(k), C(k), uvn, d.provider, self.T_b_c, keys, fcfg, depth_map)

    def _consistency_factor(self, backend, k1: int, k2: int):
        """Eq. 14 factor of the code keyframes ``(k1, k2)`` on the Sec. 5.2 samples of k2 (by its features), at
        the window's poses and codes; None when no sample is usable."""
        from gtsam.symbol_shorthand import C, X

        d1, d2 = self.kfs[k1], self.kfs[k2]
        rng = np.random.default_rng([self.cfg.seed, k1, k2])
        s = sample_consistency_pixels(d2.feat_uv, self.net.width, self.net.height, self.cfg.n_consis, rng=rng, margin=2)
        try:
            return make_consistency_factor(
                (X(k1), X(k2)),
                (C(k1), C(k2)),
                (d1.provider, d2.provider),
                s.uv,
                self.K_net,
                self.T_b_c,
                (backend.keyframe(k1).T_w_b, backend.keyframe(k2).T_w_b),
                (d1.code, d2.code),
                self.cfg.factors,
            )
        except ValueError as e:
            log.info("dense: no consistency factor %d-%d (%s)", k1, k2, e)
            return None

    def on_optimized(self, backend, result) -> None:
        from gtsam.symbol_shorthand import C

        for k in self.code_kfs:
            if result.exists(C(k)):
                self.kfs[k].code = np.asarray(result.atVector(C(k)), np.float64).copy()
        if self.probe is not None:
            t0 = time.perf_counter()
            self.probe([(self.kfs[k].provider, self.kfs[k].code) for k in self.code_kfs])
            self.timers["dense_approx_check"] += time.perf_counter() - t0
        for k in self.code_kfs:  # the next optimisation's linearisation point, computed meanwhile
            d = self.kfs[k]
            lin = np.zeros_like(d.code) if d.lin_code is None else d.lin_code
            if np.abs(d.code - lin).max() > self.cfg.relin_tol:
                d.lin_code = d.code.copy()
                d.relin = self._submit(self._relinearize, d.provider, d.lin_code)

    def _relinearize(self, provider: LinearizedDepth, code: np.ndarray) -> None:
        t0 = time.perf_counter()
        provider.relinearize(code)
        self.timers["dense_network"] += time.perf_counter() - t0

    def on_marginalize(self, backend, kf_id: int) -> None:
        """A keyframe leaves the window: evaluate its depth and fuse it into the map (final code and pose), free
        its network state."""
        d = self.kfs.get(kf_id)
        if d is None:
            return
        self._refine(backend, d)
        self._evaluate(backend, d)
        self._fuse(backend, d)
        del self.kfs[kf_id]

    def _refine(self, backend, d: _KfDense) -> None:
        """Submit the refinement of ``d``'s code for the map (:mod:`runtime.dense.refine`): jointly with its most
        co-visible keyframes that have a scale, at the window's current poses and codes (taken now)."""
        mc = self.cfg.map_codes
        if mc.neighbours == 0 or not d.had_code or self._unscaled(d.n_sparse) or d.map_code is not None:
            return
        cand = backend.covisible_keyframes(d.kf_id, len(self.kfs))
        group = [d] + [self.kfs[k] for k in cand if k in self.kfs and not self._unscaled(self.kfs[k].n_sparse)][
            : mc.neighbours
        ]
        if len(group) < 2:
            return
        samples = []
        for g in group:
            rng = np.random.default_rng([self.cfg.seed, d.kf_id, g.kf_id])
            s = sample_consistency_pixels(g.feat_uv, self.net.width, self.net.height, mc.n_samples, rng=rng, margin=2)
            samples.append(s.uv)
        poses = [np.asarray(backend.keyframe(g.kf_id).T_w_b, np.float64).copy() for g in group]
        codes = [g.code.copy() for g in group]
        frozen = self._submit(_frozen_providers, [g.job for g in group])  # urgent: after the relinearisations so far
        d.map_code = self._submit(self._fit_map_code, frozen, codes, poses, samples, urgent=False)

    def _fit_map_code(self, frozen: Future, codes: list, poses: list, samples: list) -> np.ndarray:
        """The first keyframe's map code (network thread); its window code when the fit fails (logged).
        ``frozen``: the group's providers as linearised when the fit was submitted (:func:`_frozen_providers`)."""
        t0 = time.perf_counter()
        mc = self.cfg.map_codes
        fcfg = dataclasses.replace(self.cfg.factors, sigma_per_b=mc.sigma_per_b)
        providers = frozen.result()
        try:
            fitted, _ = refine_codes(
                providers, codes, poses, samples, self.T_b_c, self.K_net, fcfg, self.cfg.code_prior_sigma,
                mc.iterations,
            )  # fmt: skip
            code = fitted[0]
        except (np.linalg.LinAlgError, ValueError, FloatingPointError) as e:
            log.warning("dense: map code fit failed (%s); the map keeps the window's code", e)
            code = np.asarray(codes[0], np.float64)
        self.timers["dense_map_codes"] += time.perf_counter() - t0
        return code

    @staticmethod
    def _map_code_of(code: np.ndarray, map_code: Future | None) -> np.ndarray:
        """The code the map uses: the refined one when there is one (network thread: it is done), else ``code``."""
        return code if map_code is None else np.asarray(map_code.result(), np.float64)

    def _fuse(self, backend, d: _KfDense) -> None:
        """Integrate keyframe ``d`` into the fused map with its current code and pose, on the network thread (the
        map is only ever touched there)."""
        if d.fused:
            return
        d.fused = True
        if self._unscaled(d.n_sparse):
            return
        T_w_c = np.asarray(backend.keyframe(d.kf_id).T_w_b, np.float64) @ self.T_b_c

        def integrate(provider: LinearizedDepth, code: np.ndarray, map_code: Future | None) -> None:
            t0 = time.perf_counter()
            depth = np.asarray(provider.exact(self._map_code_of(code, map_code)), np.float64)
            self.fused_map.integrate(d.kf_id, depth, T_w_c, self.net_cam, provider.uncertainty, d.image, self.cfg.map)
            t1 = time.perf_counter()
            self.timers["dense_fusion"] += t1 - t0
            if self.tsdf is not None:
                self.tsdf.integrate(d.kf_id, depth, T_w_c, self.net_cam, provider.uncertainty, d.image, self.cfg.map)
                self.timers["dense_tsdf"] += time.perf_counter() - t1

        self._submit(integrate, d.provider, d.code.copy(), d.map_code, urgent=False)

    # ------------------------------------------------------------------ evaluation and outputs
    def final_depth(self, d: _KfDense) -> np.ndarray:
        """The keyframe's depth as the map has it (its map code when refined, else its window code)."""
        return self._exact(d, self._map_code_of(d.code, d.map_code))

    def _evaluate(self, backend, d: _KfDense) -> None:
        if d.evaluated or not d.had_code or self.depth_gt is None:
            return
        d.evaluated = True
        uv, z = self._observed_points(backend, d.kf_id)
        uv_net = self.mapping.points_to_network(uv)
        sparse_in = self._sparse_input(d.sparse_points)
        self.per_kf_metrics[d.kf_id] = self._submit(
            self._depth_errors, d.provider, d.code.copy(), d.frame_idx, uv_net, z, d.map_code, sparse_in, urgent=False
        )

    def _depth_errors(
        self,
        provider: LinearizedDepth,
        code: np.ndarray,
        frame_idx: int,
        uv_net: np.ndarray,
        z: np.ndarray,
        map_code: Future | None = None,
        sparse_in: np.ndarray | None = None,
    ) -> dict | None:
        """Table 2 metrics of a keyframe's sparse points (network pixels ``uv_net``, depths ``z``), prior (c = 0),
        window code (``optimised``) and the map's code (``map``: refined at fixed poses, else the window's),
        against the ground truth of its frame (network thread: reading and resampling the ground truth is
        evaluation, not tracking work); None without ground truth for the frame.

        Next to them, the two references every depth table here carries: ``interpolated``, the network's own
        sparse input ``sparse_in`` interpolated (:func:`runtime.densify.interpolate_sparse`; None when the
        network took no point), which a network with sparse input has to beat, and ``median``, the constant
        image at the median of the true depth (an oracle of the scale alone)."""
        from runtime.densify import interpolate_sparse

        gt = self.depth_gt(frame_idx)
        if gt is None:
            return None
        gt_net = gt_depth_to_network(gt, self.camera, self.mapping)
        sp = sparse_depth_image(uv_net, z, gt_net.shape)
        valid = gt_net[np.isfinite(gt_net) & (gt_net > 0)]
        taken = sparse_in is not None and bool((sparse_in > 0).any())
        # The network's own fill input when it took one: the same interpolation of the same points.
        fill = getattr(getattr(provider, "kd", None), "fill", None)
        return {
            "sparse": depth_metrics(sp, gt_net) if (sp > 0).any() and (gt_net[sp > 0] > 0).any() else None,
            "interpolated": (
                depth_metrics(fill if fill is not None else interpolate_sparse(sparse_in), gt_net) if taken else None
            ),
            "median": depth_metrics(np.full(gt_net.shape, np.median(valid)), gt_net) if valid.size else None,
            "prior": depth_metrics(np.asarray(provider.exact(np.zeros_like(code)), np.float64), gt_net),
            "optimised": depth_metrics(np.asarray(provider.exact(code), np.float64), gt_net),
            "map": depth_metrics(np.asarray(provider.exact(self._map_code_of(code, map_code)), np.float64), gt_net),
        }

    def finish(self, backend, out_dir: str | Path) -> dict:
        """Fuse the keyframes still in the window into the map; write ``dense_map.ply`` (the fused map of the
        run) and the per-keyframe maps (``keyframe_depth/``, the window's), each atomically; return the dense
        metrics for ``metrics.json``."""
        out = Path(out_dir)
        active = [k for k in backend.window_ids() if k in self.kfs]
        for k in active:
            self._refine(backend, self.kfs[k])
        for k in active:
            self._evaluate(backend, self.kfs[k])
        depths, uncs = [], []
        for k in active:
            d = self.kfs[k]
            depths.append(self.final_depth(d))
            uncs.append(d.provider.uncertainty)
            self._fuse(backend, d)
        self.close()  # every pass done: the fused map and the depth metrics are complete
        if self.cfg.save_maps and active:
            maps = [(f"kf{k:05d}", depth, unc) for k, depth, unc in zip(active, depths, uncs, strict=True)]
            write_keyframe_maps(out / "keyframe_depth", maps)
        self.depth_views = self._views(active, depths, uncs)
        xyz, rgb, nrm, count = self.fused_map.points()
        write_fused_map(out / "dense_map.ply", xyz, rgb, nrm, count)
        self.dense_map = (xyz, rgb)  # for the Rerun recording
        res = self._metrics(len(active), int(xyz.shape[0]))
        res["dense_map_keyframes"] = len(self.fused_map.keyframes)
        if self.tsdf is not None:
            res.update(self._write_mesh(out))
        return res

    def _views(self, active: list[int], depths: list, uncs: list, n: int = 4) -> list[dict]:
        """Rows of :func:`runtime.render.depth_panels` for ``n`` keyframes spread over the window ``active``
        (their final depths and uncertainties), with the true depth where the sequence has it."""
        rows = []
        for i in sorted({int(round(x)) for x in np.linspace(0, len(active) - 1, min(n, len(active)))}):
            d = self.kfs[active[i]]
            gt = self.depth_gt(d.frame_idx) if self.depth_gt is not None else None
            rows.append(
                {
                    "image": d.image,
                    "sparse": self._sparse_input(d.sparse_points),
                    "depth": depths[i],
                    "uncertainty": uncs[i],
                    "gt": None if gt is None else gt_depth_to_network(gt, self.camera, self.mapping),
                    "title": f"keyframe {d.kf_id} (frame {d.frame_idx}), {max(d.n_sparse, 0)} map points",
                }
            )
        return rows

    def _write_mesh(self, out: Path) -> dict:
        """``dense_mesh.ply``: the surface of the run's TSDF; its size and costs for ``metrics.json``."""
        t0 = time.perf_counter()
        v, f, rgb, nrm = self.tsdf.mesh()
        write_mesh_ply(out / "dense_mesh.ply", v, f, rgb, nrm)
        n_kf = max(len(self.tsdf.keyframes), 1)
        return {
            "dense_mesh_vertices": int(len(v)),
            "dense_mesh_faces": int(len(f)),
            "dense_mesh_s": time.perf_counter() - t0,  # extraction and writing, at the end of the run
            "dense_tsdf_ms_per_keyframe": 1e3 * self.timers.get("dense_tsdf", 0.0) / n_kf,  # network thread
            "dense_tsdf_blocks": self.tsdf.n_blocks,
            "dense_tsdf_mb": self.tsdf.nbytes / 1e6,
        }

    def drain(self) -> None:
        """Wait until the network thread has run every job submitted so far (its later work included); the
        later-work jobs that were still waiting go into the metrics (``dense_later_jobs_at_last_frame``)."""
        if self._pool is not None:
            self.later_at_drain = self._pool.pending()[1]
            self._pool.submit(_nothing, urgent=False).result()  # a marker, not counted as later work

    def close(self) -> None:
        """Wait for the network thread's passes and stop it (a later keyframe starts a new one)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None

    def _metrics(self, n_window: int, n_points: int) -> dict:
        st = self.stats
        res = {
            "dense_map_points": n_points,
            "dense_window_keyframes": n_window,
            "dense_optimisations": st.n_optim,
            "dense_optimisations_before_start": st.n_skipped,
            "dense_mean_code_keyframes": float(np.mean(st.n_code_kfs)) if st.n_code_kfs else 0.0,
            "dense_mean_geo_rows": float(np.mean(st.n_geo_rows)) if st.n_geo_rows else 0.0,
            "dense_mean_consis_rows": float(np.mean(st.n_consis_rows)) if st.n_consis_rows else 0.0,
            "dense_keyframe_sparse_points": _quartiles(st.n_sparse),
            "dense_keyframes_below_min_sparse": int(sum(self._unscaled(n) for n in st.n_sparse)),
            "decoder_calls": int(self.net.decoder_calls),
            # The network thread's later work (map codes, depth metrics, fusion of the keyframes that left the
            # window) runs when no urgent job waits; each waiting job holds its keyframe's network state.
            "dense_later_jobs_peak": int(self.later_peak),
            "dense_later_jobs_at_last_frame": self.later_at_drain,
            "dense_config": dataclasses.asdict(self.cfg),
        }
        if self.probe is not None:
            res.update(self.probe.metrics())
        per_kf = [m for m in (job.result() for job in self.per_kf_metrics.values()) if m is not None]
        if per_kf:
            res["depth_metrics"] = {
                stage: mean_metrics([m[stage] for m in per_kf if m[stage] is not None])
                for stage in DEPTH_STAGES
                if stage not in REFERENCE_STAGES or any(m[stage] is not None for m in per_kf)
            }
            res["depth_metrics_keyframes"] = len(per_kf)
            res["depth_metrics_unit"] = "m (RMSE, MAE), 1/m (iRMSE)"
        return res


#: The rows of ``depth_metrics`` in ``metrics.json``: the estimates, then the references (see ``_depth_errors``).
REFERENCE_STAGES = ("interpolated", "median")  # left out when no keyframe has them (a network without sparse input)
DEPTH_STAGES = ("sparse", "prior", "optimised", "map", *REFERENCE_STAGES)


def _nothing() -> None:
    """A job that marks a place in the network thread's later queue (:meth:`DenseMapper.drain`)."""


def _frozen_providers(jobs: list[Future]) -> list[LinearizedDepth]:
    """The providers of ``jobs`` as they are linearised now: shallow copies, which a later relinearisation of the
    originals (it rebinds their maps) leaves as they are. A map-code fit runs on the network thread after urgent
    jobs submitted later than itself; through these copies it sees the linearisation it was submitted at."""
    return [copy.copy(j.result()) for j in jobs]


def _quartiles(values: list) -> list[float] | None:
    """``[min, 25 %, median, 75 %, max]`` of ``values`` (None when empty)."""
    if not values:
        return None
    return [float(x) for x in np.percentile(np.asarray(values, np.float64), [0, 25, 50, 75, 100])]
