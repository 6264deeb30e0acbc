"""ONNX detectors (NanoDet-m, PP-PicoDet-S, YOLOX-nano) through onnxruntime, with their decoders.

Every detector takes a BGR ``uint8`` image of any size and returns ``Detections`` in that image's
pixel coordinates, after the thesis' post-processing: confidence 0.25, class-aware NMS at IoU 0.45
(OpenCV's ``NMSBoxesBatched``), at most 1000 detections.

The network's input size is read from the ONNX graph (its first input, ``1x3xHxW``, float), not
from the model's name, so an export of the same family at another size (NanoDet-m 416, PicoDet-S
320, a non-square one) loads; the grid of every stride follows from that size, and the outputs are
checked against the family's layout before the first image.

Decoders (input/output layouts checked against the graphs with onnxruntime):

* ``gfl`` (NanoDet-m, PicoDet-S): per stride, class scores ``[1, N, 80]`` already through a
  sigmoid and box distributions ``[1, N, 4*bins]`` (left, top, right, bottom; 8 bins in the shipped
  exports). The distance of each side is the softmax-weighted bin index times the stride, measured
  from the cell's centre ``((x + 0.5)·s, (y + 0.5)·s)``; a stride's grid is ``ceil(H/s) x ceil(W/s)``.
  Input: NanoDet letterboxed (centred, black); PicoDet stretched to the input.
* ``yolox``: ``[1, rows, 85]`` raw grid outputs for strides 8/16/32 (centre offsets, log sizes,
  objectness, class scores: already sigmoid in this export), ``rows = sum (H//s)·(W//s)``;
  score = objectness × class score. Input: letterboxed top-left with pad value 114, BGR 0-255.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from zoffload.detect.models import ModelError, ModelSpec, resolve, spec

CONF = 0.25
NMS_IOU = 0.45
MAX_DET = 1000
NUM_CLASSES = 80  # COCO: class 0 = person

# Preprocessing per model (mean and std in the network's channel order)
_NANODET_MEAN = np.array([103.53, 116.28, 123.675], np.float32)
_NANODET_STD = np.array([57.375, 57.12, 58.395], np.float32)
_PICODET_MEAN = np.array([123.675, 116.28, 103.53], np.float32)
_PICODET_STD = np.array([58.395, 57.12, 57.375], np.float32)


@dataclass
class Detections:
    """Boxes ``[x1, y1, x2, y2]`` in the source image's pixels, scores, COCO class ids (0 = person)."""

    boxes: np.ndarray  # (n, 4) float32
    scores: np.ndarray  # (n,) float32
    classes: np.ndarray  # (n,) int32

    @staticmethod
    def empty() -> Detections:
        return Detections(np.zeros((0, 4), np.float32), np.zeros(0, np.float32), np.zeros(0, np.int32))

    def __len__(self) -> int:
        return len(self.scores)

    def of_class(self, cls: int) -> Detections:
        keep = self.classes == cls
        return Detections(self.boxes[keep], self.scores[keep], self.classes[keep])


def nms(boxes: np.ndarray, scores: np.ndarray, classes: np.ndarray, conf: float = CONF,
        iou: float = NMS_IOU, max_det: int = MAX_DET) -> Detections:
    """Confidence filter then class-aware NMS, best first, at most ``max_det``."""
    import cv2

    keep = scores >= conf
    boxes, scores, classes = boxes[keep], scores[keep], classes[keep]
    if len(scores) == 0:
        return Detections.empty()
    xywh = np.column_stack([boxes[:, :2], boxes[:, 2:] - boxes[:, :2]]).astype(np.float32)
    idx = np.asarray(cv2.dnn.NMSBoxesBatched(xywh.tolist(), scores.astype(float).tolist(),
                                             classes.astype(int).tolist(), conf, iou), np.int64).ravel()
    idx = idx[np.argsort(-scores[idx], kind="stable")][:max_det]
    return Detections(boxes[idx].astype(np.float32), scores[idx].astype(np.float32),
                      classes[idx].astype(np.int32))


def _softmax(x: np.ndarray, axis: int = -1) -> np.ndarray:
    e = np.exp(x - x.max(axis=axis, keepdims=True))
    return e / e.sum(axis=axis, keepdims=True)


def _hw(size: int | tuple[int, int]) -> tuple[int, int]:
    return (size, size) if isinstance(size, int) else (int(size[0]), int(size[1]))


def gfl_grid(size: int | tuple[int, int], stride: int) -> tuple[int, int]:
    """Rows and columns of a GFL head's grid at ``stride`` (the convolutions round up)."""
    h, w = _hw(size)
    return int(np.ceil(h / stride)), int(np.ceil(w / stride))


def yolox_grid(size: int | tuple[int, int], stride: int) -> tuple[int, int]:
    """Rows and columns of YOLOX's grid at ``stride`` (its exporter's meshgrid rounds down)."""
    h, w = _hw(size)
    return h // stride, w // stride


def decode_gfl(cls_maps: list[np.ndarray], reg_maps: list[np.ndarray], strides: list[int],
               size: int | tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Candidate boxes (network-input pixels), best score and class per anchor point; ``size`` is
    the network input's side or its (height, width)."""
    all_boxes, all_scores, all_cls = [], [], []
    for cls_m, reg_m, s in zip(cls_maps, reg_maps, strides, strict=True):
        rows, cols = gfl_grid(size, s)
        cls_m, reg_m = cls_m.reshape(-1, cls_m.shape[-1]), reg_m.reshape(-1, 4, reg_m.shape[-1] // 4)
        if cls_m.shape[0] != rows * cols:
            raise ModelError(f"stride {s}: {cls_m.shape[0]} anchors for a {rows}x{cols} grid")
        best = cls_m.argmax(axis=1)
        score = cls_m[np.arange(len(best)), best]
        keep = score >= CONF  # decode only what can survive the confidence filter
        if not keep.any():
            continue
        ys, xs = np.divmod(np.nonzero(keep)[0], cols)
        cx, cy = (xs + 0.5) * s, (ys + 0.5) * s
        bins = np.arange(reg_m.shape[-1], dtype=np.float32)
        dist = (_softmax(reg_m[keep]) * bins).sum(-1) * s  # (k, 4): left, top, right, bottom
        all_boxes.append(np.column_stack([cx - dist[:, 0], cy - dist[:, 1],
                                          cx + dist[:, 2], cy + dist[:, 3]]))
        all_scores.append(score[keep])
        all_cls.append(best[keep])
    if not all_boxes:
        return np.zeros((0, 4), np.float32), np.zeros(0, np.float32), np.zeros(0, np.int64)
    return np.concatenate(all_boxes), np.concatenate(all_scores), np.concatenate(all_cls)


def decode_yolox(out: np.ndarray, size: int | tuple[int, int], strides: tuple[int, ...] = (8, 16, 32)
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    out = out.reshape(-1, out.shape[-1])
    grids, exp_strides = [], []
    for s in strides:
        rows, cols = yolox_grid(size, s)
        ys, xs = np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij")
        grids.append(np.column_stack([xs.ravel(), ys.ravel()]))
        exp_strides.append(np.full((rows * cols, 1), s))
    grid, stride = np.concatenate(grids), np.concatenate(exp_strides)
    if len(grid) != len(out):
        h, w = _hw(size)
        raise ModelError(f"YOLOX output has {len(out)} rows, {len(grid)} expected at {w}x{h} px")
    cls = out[:, 5:]
    best = cls.argmax(axis=1)
    score = out[:, 4] * cls[np.arange(len(best)), best]
    keep = score >= CONF
    xy = (out[keep, :2] + grid[keep]) * stride[keep]
    wh = np.exp(out[keep, 2:4]) * stride[keep]
    boxes = np.column_stack([xy - wh / 2, xy + wh / 2])
    return boxes, score[keep], best[keep]


def shrink_size(width: int, height: int, input_hw: tuple[int, int], stretch: bool) -> tuple[int, int]:
    """The (width, height) a ``width`` x ``height`` frame can be shrunk to before it travels to a
    detector whose network input is ``input_hw`` (height, width), losing nothing the network sees:
    the size ``Detector.preprocess`` resizes it to (stretched to the input, or letterboxed at the
    one scale that fits), so the edge's own resize of the shrunk frame is the identity and the
    network gets the same pixels. Never larger than the frame in either direction (a side already
    below the input stays as it is)."""
    net_h, net_w = input_hw
    if stretch:
        return min(width, net_w), min(height, net_h)
    if min(net_h / height, net_w / width) >= 1.0:
        return width, height
    return letterbox_size(width, height, input_hw)


def letterbox_size(width: int, height: int, input_hw: tuple[int, int]) -> tuple[int, int]:
    """(width, height) of a frame letterboxed into ``input_hw`` (height, width) at the one scale
    that fits (``Detector.preprocess`` and ``shrink_size`` both use it; never a side of 0)."""
    net_h, net_w = input_hw
    r = min(net_h / height, net_w / width)
    return max(1, min(net_w, int(round(width * r)))), max(1, min(net_h, int(round(height * r))))


def resize_to(bgr: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """``bgr`` at ``size`` (width, height) with the interpolation ``Detector.preprocess`` uses
    (the robot shrinks frames with it, so the edge's resize of them is the identity)."""
    import cv2

    if size == (bgr.shape[1], bgr.shape[0]):
        return bgr
    return cv2.resize(bgr, size, interpolation=cv2.INTER_LINEAR)


def input_size(name: str, shape: list[Any], elem_type: str) -> tuple[int, int]:
    """The (height, width) of a detector input ``1x3xHxW`` float, or a ``ModelError`` saying why
    the graph's input is not one (a dynamic size, channels last, another element type)."""
    if len(shape) != 4 or shape[1] != 3:
        hint = " (channels last? export NCHW)" if len(shape) == 4 and shape[3] == 3 else ""
        raise ModelError(f"detector {name}: input {shape} is not 1x3xHxW{hint}")
    if shape[0] not in (1, None) and not isinstance(shape[0], str):
        raise ModelError(f"detector {name}: input batch {shape[0]}; export with batch 1")
    h, w = shape[2], shape[3]
    if not (isinstance(h, int) and isinstance(w, int)) or h < 32 or w < 32:
        raise ModelError(f"detector {name}: input {shape} has no fixed size of at least 32x32 "
                         "(export the model with a fixed input size, e.g. 1x3x416x416)")
    if elem_type != "tensor(float)":
        raise ModelError(f"detector {name}: input of type {elem_type}; float32 expected")
    return h, w


def gfl_heads(name: str, outputs: list[Any], size: tuple[int, int]
              ) -> tuple[list[str], list[str], list[int]]:
    """Class-score and box-bin output names per stride (finest first), and the strides, of a GFL
    head whose anchor counts fit the input ``size``; else a ``ModelError``."""
    shapes = [o.shape for o in outputs]
    layout = (f"detector {name}: outputs {shapes} are not a GFL head at {size[1]}x{size[0]} (per stride "
              f"class scores [1, N, {NUM_CLASSES}] and box bins [1, N, 4*bins])")
    if any(len(sh) != 3 or not all(isinstance(d, int) for d in sh) for sh in shapes):
        raise ModelError(layout)
    cls_outs = sorted((o for o in outputs if o.shape[-1] == NUM_CLASSES), key=lambda o: -o.shape[1])
    reg_outs = sorted((o for o in outputs if o.shape[-1] != NUM_CLASSES), key=lambda o: -o.shape[1])
    if (not cls_outs or len(cls_outs) != len(reg_outs) or len(cls_outs) + len(reg_outs) != len(outputs)
            or any(r.shape[-1] % 4 or r.shape[-1] < 8 for r in reg_outs)
            or [c.shape[1] for c in cls_outs] != [r.shape[1] for r in reg_outs]):
        raise ModelError(layout)
    by_count = {int(np.prod(gfl_grid(size, st))): st for st in (8, 16, 32, 64, 128)}
    counts = [c.shape[1] for c in cls_outs]
    if any(n not in by_count for n in counts) or len(set(counts)) != len(counts):
        raise ModelError(f"{layout}: anchor counts {counts} fit no set of strides 8-128 at that size")
    return [c.name for c in cls_outs], [r.name for r in reg_outs], [by_count[n] for n in counts]


def check_yolox(name: str, outputs: list[Any], size: tuple[int, int]) -> None:
    rows = sum(int(np.prod(yolox_grid(size, s))) for s in (8, 16, 32))
    shape = outputs[0].shape
    if len(outputs) != 1 or list(shape) != [1, rows, NUM_CLASSES + 5]:
        raise ModelError(f"detector {name}: outputs {[o.shape for o in outputs]} are not a YOLOX head "
                         f"at {size[1]}x{size[0]} (expected one [1, {rows}, {NUM_CLASSES + 5}])")


class Detector:
    """One ONNX detector in an onnxruntime session (``threads`` intra-op threads; 0 = ORT default).

    ``name`` picks the family (preprocessing and decoder, models.MODELS); ``path`` may point at any
    export of that family, at any fixed input size (``input_hw`` is read from the graph)."""

    def __init__(self, name: str, path: str | None = None, threads: int = 0, url: str | None = None) -> None:
        import onnxruntime as ort

        self.spec: ModelSpec = spec(name)
        self.path: Path = resolve(name, path, url)
        opts = ort.SessionOptions()
        opts.log_severity_level = 3  # the YOLOX export's initializer warnings are noise
        if threads:
            opts.intra_op_num_threads = threads
            opts.inter_op_num_threads = 1
        try:
            self.session = ort.InferenceSession(str(self.path), opts, providers=["CPUExecutionProvider"])
        except Exception as exc:  # onnxruntime raises its own exception types for a bad file
            raise ModelError(f"detector {name}: {self.path} is not a loadable ONNX model: {exc}") from exc
        inputs = self.session.get_inputs()
        if len(inputs) != 1:
            raise ModelError(f"detector {name}: {len(inputs)} inputs; one image input expected")
        self.input_name = inputs[0].name
        self.input_hw: tuple[int, int] = input_size(name, list(inputs[0].shape), inputs[0].type)
        outs = self.session.get_outputs()
        self.output_names = [o.name for o in outs]
        if self.spec.decoder == "gfl":
            self._cls, self._reg, self._strides = gfl_heads(name, outs, self.input_hw)
        else:
            check_yolox(name, outs, self.input_hw)
        self.last_infer_time = 0.0

    @property
    def name(self) -> str:
        return self.spec.name

    @property
    def stretch(self) -> bool:
        """Whether ``preprocess`` stretches a frame to the input (else it letterboxes it)."""
        return self.spec.name == "picodet-s"  # PaddleDetection: keep_ratio False

    def preprocess(self, bgr: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Network input and the affine map back to source pixels: ``src = (net - offset) * scale``
        as a (2, 2) array [[offset_x, offset_y], [scale_x, scale_y]]."""

        if bgr.ndim != 3 or bgr.shape[2] != 3 or bgr.dtype != np.uint8:
            raise ValueError(f"expected an HxWx3 uint8 BGR image, got {bgr.shape} {bgr.dtype}")
        net_h, net_w = self.input_hw
        h, w = bgr.shape[:2]
        if self.stretch:
            img = resize_to(bgr, (net_w, net_h)).astype(np.float32)
            img = (img[:, :, ::-1] - _PICODET_MEAN) / _PICODET_STD
            back = np.array([[0.0, 0.0], [w / net_w, h / net_h]], np.float32)
            return np.ascontiguousarray(img.transpose(2, 0, 1)[None]), back
        # Letterbox: YOLOX top-left on grey 114; NanoDet centred on black (its keep_ratio resize)
        r = min(net_h / h, net_w / w)
        nw, nh = letterbox_size(w, h, self.input_hw)
        yolox = self.spec.decoder == "yolox"
        canvas = np.full((net_h, net_w, 3), 114 if yolox else 0, np.uint8)
        oy, ox = (0, 0) if yolox else ((net_h - nh) // 2, (net_w - nw) // 2)
        canvas[oy:oy + nh, ox:ox + nw] = resize_to(bgr, (nw, nh))
        img = canvas.astype(np.float32)
        if not yolox:
            img = (img - _NANODET_MEAN) / _NANODET_STD
        back = np.array([[ox, oy], [1 / r, 1 / r]], np.float32)
        return np.ascontiguousarray(img.transpose(2, 0, 1)[None]), back

    def detect(self, bgr: np.ndarray) -> Detections:
        x, back = self.preprocess(bgr)
        t0 = time.perf_counter()
        outs = dict(zip(self.output_names, self.session.run(None, {self.input_name: x}), strict=True))
        self.last_infer_time = time.perf_counter() - t0
        if self.spec.decoder == "gfl":
            boxes, scores, cls = decode_gfl([outs[n] for n in self._cls], [outs[n] for n in self._reg],
                                            self._strides, self.input_hw)
        else:
            boxes, scores, cls = decode_yolox(outs[self.output_names[0]], self.input_hw)
        det = nms(boxes, scores, cls)
        h, w = bgr.shape[:2]
        det.boxes = (det.boxes - np.tile(back[0], 2)) * np.tile(back[1], 2)
        np.clip(det.boxes, 0, [w, h, w, h], out=det.boxes)
        return det
