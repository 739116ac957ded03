"""Fixtures of the training tests: a tiny NYU-layout data set and Hydra configs at 64x64."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

REPO = Path(__file__).resolve().parents[2]
CONF = REPO / "conf"


def write_fake_nyu(
    root: Path, n_train: int = 8, n_val: int = 4, hw: tuple[int, int] = (60, 80), seed: int = 0
) -> Path:
    """Frames in the sparse-to-dense layout: a slanted floor + boxes; image texture shaded by depth.

    Depth is in [1, 4] m with a few invalid (0) pixels; the image is a blurred random texture times a depth
    shading, so that FAST finds corners and the depth is learnable from the image.
    """
    import cv2

    rng = np.random.default_rng(seed)
    h, w = hw
    for split, n in (("train", n_train), ("val", n_val)):
        for i in range(n):
            d = np.linspace(1.5, 3.5, h, dtype=np.float32)[:, None].repeat(w, 1)
            for _ in range(3):
                y0, x0 = rng.integers(0, h - 10), rng.integers(0, w - 10)
                d[y0 : y0 + rng.integers(6, 20), x0 : x0 + rng.integers(6, 20)] = rng.uniform(1.0, 4.0)
            d[rng.random((h, w)) < 0.02] = 0.0
            tex = cv2.GaussianBlur(rng.random((h, w)).astype(np.float32), (3, 3), 0)
            shade = 1.0 - (d - 1.0) / 4.0
            rgb = np.clip(np.stack([tex * shade, tex, shade], 0) * 255, 0, 255).astype(np.uint8)
            p = root / split / f"scene_{i % 2:02d}" / f"{i:05d}.h5"
            p.parent.mkdir(parents=True, exist_ok=True)
            with h5py.File(p, "w") as f:
                f["rgb"] = rgb
                f["depth"] = d
    return root


@pytest.fixture(scope="session")
def fake_nyu(tmp_path_factory) -> Path:
    return write_fake_nyu(tmp_path_factory.mktemp("nyu"))


@pytest.fixture(autouse=True)
def _one_thread():
    torch.set_num_threads(1)
    yield


def tiny_overrides(root: Path, out: Path) -> list[str]:
    """Overrides for a seconds-long CPU run at 64x64 on the fake set."""
    return [
        "data=nyu_h5",
        f"data.root={root}",
        "data.height=64",
        "data.width=64",
        "data.batch_size=2",
        "data.val_batch_size=2",
        "model.net.width_mult=0.25",
        "trainer.max_steps=4",
        "trainer.val_check_interval=2",
        "trainer.log_every_n_steps=1",
        "trainer.enable_progress_bar=false",
        "trainer.enable_model_summary=false",
        "callbacks.last_checkpoint.every_n_train_steps=2",
        "logger.tensorboard=null",
        "num_threads=1",
        f"paths.output_dir={out}",
        f"hydra.run.dir={out}",
    ]


def compose_fit(overrides: list[str]):
    """Compose ``conf/fit.yaml`` with overrides (no Hydra run: ``paths.output_dir`` must be given)."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose(config_name="fit", overrides=overrides)
