"""Starting and restarting the sliding window from an initialisation (:mod:`runtime.init`).

:func:`seed_window` hands the states of a :class:`runtime.init.runner.StartState` to the backend (an in-motion
start: all its keyframes linked by the IMU, then triangulation and LM). A *restart* (after a start while turning
in place, once the motion allows structure from motion) does the same within the current map frame: both
frames are gravity-aligned, so the new solution is brought in by the yaw and translation that put its newest
state on the current estimate (:func:`frame_alignment`). :func:`backfill_records` gives the frames before
initialisation their poses.
"""

from __future__ import annotations

import logging

import numpy as np

from runtime.backend.imu import integrate, preintegration_params
from runtime.backend.state import Keyframe
from runtime.geometry import inv_T, ns_to_s, s_to_ns
from runtime.init import imu_rest_stats
from runtime.init.runner import Snapshot, StartState, propagate_back
from runtime.trajectory import FrameRecord

log = logging.getLogger(__name__)


def frame_alignment(T_old: np.ndarray, T_new: np.ndarray) -> np.ndarray:
    """``A`` (4, 4): a rotation about the vertical and a translation with ``A @ T_new`` at ``T_old``'s position and
    heading (both poses ``T_w_b`` in gravity-aligned frames)."""
    R = T_old[:3, :3] @ T_new[:3, :3].T
    yaw = np.arctan2(R[1, 0] - R[0, 1], R[0, 0] + R[1, 1])  # the vertical part of R
    c, s = np.cos(yaw), np.sin(yaw)
    A = np.eye(4)
    A[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    A[:3, 3] = T_old[:3, 3] - A[:3, :3] @ T_new[:3, 3]
    return A


def seed_window(system, st, A: np.ndarray | None = None) -> list[int]:
    """Start the backend's window from ``st`` (states moved by ``A``); returns the new keyframe ids."""
    A = np.eye(4) if A is None else A
    prev, kf_ids = None, []
    for snap, T, v in st.keyframes:
        kf = Keyframe(
            system._kf_id(), snap.ts, snap.frame_idx, A @ T, A[:3, :3] @ v, st.bias, still=st.method == "static"
        )
        if prev is None:
            system.backend.initialize(kf, st.sigmas)
        else:
            pim = system._new_pim(st.bias)
            integrate(pim, *system.imu.segment(prev.ts, kf.ts))
            system.backend.add_keyframe(kf, pim)
        system._register_kf_observations(kf.kf_id, snap.feats)
        if system.dense is not None and snap.image is not None:
            system.dense.on_keyframe(system.backend, kf.kf_id, snap.frame_idx, snap.image, snap.feats.uv_u)
        prev = kf
        kf_ids.append(kf.kf_id)
    if len(kf_ids) > 1:
        system._triangulate(None)
        system.backend.optimize()
        drop, _ = system.backend.remove_outliers()
        if drop.size:
            system.tracker.drop(drop)
        system.backend.optimize()
        system.backend.marginalize()
    latest = system.backend.latest
    system.pim = system._new_pim(latest.bias)
    system.T_cur, system.v_cur = latest.T_w_b.copy(), latest.v_w.copy()
    system.still_since_kf = True
    system.kf_reasons["init"] += len(kf_ids)
    return kf_ids


def backfill_records(system, st, kf_ids: list[int]) -> None:
    """Records for the frames of the start window (keyframes and the frames between them), oldest first. After an
    in-motion start, those older than the first keyframe are handed to :func:`repose_older`."""
    firsts = [(snap.ts, k, T) for (snap, T, _), k in zip(st.keyframes, kf_ids, strict=True)]
    older = []
    for snap, T in sorted([(k[0], k[1]) for k in st.keyframes] + st.frames, key=lambda x: x[0].ts):
        t_ref, ref_id, T_ref = max([f for f in firsts if f[0] <= snap.ts], default=firsts[0], key=lambda f: f[0])
        is_kf = t_ref == snap.ts
        rec = FrameRecord(snap.ts, snap.frame_idx, ref_id, inv_T(T_ref) @ T, T.copy(), is_kf, "init")
        rec.segment = system.segment
        if st.t_window is not None and snap.ts < st.t_window:  # kept from before the start: the IMU alone
            rec.status, rec.imu_s = "imu_backfill", ns_to_s(st.t_window - snap.ts)
        if is_kf:
            rec.T_created = T.copy()
        system.records.append(rec)
        if snap.ts < firsts[0][0]:
            older.append((snap, rec))
    system.older_pending = (kf_ids[0], older) if st.method == "dynamic" and older else None
    repose_older(system)


def repose_older(system) -> None:
    """The frames before an in-motion start's first keyframe (``system.older_pending``: that keyframe's id and
    ``[(snapshot, record)]``, oldest first) integrated backwards from the keyframe's current state, after each
    optimisation until it leaves the window: its velocity and biases as the alignment gave them were off by enough
    to cost 0.24 m over the 1 s before the start on the realistic ``handheld`` seed 0 (reports/ablations.md)."""
    if system.older_pending is None:
        return
    kf_id, older = system.older_pending
    if not system.backend.has_keyframe(kf_id):
        system.older_pending = None
        return
    kf = system.backend.keyframe(kf_id)
    moved = propagate_back(system.imu, [s for s, _ in older], kf.ts, kf.T_w_b, kf.v_w, kf.bias)
    T_kf_w = inv_T(kf.T_w_b)
    for (_, rec), (_, T) in zip(reversed(older), moved, strict=True):
        rec.T_rel = T_kf_w @ T


def withdraw_diverged(system) -> str:
    """Take a diverged estimate out of the trajectory, before its window is cleared. Returns a phrase for the log.

    - The records of the current segment after its last frame with visual tracking (``system.t_visual``; all of
      them when it never held it) are withdrawn, with their keyframes' final poses. The next start integrates the
      IMU back over them (:func:`repose_diverged`).
    - The failed window's other keyframes keep the pose each had after its own solve, not the failed one's, and its
      landmarks are not kept as map points.
    - When poses of the segment stay, the next start opens a new segment (its own frame), as after an IMU gap.

    Before, every diverged pose stayed, in one frame with the next start's: on the realistic ``handheld`` seed 289 a
    start turning in place with a 0.08 rad/s gyroscope bias error never made a landmark, and its 6.2 s of IMU
    drift up to the divergence (15 m/s) were reported as tracking (5.38 m SE(3); 84 mm with the IMU integrated
    back from the next start)."""
    m, seg = system.map, system.segment
    mine = [r for r in system.records if r.segment == seg]
    t_cut = (mine[0].ts if mine else None) if system.t_visual is None else system.t_visual + 1
    drop = [] if t_cut is None else [r for r in mine if r.ts >= t_cut]
    if drop:
        gone = {r.ref_kf for r in drop} | {k for k, (t, _) in m.history.items() if t >= t_cut}
        ids = {id(r) for r in drop}
        system.records = [r for r in system.records if id(r) not in ids]
        for k in gone - {r.ref_kf for r in system.records}:
            m.history.pop(k, None)
        system.diverged_pending = [Snapshot(r.frame_idx, r.ts, None) for r in drop]
    m.landmarks = {}  # placed by the failed solve: not kept as map points
    online = {r.ref_kf: r.T_online for r in system.records if r.is_kf and r.segment == seg}
    for k in m.active:
        if k in m.history and k in online:
            m.history[k] = (m.history[k][0], online[k].copy())
    if any(r.segment == seg for r in system.records):
        system.segment += 1
    if not drop:
        return "no pose withdrawn"
    t0, t1 = ns_to_s(drop[0].ts - system.t_first), ns_to_s(drop[-1].ts - system.t_first)
    return f"{len(drop)} poses of the diverged estimate withdrawn ({t0:.2f}-{t1:.2f} s after the first frame)"


def repose_diverged(system, st: StartState) -> None:
    """Give the start ``st`` the withdrawn frames of a diverged estimate (:func:`withdraw_diverged`) up to
    ``backfill_s`` before its first keyframe, to be integrated back on the IMU like the frames kept from before any
    start (``imu_backfill``); older ones stay without a pose. After a start turning in place (its velocity taken as
    0) they are kept for its restart in motion (:func:`try_restart`), which poses them again. The counts go to
    ``st.info``."""
    pending = system.diverged_pending
    if not pending:
        return
    if st.method != "hover":
        system.diverged_pending = []
    snap0, T0, v0 = st.keyframes[0]
    t_own = min([s.ts for s, _ in st.frames] + [snap0.ts])
    oldest = snap0.ts - s_to_ns(system.cfg.dynamic_init.backfill_s)
    older = [s for s in pending if oldest <= s.ts < t_own]
    st.frames.extend(propagate_back(system.imu, older, snap0.ts, T0, v0, st.bias))
    st.info.update(diverged_reposed=len(older), diverged_unposed=sum(s.ts < oldest for s in pending))


def adapt_imu_noise(system, t0: int, t1: int) -> tuple[float, float] | None:
    """Raise the IMU white-noise densities to the level measured over ``[t0, t1)`` (from the samples' second
    differences, :func:`runtime.init.imu_rest_stats`: white noise plus vibration, which a MAV IMU's sensor.yaml
    densities leave out, and not the motion).
    Returns the (gyro, accel) multipliers, None when left as configured."""
    c = system.cfg.imu
    its, g, a = system.imu.window(t0, t1)
    if not c.adapt_noise or its.size < 20:
        return None
    st = imu_rest_stats(its, g, a, system.cfg.init.block_s, c.gravity)
    root_rate = np.sqrt(float(system.imu.rate_hz))
    meas = (st.gyro_noise / root_rate, st.accel_noise / root_rate)  # densities
    stated = (system.imu_params.gyro_noise_density, system.imu_params.accel_noise_density)
    scales = tuple(float(np.clip(m / s, c.noise_scale, c.max_noise_scale)) for m, s in zip(meas, stated, strict=True))
    if max(scales) <= 1.5 * c.noise_scale:
        return None
    system.pim_params = preintegration_params(system.imu_params, c, scales)
    system.backend.preint_params = system.pim_params
    system.event(
        t1,
        f"IMU noisier than its calibration (vibration?): measured {meas[0]:.2e} rad/s/sqrt(Hz), "
        f"{meas[1]:.2e} m/s^2/sqrt(Hz); white-noise densities raised x{scales[0]:.1f} (gyro), "
        f"x{scales[1]:.1f} (accel)",
        logging.INFO,
    )
    return scales


def try_restart(system, frame_idx: int, ts: int, image, feats) -> bool:
    """Re-initialise in motion, within the current map frame, once structure from motion works, within
    ``refine_within_s``. Returns True when it did. Two cases arm it:

    - After a start while turning in place (velocity taken as 0): over all frames since the first, which then take
      the new poses. From ``restart_recent_after_s`` after the start on, when those frames fail (too few tracks
      common to the first and the newest on a bare wall), a recent window as a first in-motion start takes it, the
      older frames integrated back from it: on the realistic ``handheld`` seed 102 a start turning in place had read
      0.38 m/s of translation as a 0.05 rad/s gyroscope bias, and no restart over every frame came (12.3 m; 48.1 mm
      with the fallback).
    - After a loss of visual tracking while the front end still holds ``restart_lost_min_tracks`` tracks, or after
      ``building_restart_s`` of a map that acquires no visual tracking with as many in view
      (``system.restart_why`` says which): the window's estimate disagrees with a textured view. Over a
      recent window;
      every record of the last ``backfill_s`` older than it is integrated back from the new state on the IMU. On
      ``handheld`` seed 115 a restart with a 5.5x scale lost every landmark while 176 tracks were in view, and the
      run diverged (14.3 m; 39 mm with this restart). Tracking regained (or acquired) first cancels it.

    (Restarting after any long loss of visual tracking was tried and removed: on the synthetic test with tracking
    forced lost, restarts every second gave ATE 0.46 m; bridging on the IMU and triangulating from the coasted
    keyframes keeps it at centimetres. A bare view is not a disagreement.)"""
    loss = system.restart_why
    if system.restart_until is not None and ts > system.restart_until:
        system.restart_until, system.restart_why = None, None
        system.diverged_pending = []  # as the start turning in place posed them
        what = loss or "after the start turning in place"
        system.event(ts, f"no in-motion re-initialisation {what}: keeping the estimate")
    run = system.initializer
    if system.restart_until is None:
        if run.frames:
            run.reset()
        return False
    d = system.cfg.dynamic_init
    since = None if loss else system.t_first
    keep = max(system.t_first, ts - s_to_ns(d.backfill_s)) if loss else since
    run.add(Snapshot(frame_idx, ts, feats, image if system.dense is not None else None), keep_since=keep)
    started = system.restart_until - s_to_ns(d.refine_within_s)  # the start turning in place
    after = d.restart_recent_after_s
    recent_from = started + s_to_ns(after) if np.isfinite(after) and not loss else None
    st = run.try_motion(ts, allow_hover=False, since=since, recent_from=recent_from)
    if st is None:
        return False
    repose_diverged(system, st)
    if loss:  # the records of the estimate that lost the view, from the new state backwards
        snap0, T0, v0 = st.keyframes[0]
        kept = {s.ts for s, _ in st.frames}
        older = [
            Snapshot(r.frame_idx, r.ts, None) for r in system.records if keep <= r.ts < snap0.ts and r.ts not in kept
        ]
        st.frames.extend(propagate_back(system.imu, older, snap0.ts, T0, v0, st.bias))
    A = frame_alignment(system.T_cur, st.keyframes[-1][1])
    system.backend.clear_window()
    system.track_obs = {}
    kf_ids = seed_window(system, st, A)
    t0 = min([k[0].ts for k in st.keyframes] + [f[0].ts for f in st.frames])
    system.records = [r for r in system.records if r.ts < t0]  # the frames since take the new solution
    kept = {r.ref_kf for r in system.records} | set(kf_ids)
    for k in [k for k in system.map.history if k not in kept]:  # the discarded start's keyframes
        del system.map.history[k]
    moved = StartState(
        st.method,
        [(s, A @ T, v) for s, T, v in st.keyframes],
        st.bias,
        [(s, A @ T) for s, T in st.frames],
        t_window=st.t_window,
    )
    backfill_records(system, moved, kf_ids)
    system.last_kf_feats = feats
    system.lost, system.acquired, system.building, system.building_since = False, False, False, None
    system.restart_until, system.reloc_pending = None, None
    run.reset()
    why = loss or "after a start turning in place"
    system.restart_why = None
    system.restarts.append({"t_s": round(ns_to_s(ts), 4), "why": why, **st.info})
    system.event(ts, f"re-initialised in motion {why}, same map frame: {st.info}")
    return True
