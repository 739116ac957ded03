"""Priors on keyframe states: the initial gauge, marginal priors from eliminated states, and the visual fix.

What the window knows of the keyframes that left it is carried as a Gaussian prior on the oldest active
keyframe's ``X, V, B``: a partial elimination (:func:`eliminate`) of the leaving states, kept as
``LinearContainerFactor`` s linearised at the remaining state (:func:`linear_prior`).
"""

from __future__ import annotations

import logging

import numpy as np

from runtime.backend.factors import pose_prior_noise_world
from runtime.backend.imu import make_bias
from runtime.backend.state import Keyframe, MapState, insert_state, keys
from runtime.geometry import to_pose3

log = logging.getLogger(__name__)


def state_priors(k: int, T_w_b, v_w, bias, pose_noise, vel_sigma: float, bias_sigmas) -> list:
    """Prior factors on keyframe ``k``'s pose (noise model ``pose_noise``), velocity (isotropic ``vel_sigma``)
    and bias (diagonal ``bias_sigmas``: 3 accelerometer then 3 gyroscope)."""
    import gtsam

    X, V, B, _, _ = keys()
    return [
        gtsam.PriorFactorPose3(X(k), to_pose3(T_w_b), pose_noise),
        gtsam.PriorFactorVector(V(k), v_w, gtsam.noiseModel.Isotropic.Sigma(3, float(vel_sigma))),
        gtsam.PriorFactorConstantBias(
            B(k), make_bias(bias), gtsam.noiseModel.Diagonal.Sigmas(np.asarray(bias_sigmas, np.float64))
        ),
    ]


def gravity_aligned_priors(kf: Keyframe, roll_pitch_sigma, yaw_sigma, pos_sigma, vel_sigma, bias_sigmas) -> list:
    """:func:`state_priors` around ``kf``'s state with the pose's rotation noise in the world frame (roll and
    pitch are observable from gravity, yaw and position are the gauge)."""
    pose_noise = pose_prior_noise_world(
        kf.T_w_b[:3, :3], np.array([roll_pitch_sigma, roll_pitch_sigma, yaw_sigma]), pos_sigma
    )
    return state_priors(kf.kf_id, kf.T_w_b, kf.v_w, kf.bias, pose_noise, vel_sigma, bias_sigmas)


def linear_prior(remaining, lin_pt) -> list:
    """The factors left by a partial elimination, as nonlinear factors linearised at ``lin_pt``."""
    import gtsam

    return [
        gtsam.LinearContainerFactor(remaining.at(i), lin_pt)
        for i in range(remaining.size())
        if remaining.at(i) is not None
    ]


def eliminate(factors: list, states: list[Keyframe], eliminated: list, keep: Keyframe) -> list:
    """Eliminate the keys ``eliminated`` from ``factors`` linearised at ``states``; the prior left on the
    remaining keys, linearised at ``keep``'s state. Raises RuntimeError when the system is indeterminate."""
    import gtsam

    fg = gtsam.NonlinearFactorGraph()
    for f in factors:
        fg.add(f)
    vals = gtsam.Values()
    for kf in states:
        insert_state(vals, kf.kf_id, kf.T_w_b, kf.v_w, kf.bias)
    ordering = gtsam.Ordering()
    for key in eliminated:
        ordering.push_back(key)
    _, remaining = fg.linearize(vals).eliminatePartialSequential(ordering)
    lin_pt = gtsam.Values()
    insert_state(lin_pt, keep.kf_id, keep.T_w_b, keep.v_w, keep.bias)
    return linear_prior(remaining, lin_pt)


def visual_prior(window: MapState, prior_factors: list, o: int, fix_sigma: float, min_landmarks: int):
    """The prior on ``X, V, B`` of keyframe ``o`` plus a visual fix of its pose, as linear factors.

    The fix is what ``o``'s own observations say about its pose with its landmarks held near their current
    estimates (``fix_sigma`` [m]): the map's word on where ``o`` is. Marginalising ``o`` with it and the link
    ``o -> n`` hands that information on: the window keeps a visually informed position and velocity when every
    landmark has gone (a textureless stretch). It is cheap (``o``'s factors only, no Schur complement over the
    window) and counts only ``o``'s own visual information twice (its observations stay in the window through
    its anchor); the inertial chain and the biases are never duplicated. Returns None (use the plain prior)
    when ``o`` sees fewer than ``min_landmarks`` landmarks.
    """
    import gtsam

    _, _, _, L, _ = keys()
    obs = [j for j in window.kf_obs.get(o, ()) if j in window.landmarks and o in window.landmarks[j].factors]
    if len(obs) < min_landmarks:
        return None
    kf = window.keyframes[o]
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    insert_state(values, o, kf.T_w_b, kf.v_w, kf.bias)
    for f in prior_factors:
        graph.add(f)
    fix = gtsam.noiseModel.Isotropic.Sigma(3, fix_sigma)
    lm_order = gtsam.Ordering()
    for j in obs:
        lm = window.landmarks[j]
        values.insert(L(j), lm.X_w)
        graph.add(lm.factors[o])
        graph.add(gtsam.PriorFactorPoint3(L(j), lm.X_w, fix))
        lm_order.push_back(L(j))
    try:
        _, remaining = graph.linearize(values).eliminatePartialSequential(lm_order)
    except RuntimeError as e:
        log.info("backend: visual fix of keyframe %d unavailable (%s)", o, str(e).splitlines()[0][:120])
        return None
    lin_pt = gtsam.Values()
    insert_state(lin_pt, o, kf.T_w_b, kf.v_w, kf.bias)
    return linear_prior(remaining, lin_pt)


def carried_prior(chain: list[Keyframe], anchor_priors: list, links: dict, keep: Keyframe) -> list:
    """The prior on ``keep`` (the oldest active keyframe) from the anchor prior of ``chain[0]`` and the archived
    ``links`` (``kf_id -> factors`` to its predecessor) along ``chain`` up to ``keep``, linearised at the chain's
    states (the window's own links are not in it). Raises RuntimeError when indeterminate."""
    X, V, B, _, _ = keys()
    factors, states, elim = list(anchor_priors), [], []
    for kf in chain:
        k = kf.kf_id
        if k > keep.kf_id:
            break
        if kf is not chain[0]:
            factors += links.get(k, ())
        if k != keep.kf_id:
            elim += [X(k), V(k), B(k)]
        states.append(kf)
    return eliminate(factors, states, elim, keep)


def gap_link(i: int, kf: Keyframe, cfg) -> list:
    """In place of an IMU factor from keyframe ``i`` to ``kf`` (an IMU gap): the bias continues through a
    between factor, the pose and velocity get loose priors around ``kf``'s values (``cfg``: BackendConfig)."""
    import gtsam

    X, V, B, _, _ = keys()
    j = kf.kf_id
    bias_noise = np.array([cfg.prior_acc_bias_sigma] * 3 + [cfg.prior_gyro_bias_sigma] * 3)
    return [
        gtsam.BetweenFactorConstantBias(
            B(i), B(j), gtsam.imuBias.ConstantBias(), gtsam.noiseModel.Diagonal.Sigmas(bias_noise)
        ),
        gtsam.PriorFactorVector(V(j), kf.v_w, gtsam.noiseModel.Isotropic.Sigma(3, cfg.gap_vel_sigma)),
        gtsam.PriorFactorPose3(
            X(j),
            to_pose3(kf.T_w_b),
            gtsam.noiseModel.Diagonal.Sigmas(np.array([cfg.gap_rot_sigma] * 3 + [cfg.gap_pos_sigma] * 3)),
        ),
    ]


def zero_motion(i: int, j: int, cfg) -> tuple:
    """Keyframes ``i`` and ``j`` taken at rest: a zero-motion between factor and a zero-velocity prior on ``j``."""
    import gtsam

    X, V, _, _, _ = keys()
    between = gtsam.BetweenFactorPose3(
        X(i),
        X(j),
        gtsam.Pose3.Identity(),
        gtsam.noiseModel.Diagonal.Sigmas(np.array([cfg.still_rot_sigma] * 3 + [cfg.still_pos_sigma] * 3)),
    )
    vel = gtsam.PriorFactorVector(V(j), np.zeros(3), gtsam.noiseModel.Isotropic.Sigma(3, cfg.still_vel_sigma))
    return between, vel
