"""Synthetic sequences rendered once into a cache folder and reused (the default data of ``dit-slam``)."""

from __future__ import annotations

import json
from pathlib import Path

from sim.euroc import write_euroc_sequence


def cached_sequence(
    preset: str,
    duration: float,
    seed: int,
    imu_noise: bool,
    cache_dir: str | Path,
    progress: bool = True,
    realism: bool = True,
) -> Path:
    """The synthetic sequence of these settings in ``cache_dir``, rendered on first use, reused after."""
    tag = ("" if imu_noise else "_exact") + ("" if realism else "_synthetic")
    cache = Path(cache_dir) / f"euroc_{preset}_{duration:g}s_s{seed}{tag}"
    info = cache / "sim_info.json"
    if info.is_file() and (cache / "mav0" / "cam0" / "data.csv").is_file():
        meta = json.loads(info.read_text())
        complete = meta.get("complete", True)  # sim_info.json says false while (or if) the rendering stopped
        key = (
            meta.get("preset"),
            float(meta.get("duration_s", -1)),
            int(meta.get("seed", -1)),
            bool(meta.get("imu_noise")),
            bool(meta.get("realism")),
        )
        if complete and key == (preset, float(duration), int(seed), bool(imu_noise), bool(realism)):
            return cache
    print(f"rendering the synthetic sequence ({preset}, {duration:g} s, seed {seed}) into {cache}")
    return Path(
        write_euroc_sequence(
            cache,
            preset=preset,
            duration=float(duration),
            seed=int(seed),
            imu_noise=bool(imu_noise),
            progress=progress,
            realism=bool(realism),
        )
    )
