"""Relocalisation against the map after a loss of visual tracking, and guided re-finding of map points.

KLT tracks die when the view is lost (a white wall); the map points seen before are then unreachable for the
tracker, and the estimate drifts with the IMU. Each landmark gets an ORB descriptor when it is triangulated (in
its keyframe image). After tracking resumes, a new keyframe's features are described and matched against the
map points the estimated camera could see (generous frustum: the estimate may be off by a metre), and a RANSAC
PnP on the matches gives the camera pose in the map (:meth:`Relocalizer.relocalize`). The coasted keyframes
are then re-estimated over their IMU links between the last visual fix before the loss and the PnP pose (the
backend's coast bridge, :mod:`runtime.backend.coast`); when no inertial chain is left (an IMU gap, a loss longer
than the archive), a 4-DoF correction (yaw and translation: roll and pitch are observable from gravity) is
spread over the coast instead. The matched map points re-enter the window.

At every other keyframe, old map points are re-found among the keyframe's new tracks near their predicted
projections (:meth:`Relocalizer.guided_match`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from runtime.geometry import inv_T, ns_to_s
from runtime.reloc.descriptors import MapDescriptors, candidates_in_view, guided_match, in_view, match, pnp

log = logging.getLogger(__name__)


@dataclass
class RelocConfig:
    """Map re-use: relocalisation after a loss of visual tracking, and guided re-finding of map points."""

    enabled: bool = True
    min_lost_s: float = 1.0  # only after losses at least this long (shorter ones are bridged by the IMU)
    max_attempts: int = 30  # keyframes to try after tracking resumed
    max_hamming: int = 60  # descriptor distance bound (of 256 bits)
    ratio: float = 0.85  # Lowe's ratio test between the best and second-best candidate
    frustum_margin: float = 0.6  # candidate map points may project this fraction of the image size outside it
    max_depth: float = 12.0  # m, candidate map points farther than this are ignored
    min_inliers: int = 15  # PnP inliers to accept a relocalisation
    min_inlier_ratio: float = 0.3
    pnp_reproj_px: float = 2.5  # RANSAC threshold
    map_point_sigma: float = 0.02  # m, prior on a re-activated map point
    min_correction_m: float = 0.0  # corrections smaller than this are not applied (0: always)
    drift_exponent: float = 2.0  # share of a spread correction given to coasted keyframes: (elapsed fraction)^this
    guided: bool = True  # at every keyframe, re-find map points near their predicted projection
    guided_radius_px: float = 12.0
    guided_max_hamming: int = 50
    # the guided search also looks for the window's own landmarks that no track follows now (lost by the KLT, back
    # in view), within this radius of their projections, as ORB-SLAM3 matches its local map; 0: off. Their
    # positions share the window with the keyframe's pose, so their projections are good to a few pixels: a tight
    # radius keeps out wrong matches (at 12 px it lost on MH_05). Adopted at 4 px over 29 fresh pairs:
    # SE(3) -6.3 +- 3.8 mm sparse, -4.0 +- 2.7 dense (reports/ablations.md, slam_ablations/guided_window_4px.json)
    guided_window_radius_px: float = 4.0


@dataclass
class Relocalization:
    """A successful relocalisation: what the system applies and reports."""

    T_corr: np.ndarray  # (4, 4) world-frame correction of the relocalised keyframe (applies to the current pose)
    track_ids: np.ndarray  # tracks that now carry map-point ids (renamed)
    n_inliers: int
    n_matches: int
    drift_m: float
    yaw_deg: float
    bridged: bool  # the coast was re-estimated over its IMU links (else the correction was spread)


class Relocalizer:
    """Descriptors of the map points and the matching against them.

    Args:
        cfg: settings.
        camera: raw cam0 model (its pinhole intrinsics and size are used).
        T_b_c: (4, 4) cam0-to-body.
        backend: the :class:`runtime.backend.window.SlidingWindowBackend` (its map and the coast bridge).
        tracker: the feature tracker (``current``, ``rename``).
    """

    def __init__(self, cfg: RelocConfig, camera, T_b_c: np.ndarray, backend, tracker) -> None:
        self.cfg = cfg
        self.camera = camera
        self.K = camera.pinhole().K
        self.T_b_c = np.asarray(T_b_c, np.float64)
        self.T_c_b = inv_T(self.T_b_c)
        self.backend = backend
        self.tracker = tracker
        self.descriptors = MapDescriptors()

    def describe(self, image: np.ndarray, lm_ids: np.ndarray) -> None:
        """Give new landmarks (tracks of the current frame) their descriptors in ``image``."""
        cur = self.tracker.current(0)
        _, ia, ib = np.intersect1d(lm_ids, cur.ids, assume_unique=True, return_indices=True)
        desc, ok = self.descriptors.describe(image, cur.uv[ib])
        self.descriptors.add(lm_ids[ia], desc, ok)

    def relocalize(self, kf, image: np.ndarray, lost_since: int, regained: int) -> Relocalization | None:
        """Match keyframe ``kf``'s features with the map points; on a PnP fix, correct the drift (the coast
        bridge, or a spread 4-DoF correction) and bring the matched map points back into the window."""
        c = self.cfg
        map_ids, Xm = self.backend.map.map_point_arrays()
        if map_ids.size < c.min_inliers:
            return None
        view = candidates_in_view(
            kf.T_w_b @ self.T_b_c, Xm, self.K, self.camera.width, self.camera.height, c.frustum_margin, c.max_depth
        )
        feats = self.tracker.current(kf.ts)
        dm, okm = self._untracked_descriptors(map_ids[view], feats)
        ids_c, X_c, dm = map_ids[view][okm], Xm[view][okm], dm[okm]
        df, okf = self.descriptors.describe(image, feats.uv)
        f_idx = np.nonzero(okf)[0]
        qi, ti = match(df[f_idx], dm, c.max_hamming, c.ratio)
        T_w_c, n_in = None, 0  # too few matches: no PnP
        if qi.size >= c.min_inliers:
            fi = f_idx[qi]
            T_w_c, inl = pnp(X_c[ti], feats.xn[fi], c.pnp_reproj_px / self.camera.fx)
            n_in = int(inl.sum())
        log.debug(
            "t=%.3f s: relocalisation tried: %d tracks, %d map points in view, %d matches, %d PnP inliers",
            ns_to_s(kf.ts), feats.ids.size, ids_c.size, qi.size, n_in,
        )  # fmt: skip
        if T_w_c is None or n_in < c.min_inliers or n_in < c.min_inlier_ratio * qi.size:
            return None
        T_new = T_w_c @ self.T_c_b
        dR = T_new[:3, :3] @ kf.T_w_b[:3, :3].T
        yaw = float(np.arctan2(dR[1, 0], dR[0, 0]))
        shift = float(np.linalg.norm(T_new[:3, 3] - kf.T_w_b[:3, 3]))
        T_corr, bridged = np.eye(4), False
        if shift >= c.min_correction_m:
            T_corr, bridged = self._correct(kf, T_new, yaw, lost_since, regained)
        mi, fi = ti[inl], fi[inl]
        t_ids = self._adopt(kf.kf_id, feats.ids[fi], ids_c[mi], X_c[mi], feats.uv_u[fi])
        return Relocalization(T_corr, t_ids, n_in, int(qi.size), shift, float(np.degrees(yaw)), bridged)

    def _correct(self, kf, T_new: np.ndarray, yaw: float, t0: int, t1: int) -> tuple[np.ndarray, bool]:
        """Re-estimate the coast from ``t0`` (the loss) to ``kf`` (PnP pose ``T_new``) over its IMU links, or,
        without an inertial chain, spread a 4-DoF correction: keyframes since the loss get the fraction
        ``((t - t0) / (t1 - t0)) ** drift_exponent`` of it (the dead-reckoning error starts flat and grows
        about quadratically), those after tracking resumed at ``t1`` the whole of it. Returns the correction
        of ``kf`` and whether the coast was bridged."""
        c = self.cfg

        def correction(ts: int) -> np.ndarray:
            a = float(np.clip((ts - t0) / max(t1 - t0, 1), 0.0, 1.0)) ** c.drift_exponent
            ca, sa = np.cos(a * yaw), np.sin(a * yaw)
            C = np.eye(4)
            C[:3, :3] = [[ca, -sa, 0.0], [sa, ca, 0.0], [0.0, 0.0, 1.0]]
            # rotate about the keyframe's position so that a partial correction does not swing far points
            C[:3, 3] = a * (T_new[:3, 3] - kf.T_w_b[:3, 3]) + kf.T_w_b[:3, 3] - C[:3, :3] @ kf.T_w_b[:3, 3]
            return C

        corr = self.backend.bridge(t0, kf.kf_id, T_new, init=correction)
        if corr is not None:
            return corr[kf.kf_id], True
        self.backend.apply_correction(correction, t0)
        return correction(kf.ts), False  # about the keyframe's corrected position

    def guided_match(self, kf, image: np.ndarray) -> np.ndarray:
        """Re-find old map points among the keyframe's tracks that are not landmarks yet (small search radius
        around the predicted projections, descriptor check); matched tracks take the map point's id. With
        ``guided_window_radius_px``, then the window's landmarks that no track follows now, within that radius: a
        matched track takes the landmark's id and the keyframe observes it. Returns the renamed track ids."""
        c = self.cfg
        m = self.backend.map
        ids, Xm = m.map_point_arrays()
        t_ids, m_ids, X_m, uv = self._guided(kf, image, ids, Xm, c.guided_radius_px)
        renamed = self._adopt(kf.kf_id, t_ids, m_ids, X_m, uv) if t_ids.size else t_ids
        if c.guided_window_radius_px > 0:
            ids, Xw = m.landmark_arrays()
            lost = np.array([m.landmarks[int(j)].map_prior is None for j in ids], dtype=bool)
            t_ids, w_ids, _, uv = self._guided(kf, image, ids[lost], Xw[lost], c.guided_window_radius_px)
            ok = self.tracker.rename(t_ids, w_ids)
            self.backend.add_observations(kf.kf_id, w_ids[ok], uv[ok])
            renamed = np.concatenate([renamed, t_ids[ok]])
        return renamed

    def _guided(self, kf, image: np.ndarray, ids: np.ndarray, X: np.ndarray, radius: float) -> tuple:
        """Matches of points ``ids`` (positions ``X``) that no track follows, projected into keyframe ``kf``, with
        its tracks that are not landmarks, within ``radius`` px and by descriptor: ``(track ids, point ids, point
        positions, the tracks' undistorted pixels)``."""
        c = self.cfg
        none = (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 2)))
        if ids.size == 0:
            return none
        uv, view = in_view(inv_T(kf.T_w_b @ self.T_b_c), X, self.K, self.camera.width, self.camera.height, c.max_depth)
        if not view.any():
            return none
        feats = self.tracker.current(kf.ts)
        dm, okm = self._untracked_descriptors(ids[view], feats)
        ids_c, X_c, uv_c, dm = ids[view][okm], X[view][okm], uv[view][okm], dm[okm]
        free = np.array([not self.backend.map.is_landmark(j) for j in feats.ids], dtype=bool)
        if not free.any() or ids_c.size == 0:
            return none
        fidx = np.nonzero(free)[0]
        df, okf = self.descriptors.describe(image, feats.uv[fidx])
        fidx = fidx[okf]
        mi, fi = guided_match(uv_c, dm, feats.uv_u[fidx], df[okf], radius, c.guided_max_hamming, c.ratio)
        fi = fidx[fi]
        return feats.ids[fi], ids_c[mi], X_c[mi], feats.uv_u[fi]

    def _untracked_descriptors(self, ids: np.ndarray, feats) -> tuple[np.ndarray, np.ndarray]:
        """Descriptors (N, 32) of map points ``ids`` and the mask of those that have one and are not tracked in
        ``feats``: a map point still tracked keeps its own track."""
        dm, ok = self.descriptors.get(ids)
        return dm, ok & ~np.isin(ids, feats.ids)

    def _adopt(self, kf_id: int, t_ids: np.ndarray, m_ids: np.ndarray, X_m: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """Tracks ``t_ids`` take the ids of map points ``m_ids`` (positions ``X_m``), which come back into the window
        observed by keyframe ``kf_id`` at undistorted pixels ``uv``; a track that was a landmark gives it up. Pairs
        that would give two tracks one id are skipped. Returns the renamed track ids."""
        ok = self.tracker.rename(t_ids, m_ids)
        t_ids = t_ids[ok]
        for j in t_ids:
            if self.backend.map.is_landmark(j):
                self.backend.map.delete_landmark(int(j))
        self.backend.reactivate_landmarks(m_ids[ok], X_m[ok], kf_id, uv[ok], self.cfg.map_point_sigma)
        return t_ids


def relocalize_pending(system, kf, image: np.ndarray) -> None:
    """The pending relocalisation of ``system`` (a :class:`runtime.slam.SlamSystem` whose visual tracking
    resumed after a long loss) at keyframe ``kf``: try it, apply its correction, report it, or give up after
    ``max_attempts`` keyframes."""
    pend = system.reloc_pending
    pend["attempts"] += 1
    if pend["attempts"] > system.cfg.reloc.max_attempts:
        system.event(
            kf.ts,
            f"relocalisation gave up after {system.cfg.reloc.max_attempts} keyframes: continuing on the "
            f"estimate that drifted for {ns_to_s(pend['regained'] - pend['since']):.1f} s without visual tracking",
        )
        system.reloc_pending = None
        return
    r = system.reloc.relocalize(kf, image, pend["since"], pend["regained"])
    if r is None:
        return
    system.T_cur = r.T_corr @ system.T_cur
    for j in r.track_ids:
        system.track_obs.pop(int(j), None)
    lost_s = ns_to_s(pend["regained"] - pend["since"])
    system.relocalisations.append(
        {
            "t_s": round(ns_to_s(kf.ts), 4),
            "lost_s": round(lost_s, 3),
            "drift_m": r.drift_m,
            "yaw_deg": r.yaw_deg,
            "inliers": r.n_inliers,
            "bridged": r.bridged,
        }
    )
    system.event(
        kf.ts,
        f"relocalised against {r.n_inliers} map points ({r.n_matches} matches) after {lost_s:.1f} s "
        f"without visual tracking: drift correction {r.drift_m:.3f} m, yaw {r.yaw_deg:.2f} deg"
        + (" (coast re-estimated over its IMU links)" if r.bridged else " (spread over the coast)"),
    )
    system.reloc_pending = None
