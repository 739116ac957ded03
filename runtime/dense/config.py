"""Settings of the dense system, each defined once: the depth factors, the local dense map, and the mapper that
holds them (Hydra ``dense_settings``, ``conf/slam/dense_settings/default.yaml``; nested keys
``dense_settings.factors.*``, ``dense_settings.map.*``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from runtime.config import dataclass_from_dict

__all__ = ["SIGMA_PER_LAPLACE_B", "DepthFactorConfig", "DenseMapConfig", "MapCodeConfig", "DenseConfig"]

#: Standard deviation of a Laplace distribution per unit of its scale ``B`` (variance ``2 B^2``).
SIGMA_PER_LAPLACE_B = math.sqrt(2.0)


@dataclass(frozen=True)
class DepthFactorConfig:
    """Settings of the depth factors (Eq. 13-14, :mod:`runtime.dense.factors`).

    Attributes:
        sigma_per_b: row sigma per unit of the predicted Laplace scale ``B`` (``sqrt(2)``: Laplace). 16x Laplace:
            a depth map's errors are one smooth field, so hundreds of rows on one map are worth a handful of
            independent ones (``reports/``).
        min_sigma: floor on a row's sigma [m] (a tiny predicted ``B`` must not make a row rigid).
        geo_huber_k: Huber threshold of Eq. 13 in sigmas (None or <= 0: no robust kernel).
        consis_huber_k: Huber threshold of Eq. 14 in sigmas (None or <= 0: none, as Eq. 15).
        consis_covariance: ``"full"`` (``dr/dd2``, with the image gradient of ``d_k1``) or ``"z"``
            (``dz/dd2`` only).
        chunk_size: landmarks per Eq. 13 factor (0: one factor per keyframe).
        min_depth: smallest depth [m] in ``k1`` for an Eq. 14 sample to count.
        edge_rel: depth-edge test of both residuals (:func:`runtime.dense.lookup.depth_edge_ratio`): rows
            whose 3x3 depth range over its minimum exceeds it are not used; None: off. 0.05 removes the Eq. 14
            rows that the rendered depth at the true poses puts decimetres off (``reports/``).
        check_shapes: assert every Jacobian's shape at each linearisation (GTSAM accepts wrong shapes).
    """

    sigma_per_b: float = 16.0 * SIGMA_PER_LAPLACE_B
    min_sigma: float = 0.02
    geo_huber_k: float | None = 1.5
    consis_huber_k: float | None = 1.5
    consis_covariance: str = "full"
    chunk_size: int = 32
    min_depth: float = 0.05
    edge_rel: float | None = 0.05
    check_shapes: bool = False

    def __post_init__(self) -> None:
        if self.edge_rel is not None and not self.edge_rel > 0:
            raise ValueError(f"edge_rel={self.edge_rel}: must be > 0 (or None: no depth-edge test)")
        if not self.sigma_per_b > 0:
            raise ValueError(f"sigma_per_b={self.sigma_per_b}: must be > 0")
        if not self.min_sigma > 0:
            raise ValueError(f"min_sigma={self.min_sigma}: must be > 0")
        if self.consis_covariance not in ("full", "z"):
            raise ValueError(f"consis_covariance={self.consis_covariance!r}: expected 'full' or 'z'")
        if self.chunk_size < 0:
            raise ValueError(f"chunk_size={self.chunk_size}: must be >= 0")


@dataclass(frozen=True)
class DenseMapConfig:
    """Settings of the dense map (:mod:`runtime.dense.map`, :mod:`runtime.dense.fusion`).

    A pixel is kept when its Laplace scale ``B`` is at most ``max_uncertainty`` [m] and ``B / depth`` at most
    ``max_rel_uncertainty`` (either may be None), and ``min_depth <= depth <= max_depth``.

    Attributes:
        max_uncertainty: largest Laplace scale ``B`` [m] kept (None: no absolute limit).
        max_rel_uncertainty: largest ``B / depth`` kept (None: no relative limit).
        min_depth, max_depth: depth range kept [m].
        stride: back-project every ``stride``-th pixel in u and v (1: all).
        voxel: voxel edge [m] of the downsampling (0: none) and of the fused map
            (:class:`runtime.dense.fusion.VoxelMap`; 0 there: 1 cm).
        mesh: also fuse the keyframes into a TSDF (:class:`runtime.dense.tsdf.TsdfVolume`, same filter and
            ``1 / B^2`` weights) and write its surface as ``dense_mesh.ply``. Off by default: on the network
            thread it cost 10-29 CPU ms a frame, and the default sequence ran at 18.0 / 21.0 frames/s with it
            against 31.3 / 25.5 without it (alternating runs, ``reports/ablations.md``).
        tsdf_voxel: voxel edge [m] of the TSDF.
        tsdf_trunc: truncation distance [m] of the TSDF (> ``tsdf_voxel``).
    """

    max_uncertainty: float | None = None
    max_rel_uncertainty: float | None = 0.1
    min_depth: float = 0.1
    max_depth: float = 10.0
    stride: int = 1
    voxel: float = 0.02
    mesh: bool = False
    tsdf_voxel: float = 0.04
    tsdf_trunc: float = 0.12

    def __post_init__(self) -> None:
        if not self.tsdf_voxel > 0:
            raise ValueError(f"tsdf_voxel={self.tsdf_voxel}: must be > 0")
        if not self.tsdf_trunc > self.tsdf_voxel:
            raise ValueError(f"tsdf_trunc={self.tsdf_trunc}: must be > tsdf_voxel={self.tsdf_voxel}")
        if self.stride < 1:
            raise ValueError(f"stride={self.stride}: must be >= 1")
        if self.voxel < 0:
            raise ValueError(f"voxel={self.voxel}: must be >= 0")
        if not 0 <= self.min_depth < self.max_depth:
            raise ValueError(f"depth range [{self.min_depth}, {self.max_depth}] is empty")


@dataclass(frozen=True)
class MapCodeConfig:
    """Settings of the map's code refinement at fixed poses (:mod:`runtime.dense.refine`).

    Attributes:
        neighbours: co-visible keyframes fitted jointly with a keyframe that leaves the window (0: off, the map
            and the depth metrics take the window's code).
        n_samples: Eq. 14 samples of each keyframe of the group (Sec. 5.2 sampler).
        sigma_per_b: row sigma per unit of the predicted Laplace scale ``B`` (``sqrt(2)``: the network's own
            likelihood; the window's factors use ``factors.sigma_per_b``).
        iterations: Levenberg-Marquardt iterations (the decoder is linearised, so the fit is nearly linear: one
            iteration gave the depth of eight on `handheld`, 13 groups at the true poses).
    """

    neighbours: int = 2
    n_samples: int = 300
    sigma_per_b: float = SIGMA_PER_LAPLACE_B
    iterations: int = 2

    def __post_init__(self) -> None:
        if self.neighbours < 0 or self.n_samples < 1 or self.iterations < 0:
            raise ValueError(
                f"map_codes: neighbours={self.neighbours} and iterations={self.iterations} must be >= 0, "
                f"n_samples={self.n_samples} >= 1"
            )
        if not self.sigma_per_b > 0:
            raise ValueError(f"map_codes.sigma_per_b={self.sigma_per_b}: must be > 0")


@dataclass
class DenseConfig:
    """Settings of the dense (tightly coupled) system (:class:`runtime.dense.mapper.DenseMapper`).

    Attributes:
        n_code_keyframes: keyframes of the window with a depth code (the newest + its most co-visible ones).
        use_depth_residual: Eq. 13 factors (off by default: with Eq. 14 alone the realistic sequences' ATE was
            5.0 +- 2.2 mm lower over 15 runs, ``reports/ablations.md``).
        use_consistency: Eq. 14 factors.
        n_consis: ``N_consis``, Eq. 14 samples per keyframe pair (Sec. 5.2 sampler).
        code_prior_sigma: sigma of the ``N(0, I)`` code prior (1: the CVAE prior).
        start_after_s: seconds after the first keyframe (the initialisation) before codes and depth factors
            join the window's optimisations (0: from the first one); a re-initialisation after a reset waits
            again. While the visual-inertial scale and gravity still converge, a biased depth network pulls
            them and that early error stays in the trajectory (``reports/``).
        min_sparse_points: a keyframe whose network input held fewer map points than this takes no code and
            no depth factor, and is not fused into the dense map (the network was trained on 20-300 points;
            with none its depth has the scale of ``runtime.densify.DEFAULT_FILL_M``, not the scene's: about
            40 % of the realistic ``whitewall`` keyframes). 0: every keyframe. 20 against 0 over 43 paired dense
            runs: SE(3) -0.57 +- 0.61 mm (17 runs) and -0.25 +- 0.25 mm (26), ``whitewall`` seed 2 123.2 ->
            107.2 mm; leaving them out of the map raised its F-score at 5 cm on ``whitewall`` from 0.344 to 0.428
            (``reports/``).
        relin_tol: after an optimisation, a code keyframe's decoder is relinearised at its new code (Eq. 17: one
            batch of C + 1 decodes) only when a component of the code moved more than this since its last
            linearisation; between, the first-order expansion stands in
            (:class:`runtime.dense.linearized.LinearizedDepth`). 0: whenever it moved.
        background: run the network in a background thread while tracking goes on (ONNX Runtime releases the
            GIL): each keyframe's prior with its decoder linearised at c = 0, and the relinearisation of the
            codes an optimisation moved (Eq. 17). The optimisation of a new keyframe waits for the passes it
            needs, except the new keyframe's own: its code joins from the next keyframe's optimisation on.
            False: every pass on the tracking thread, and a keyframe's code joins at its own optimisation.
        save_maps: write per-keyframe depth / uncertainty maps.
        seed: sampler seed (combined with the keyframe ids of a pair).
        factors: the depth factors' settings.
        map: the local dense map's settings.
        map_codes: the codes of the map, refined at fixed poses when a keyframe leaves the window.
    """

    n_code_keyframes: int = 5
    use_depth_residual: bool = False
    use_consistency: bool = True
    n_consis: int = 300
    code_prior_sigma: float = 1.0
    start_after_s: float = 5.0
    min_sparse_points: int = 20
    relin_tol: float = 0.3
    background: bool = True
    save_maps: bool = True
    seed: int = 0
    factors: DepthFactorConfig = field(default_factory=DepthFactorConfig)
    map: DenseMapConfig = field(default_factory=DenseMapConfig)
    map_codes: MapCodeConfig = field(default_factory=MapCodeConfig)

    def __post_init__(self) -> None:
        if self.n_code_keyframes < 1:
            raise ValueError(f"n_code_keyframes={self.n_code_keyframes}: must be >= 1")
        if not self.start_after_s >= 0:
            raise ValueError(f"start_after_s={self.start_after_s}: must be >= 0")
        if self.min_sparse_points < 0:
            raise ValueError(f"min_sparse_points={self.min_sparse_points}: must be >= 0")
        if not self.relin_tol >= 0:
            raise ValueError(f"relin_tol={self.relin_tol}: must be >= 0")
        if self.n_consis < 1:
            raise ValueError(f"n_consis={self.n_consis}: must be >= 1")
        if not self.code_prior_sigma > 0:
            raise ValueError(f"code_prior_sigma={self.code_prior_sigma}: must be > 0")
        if not isinstance(self.factors, DepthFactorConfig):
            raise ValueError(f"factors={self.factors!r}: expected a DepthFactorConfig")
        if not isinstance(self.map, DenseMapConfig):
            raise ValueError(f"map={self.map!r}: expected a DenseMapConfig")
        if not isinstance(self.map_codes, MapCodeConfig):
            raise ValueError(f"map_codes={self.map_codes!r}: expected a MapCodeConfig")

    @classmethod
    def from_dict(cls, d: dict | None) -> DenseConfig:
        """Build from a (nested) mapping; unknown keys raise naming the key (``dense_settings.factors.x``)."""
        return dataclass_from_dict(cls, d or {}, "dense_settings")
