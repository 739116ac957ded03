"""The archive of marginalised keyframes and the coast bridge (relocalisation after a loss of visual tracking).

While the camera sees nothing usable (a white wall), the window coasts on the IMU. Marginalised keyframes of
the last ``archive_s`` seconds keep their final state, the factors that linked them (IMU, zero motion) and what
the window knew of their state when they left (their marginal prior with their own visual fix). When a
relocalisation gives a PnP pose, the coasted stretch is re-estimated over those links between the last visual
fix before the loss (the anchor) and the relocalised keyframe (:func:`smooth_chain`): velocities and biases
are re-estimated with the poses, so a systematic drift is explained rather than spread. The stretch then stays
in the window's optimisations (a :class:`Coast`) until the relocalised keyframe leaves the window, so the
visual tracking after the relocalisation reaches back into the coast.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from runtime.backend.priors import state_priors
from runtime.backend.state import Keyframe, insert_state, keys
from runtime.geometry import to_pose3

log = logging.getLogger(__name__)


@dataclass
class CoastConfig:
    """The archive and the coast bridge."""

    archive_s: float = 60.0  # s, marginalised keyframes' states and inertial links kept for a coast bridge
    fix_rot_sigma: float = 0.01  # rad, the PnP pose of the relocalised keyframe
    fix_pos_sigma: float = 0.03  # m
    # the anchor's prior when the archive no longer holds its marginal (else the marginal is used)
    anchor_rot_sigma: float = 0.005  # rad
    anchor_pos_sigma: float = 0.01  # m
    anchor_vel_sigma: float = 0.05  # m/s
    anchor_acc_bias_sigma: float = 0.05  # m/s^2
    anchor_gyro_bias_sigma: float = 0.002  # rad/s
    lm_max_iterations: int = 50
    lm_relative_tol: float = 1e-6


@dataclass
class Coast:
    """A re-estimated coast that stays in the window's optimisations."""

    anchor: int  # kf_id of the last keyframe tracked visually before the loss
    anchor_priors: list  # the bridge's priors on the anchor's X, V, B
    until: int  # the relocalised keyframe: the coast leaves the smoother with it


class CoastArchive:
    """Marginalised keyframes' states, links and marginal priors, and the coast kept in the smoother."""

    def __init__(self, cfg: CoastConfig) -> None:
        self.cfg = cfg
        self.clear()

    def clear(self) -> None:
        self.states: dict[int, Keyframe] = {}
        self.links: dict[int, list] = {}  # factors to the predecessor (IMU, zero motion) and zero-velocity priors
        self.priors: dict[int, list] = {}  # what was known of X, V, B when the keyframe left
        self.coast: Coast | None = None

    def keep(self, kf: Keyframe, own_prior: list) -> None:
        """Archive a keyframe leaving the window with the prior it was marginalised with."""
        self.priors[kf.kf_id] = own_prior
        self.states[kf.kf_id] = kf.copy_state()

    def add_link(self, k: int, factors: list) -> None:
        self.links.setdefault(k, []).extend(factors)

    def prune(self, t_keep: int) -> None:
        """Forget keyframes older than ``t_keep`` (ns)."""
        for k in [k for k, a in self.states.items() if a.ts < t_keep]:
            del self.states[k]
            self.links.pop(k, None)
            self.priors.pop(k, None)

    def end_coast_with(self, kf_id: int) -> None:
        """Keyframe ``kf_id`` left the window: a coast that lasted until it leaves the smoother."""
        if self.coast is not None and self.coast.until == kf_id:
            self.coast = None

    def window_chain(self, active: list[int]) -> list[Keyframe] | None:
        """The archived keyframes of the coast kept in the smoother, from its anchor up to the oldest active
        keyframe (excluded); None when there is none, when the relocalised keyframe has left the window, or
        when the archive no longer holds an unbroken chain back to the anchor."""
        c = self.coast
        if c is None or c.until not in active:
            return None
        o = active[0]
        ids = sorted(k for k in self.states if c.anchor <= k < o)
        if not ids or ids[0] != c.anchor or any(k not in self.links for k in ids[1:] + [o]):
            return None
        return [self.states[k] for k in ids]

    def anchor_priors(self, anchor: Keyframe) -> list:
        """The anchor's marginal prior when archived, else a diagonal prior of the configured sigmas."""
        import gtsam

        if anchor.kf_id in self.priors:
            return self.priors[anchor.kf_id]
        c = self.cfg
        return state_priors(
            anchor.kf_id,
            anchor.T_w_b,
            anchor.v_w,
            anchor.bias,
            gtsam.noiseModel.Diagonal.Sigmas(np.array([c.anchor_rot_sigma] * 3 + [c.anchor_pos_sigma] * 3)),
            c.anchor_vel_sigma,
            [c.anchor_acc_bias_sigma] * 3 + [c.anchor_gyro_bias_sigma] * 3,
        )


def inertial_chain(states: dict[int, Keyframe], t_from: int, kf_id: int, link) -> list[Keyframe] | None:
    """Keyframes of ``states`` from the last one at or before ``t_from`` to ``kf_id``, or None when the states do
    not reach back that far or an IMU gap broke the inertial chain (``link(k)``: the factors to k's
    predecessor)."""
    import gtsam

    ids = sorted(k for k in states if k <= kf_id)
    before = [k for k in ids if states[k].ts <= t_from]
    if not before or kf_id not in states:
        return None
    chain = [states[k] for k in ids if k >= before[-1]]
    for kf in chain[1:]:
        if not any(isinstance(f, gtsam.CombinedImuFactor) for f in link(kf.kf_id)):
            return None
    return chain


def smooth_chain(chain: list[Keyframe], anchor_priors: list, link, kf_id: int, T_fix, cfg: CoastConfig, init=None):
    """LM over the chain's ``X, V, B``: the anchor prior, the links ``link(k)``, and the pose ``T_fix`` of
    ``kf_id``; start values ``init(ts) @ T`` (``init``: a world-frame correction, the anchor stays). Returns the
    GTSAM result, or None when LM fails."""
    import gtsam

    X, _, _, _, _ = keys()
    graph = gtsam.NonlinearFactorGraph()
    for f in anchor_priors:
        graph.add(f)
    for kf in chain[1:]:
        for f in link(kf.kf_id):
            graph.add(f)
    graph.add(
        gtsam.PriorFactorPose3(
            X(kf_id),
            to_pose3(T_fix),
            gtsam.noiseModel.Diagonal.Sigmas(np.array([cfg.fix_rot_sigma] * 3 + [cfg.fix_pos_sigma] * 3)),
        )
    )
    values = gtsam.Values()
    anchor = chain[0]
    for kf in chain:
        C = init(kf.ts) if init is not None and kf is not anchor else np.eye(4)
        insert_state(values, kf.kf_id, C @ kf.T_w_b, C[:3, :3] @ kf.v_w, kf.bias)
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(cfg.lm_max_iterations)
    params.setRelativeErrorTol(cfg.lm_relative_tol)
    try:
        return gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    except RuntimeError as e:
        log.warning("backend: coast bridge failed (%s)", str(e).splitlines()[0][:200])
        return None
