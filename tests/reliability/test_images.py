"""Loud degradation: 12-bit data in 16-bit PNGs (almost black after OpenCV's 8-bit conversion) and saturated
images are reported, in the log and in metrics.json."""

import shutil

import cv2
import numpy as np

from runtime.io.euroc import read_euroc
from runtime.run import run_sequence


def test_twelve_bit_data_in_sixteen_bit_pngs_is_reported(tiny_seq, tmp_path):
    root = tmp_path / "seq12"
    shutil.copytree(tiny_seq, root)
    for p in (root / "mav0" / "cam0" / "data").glob("*.png"):
        img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE).astype(np.uint16) * 16  # 12-bit values, 16-bit file
        cv2.imwrite(str(p), img)
    m = run_sequence(read_euroc(root), tmp_path / "o", progress=False, max_frames=5, plot=False)
    w = " | ".join(m["image_warnings"])
    assert "16-bit PNG whose maximum is" in w and "12-bit or less data" in w
    assert "the image is almost black" in w
    assert any("almost black" in e["message"] if isinstance(e, dict) else "almost black" in str(e) for e in m["events"])


def test_good_images_give_no_warning(tiny_seq, tmp_path):
    m = run_sequence(read_euroc(tiny_seq), tmp_path / "o", progress=False, max_frames=5, plot=False)
    assert m["image_warnings"] == []


def test_saturated_image_is_reported_once():
    from runtime.image_check import ImageCheck

    chk = ImageCheck()
    white = np.full((48, 64), 255, np.uint8)
    assert "100% of the pixels are saturated" in chk.look(0, white)[0]
    assert chk.look(20, white) == [] and chk.kinds() == ["saturated"]
