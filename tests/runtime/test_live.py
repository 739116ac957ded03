"""The live API: samples fed in a shuffled but causal order (IMU up to 50 ms late) give the batch trajectory."""

import numpy as np
import pytest

from runtime.backend.imu import ImuStream
from runtime.io.euroc import read_euroc
from runtime.live import GrowingImuStream, LiveSlam
from runtime.slam import SlamSystem

sim_euroc = pytest.importorskip("sim.euroc")


@pytest.fixture(scope="module")
def seq(tmp_path_factory):
    out = tmp_path_factory.mktemp("live") / "seq"
    return read_euroc(
        sim_euroc.write_euroc_sequence(
            out, "textured", duration=4.5, seed=3, imu_noise=True, progress=False, scale=0.5, realism=False
        )
    )


def _arrivals(seq, seed: int, imu_late_ns: int = 50_000_000):
    """(arrival time, kind, index): IMU samples up to ``imu_late_ns`` late (in order among themselves), images
    up to 5 ms late; an image may therefore arrive long before the IMU that covers it."""
    rng = np.random.default_rng(seed)
    imu_arr = np.maximum.accumulate(seq.imu_ts + rng.integers(0, imu_late_ns, seq.imu_ts.size))
    img_arr = seq.frame_ts + rng.integers(0, 5_000_000, len(seq))
    ev = [(int(t), 0, k) for k, t in enumerate(imu_arr)] + [(int(t), 1, k) for k, t in enumerate(img_arr)]
    return sorted(ev)


def test_shuffled_causal_order_gives_the_batch_trajectory(seq):
    batch = SlamSystem(seq.camera, seq.T_b_c, ImuStream.from_sequence(seq), seq.imu)
    for i in range(len(seq)):
        batch.process(i, int(seq.frame_ts[i]), seq.image(i))
    ts_b, T_b = batch.trajectory()
    assert len(ts_b) > 20

    states, kfs, maps, depths = [], [], [], []
    live = LiveSlam(
        seq.camera,
        seq.T_b_c,
        seq.imu,
        on_keyframe=kfs.append,
        on_map=lambda ids, X: maps.append((ids.copy(), X.copy())),
        on_depth=lambda k, d: depths.append(k),
    )
    max_pending = 0
    for _, kind, k in _arrivals(seq, seed=7):
        if kind == 0:
            states += live.add_imu(int(seq.imu_ts[k]), seq.gyro[k], seq.accel[k])
        else:
            st = live.add_image(int(seq.frame_ts[k]), seq.image(k))
            states += [st] if st is not None else []
        max_pending = max(max_pending, live.n_pending)
    m = live.close()
    ts_l, T_l = live.trajectory()
    assert max_pending >= 1  # images did wait for the IMU
    assert np.array_equal(ts_l, ts_b) and np.array_equal(T_l, T_b)  # bit-identical
    assert m["frames"] == len(seq) and len(states) + live.n_pending <= len(seq)
    assert [s.ts for s in kfs] == [s.ts for s in states if s.is_keyframe] and len(kfs) == m["keyframes"] > 2
    assert len(maps) == len(kfs) and not depths  # the map after every keyframe; no depth without dense
    ids, X = live.system.map.all_points()
    assert np.array_equal(np.sort(maps[-1][0]), np.sort(ids)) and np.isfinite(maps[-1][1]).all()
    assert maps[-1][0].size > maps[0][0].size  # the map grows
    last = [s for s in states if s.initialized][-1]
    assert last.T_w_b.shape == (4, 4) and np.array_equal(last.T_w_b, batch.records[-1].T_online)


def test_growing_imu_stream_matches_the_batch_stream():
    rng = np.random.default_rng(0)
    ts = np.cumsum(rng.integers(4_000_000, 6_000_000, 50)).astype(np.int64)
    g, a = rng.normal(size=(50, 3)), rng.normal(size=(50, 3))
    g[10] = np.nan
    ref = ImuStream(ts, g, a, 200.0)
    live = GrowingImuStream(200.0)
    for k in range(50):
        live.append(int(ts[k]), g[k], a[k])
    assert len(live) == 49 and live.dropped_ts.tolist() == [ts[10]]
    for t0, t1 in ((ts[3], ts[20] + 7), (ts[0] - 5, ts[2])):
        for x, y in zip(live.segment(int(t0), int(t1)), ref.segment(int(t0), int(t1)), strict=True):
            assert np.array_equal(x, y)
    with pytest.raises(ValueError, match="not after the previous one"):
        live.append(int(ts[-1]), g[0], a[0])
