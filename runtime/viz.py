"""Optional Rerun recording of a SLAM run (``dit-slam viz=rerun``): images, tracks, camera, trajectory, sparse and
dense maps.

Written to an ``.rrd`` file (open with ``rerun slam.rrd``). Needs ``rerun-sdk`` (``pip install rerun-sdk``);
nothing else in the runtime imports it. Images are JPEG-compressed and logged every ``image_every`` frames and
at keyframes, so that a 60 s run stays a few tens of megabytes.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from runtime.geometry import Camera


class RerunRecorder:
    """Logs the system state frame by frame into ``path`` (an ``.rrd`` file).

    Args:
        path: output ``.rrd`` file.
        camera: the raw camera (for the pinhole frustum).
        T_b_c: (4, 4) camera-to-body.
        image_every: log the image every n-th frame (and at every keyframe).
    """

    def __init__(self, path: str | Path, camera: Camera, T_b_c: np.ndarray, image_every: int = 4) -> None:
        try:
            import rerun as rr
        except ImportError as e:
            raise ImportError("viz=rerun needs the rerun-sdk package: pip install rerun-sdk") from e
        self.rr = rr
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.rec = rr.RecordingStream("dit-slam")
        self.rec.save(str(self.path))
        self.camera = camera
        self.T_b_c = np.asarray(T_b_c, dtype=np.float64)
        self.image_every = max(1, int(image_every))
        self.n = 0
        self.positions: list[np.ndarray] = []
        self.rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        self.rec.log(
            "world/camera/image",
            rr.Pinhole(image_from_camera=camera.K, width=camera.width, height=camera.height),
            static=True,
        )

    def log_frame(self, system, ts: int, image: np.ndarray, record) -> None:
        """Log one processed frame (``record`` is the system's FrameRecord or None before initialisation)."""
        rr, rec = self.rr, self.rec
        self.n += 1
        rec.set_time("time", duration=ts * 1e-9)
        is_kf = bool(record is not None and record.is_kf)
        if self.n % self.image_every == 1 or is_kf or self.image_every == 1:
            rec.log("world/camera/image", rr.Image(image).compress(jpeg_quality=70))
        f = system.tracker.current(ts)
        if f.ids.size:
            is_lm = np.array([system.map.is_landmark(j) for j in f.ids], dtype=bool)
            colors = np.where(is_lm[:, None], [[40, 220, 60]], [[240, 160, 30]]).astype(np.uint8)
            rec.log("world/camera/image/tracks", rr.Points2D(f.uv, colors=colors, radii=2.0))
        if record is None:
            return
        T_w_c = record.T_online @ self.T_b_c
        rec.log("world/camera", rr.Transform3D(translation=T_w_c[:3, 3], mat3x3=T_w_c[:3, :3]))
        self.positions.append(record.T_online[:3, 3].copy())
        if len(self.positions) % 10 == 0 or is_kf:
            rec.log("world/trajectory", rr.LineStrips3D([np.array(self.positions)], colors=[[230, 60, 60]]))
        if is_kf:
            _, X_w = system.map.landmark_arrays()
            if X_w.shape[0]:
                rec.log("world/window_landmarks", rr.Points3D(X_w, colors=[[40, 220, 60]], radii=0.01))

    def log_final(
        self,
        system,
        ts: np.ndarray,
        T: np.ndarray,
        points: np.ndarray,
        dense_map: tuple[np.ndarray, np.ndarray | None] | None = None,
    ) -> None:
        """The final (refined) trajectory, the whole sparse map and, with ``dense=true``, the local dense map
        (``dense_map``: (N, 3) world points and (N, 3) uint8 colours or None, as in ``dense_map.ply``)."""
        rr, rec = self.rr, self.rec
        if len(ts):
            rec.set_time("time", duration=float(ts[-1]) * 1e-9)
            rec.log("world/trajectory_final", rr.LineStrips3D([T[:, :3, 3]], colors=[[60, 120, 240]]))
        if points.shape[0]:
            rec.log("world/sparse_map", rr.Points3D(points, colors=[[200, 200, 200]], radii=0.008))
        if dense_map is not None and dense_map[0].shape[0]:
            xyz, rgb = dense_map
            rec.log("world/dense_map", rr.Points3D(xyz, colors=rgb, radii=0.004))

    def close(self) -> None:
        self.rec.flush()
        self.rec.disconnect()
