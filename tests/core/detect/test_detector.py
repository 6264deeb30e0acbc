"""Detector decoders, NMS, model resolution, and the real models' AP."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from zoffload.detect import models
from zoffload.detect.detector import Detector, decode_gfl, decode_yolox, nms
from zoffload.detect.models import ModelError, resolve
from zoffload.lab.eval.detection import person_ap50


def test_gfl_decoder_places_a_box_from_its_bin_distribution() -> None:
    size, stride = 32, 8  # a 4x4 grid
    cls = np.zeros((1, 16, 80), np.float32)
    reg = np.full((1, 16, 32), -50.0, np.float32)
    cell = 1 * 4 + 2  # row 1, column 2: centre (20, 12)
    cls[0, cell, 0] = 0.9
    # left 1 bin, top 2 bins, right 3 bins, bottom 0 bins (x stride 8)
    for side, b in enumerate([1, 2, 3, 0]):
        reg[0, cell, side * 8 + b] = 50.0
    boxes, scores, classes = decode_gfl([cls], [reg], [stride], size)
    assert classes.tolist() == [0]
    assert scores[0] == pytest.approx(0.9)
    np.testing.assert_allclose(boxes[0], [20 - 8, 12 - 16, 20 + 24, 12 + 0], atol=1e-3)


def test_gfl_decoder_rejects_a_grid_that_does_not_fit() -> None:
    with pytest.raises(ModelError):
        decode_gfl([np.zeros((1, 15, 80), np.float32)], [np.zeros((1, 15, 32), np.float32)], [8], 32)


def test_yolox_decoder_uses_grid_offsets_and_log_sizes() -> None:
    size = 32  # strides 8, 16, 32: 16 + 4 + 1 rows
    out = np.zeros((1, 21, 85), np.float32)
    row = 16 + 3  # stride 16, cell (x=1, y=1)
    out[0, row, :4] = [0.5, 0.25, np.log(2.0), np.log(1.0)]
    out[0, row, 4] = 0.8  # objectness
    out[0, row, 5 + 2] = 0.5  # class 2
    boxes, scores, classes = decode_yolox(out, size)
    assert classes.tolist() == [2] and scores[0] == pytest.approx(0.4)
    cx, cy, w, h = (1.5) * 16, (1.25) * 16, 32, 16
    np.testing.assert_allclose(boxes[0], [cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2], atol=1e-4)


def test_nms_is_class_aware_and_filters_by_confidence() -> None:
    boxes = np.array([[0, 0, 10, 10], [1, 1, 11, 11], [0, 0, 10, 10], [50, 50, 60, 60]], np.float32)
    scores = np.array([0.9, 0.8, 0.7, 0.2], np.float32)
    classes = np.array([0, 0, 1, 0])
    det = nms(boxes, scores, classes)
    # the 0.8 box overlaps the 0.9 box of its class (IoU 0.68) and goes; class 1 stays; 0.2 < 0.25
    assert det.scores.tolist() == pytest.approx([0.9, 0.7])
    assert det.classes.tolist() == [0, 1]
    assert len(nms(boxes, scores, classes, max_det=1)) == 1


def test_missing_model_names_where_it_looked(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("ZOFFLOAD_MODELS", str(tmp_path))
    monkeypatch.delenv("ZOFFLOAD_DATA", raising=False)
    monkeypatch.setattr(models, "SHARED_MODELS", tmp_path / "absent")
    with pytest.raises(ModelError, match=r"nanodet_m_320.onnx not found .*SHA-256"):
        resolve("nanodet-m")
    with pytest.raises(ModelError, match="does not exist"):
        resolve("nanodet-m", path=str(tmp_path / "nope.onnx"))
    with pytest.raises(ModelError, match="unknown detector"):
        resolve("resnet")


def test_download_is_kept_only_with_the_pinned_checksum(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                       models_dir: Path) -> None:
    monkeypatch.setattr(models, "SHARED_MODELS", tmp_path / "absent")
    monkeypatch.delenv("ZOFFLOAD_MODELS", raising=False)
    monkeypatch.delenv("ZOFFLOAD_DATA", raising=False)
    bogus = tmp_path / "bogus.onnx"
    bogus.write_bytes(b"not the model")
    with pytest.raises(ModelError, match="is not the pinned"):
        resolve("nanodet-m", url=bogus.as_uri(), cache=tmp_path / "cache")
    assert not (tmp_path / "cache" / "nanodet_m_320.onnx").exists()
    got = resolve("nanodet-m", url=(models_dir / "nanodet_m_320.onnx").as_uri(), cache=tmp_path / "cache")
    assert got == tmp_path / "cache" / "nanodet_m_320.onnx" and got.stat().st_size > 100_000


def test_a_file_that_is_not_onnx_is_a_model_error(tmp_path: Path) -> None:
    bad = tmp_path / "nanodet_m_320.onnx"
    bad.write_bytes(b"\x00garbage" * 100)
    with pytest.raises(ModelError, match="not a loadable ONNX model"):
        Detector("nanodet-m", path=str(bad))


def _person_ap50(name: str, coco: Path) -> float:
    return person_ap50(Detector(name), coco)


@pytest.mark.realdata
@pytest.mark.parametrize("name", ["nanodet-m", "picodet-s", "yolox-nano"])
def test_real_models_find_the_people_in_the_coco_dev_images(name: str, coco_dir: Path,
                                                           models_dir: Path) -> None:
    # Measured: nanodet-m 0.716, picodet-s 0.793, yolox-nano 0.705. A decoder off by half a cell or
    # a wrong channel order drops these by 0.1 or more (nanodet-m without its centred letterbox: 0.64)
    ap = _person_ap50(name, coco_dir)
    assert 0.68 <= ap <= 0.9
