"""Camera frame sources: image folders, video files, and COCO clips with moving ground truth.

A ``coco-clips`` source turns each annotated still image into a short video: a virtual camera pans
across the image while zooming in, at 25 FPS, and the person boxes are carried through the same
crop-and-resize. A detection that arrives late is then scored against boxes that have moved on,
which is what makes the offloading thesis' asynchronous AP meaningful on real pixels.

Every source yields ``ImageFrame`` (BGR ``uint8``) by index; the camera thread paces the replay.
"""

from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, TypeAlias

import numpy as np

from zoffload.sources.base import ScanSourceError

if TYPE_CHECKING:
    from zoffload.ros2.session import Ros2Link
    from zoffload.sources.ros2_images import BagImageSource, Ros2ImageSource

log = logging.getLogger("zoffload.sources.images")

IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".bmp")
SHARED_COCO = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "coco-person-dev"


class ImageSourceError(ScanSourceError):
    """An image source that cannot be opened or a frame that cannot be decoded."""


@dataclass(frozen=True)
class ImageFrame:
    index: int
    image: np.ndarray  # (H, W, 3) uint8 BGR
    gt_boxes: np.ndarray | None = None  # (n, 4) person boxes x1, y1, x2, y2 in this frame's pixels
    stamp: float | None = None  # capture time on the camera's clock (ROS topics and bags), epoch s


def _imread(path: Path) -> np.ndarray:
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise ImageSourceError(f"{path}: not a readable image (corrupt or unsupported)")
    return img


class ImageFolderSource:
    """Every image in a folder, in name order (e.g. the KITTI-360 ``image_00`` frames)."""

    def __init__(self, folder: Path, rate_hz: float = 10.0) -> None:
        self.files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_EXTS)
        if not self.files:
            raise ImageSourceError(f"no {'/'.join(IMAGE_EXTS)} images in {folder}")
        self.name = f"images:{folder}"
        self.rate_hz = rate_hz

    def __len__(self) -> int:
        return len(self.files)

    def read(self, index: int) -> ImageFrame:
        return ImageFrame(index, _imread(self.files[index]))


class VideoFileSource:
    """A video file decoded with OpenCV; frames are read in order (random access seeks)."""

    def __init__(self, path: Path, rate_hz: float | None = None) -> None:
        import cv2

        self.cap = cv2.VideoCapture(str(path))
        if not self.cap.isOpened():
            raise ImageSourceError(f"{path}: cannot open as a video")
        self.n = int(self.cap.get(cv2.CAP_PROP_FRAME_COUNT))
        if self.n <= 0:
            raise ImageSourceError(f"{path}: the video has no frames")
        self.rate_hz = rate_hz or float(self.cap.get(cv2.CAP_PROP_FPS) or 25.0)
        self.name = f"video:{path}"
        self._next = 0

    def __len__(self) -> int:
        return self.n

    def read(self, index: int) -> ImageFrame:
        import cv2

        if index != self._next:
            self.cap.set(cv2.CAP_PROP_POS_FRAMES, index)
        ok, img = self.cap.read()
        self._next = index + 1
        if not ok or img is None:
            raise ImageSourceError(f"{self.name}: frame {index} cannot be decoded")
        return ImageFrame(index, img)


@dataclass(frozen=True)
class _Still:
    path: Path
    width: int
    height: int
    boxes: np.ndarray  # (n, 4) x1, y1, x2, y2 in the still's pixels


def coco_person_boxes(root: Path) -> list[tuple[Path, int, int, np.ndarray]]:
    """The images of ``root/person_gt.json`` (COCO format) as (path, width, height, person boxes
    (category 1) as x1, y1, x2, y2, float32 (n, 4)). ImageSourceError when the file is missing
    or malformed."""
    ann = root / "person_gt.json"
    if not ann.is_file():
        raise ImageSourceError(f"{root}: no person_gt.json (COCO-format person boxes)")
    try:
        gt = json.loads(ann.read_text())
        out = []
        for im in gt["images"]:
            boxes = np.array([a["bbox"] for a in gt["annotations"] if a["image_id"] == im["id"]
                              and a.get("category_id", 1) == 1], np.float32).reshape(-1, 4)
            boxes[:, 2:] += boxes[:, :2]
            out.append((root / im["file_name"], int(im["width"]), int(im["height"]), boxes))
    except (KeyError, TypeError, ValueError) as exc:
        raise ImageSourceError(f"{ann}: not COCO-format annotations: {exc}") from exc
    if not out:
        raise ImageSourceError(f"{ann}: no images")
    return out


# An honest evaluation tunes on one half of the annotated images and reports on the other. The
# rule, fixed before any tuning: the images sorted by file name (COCO names are zero-padded ids),
# positions 0, 2, 4, ... are "tune", positions 1, 3, 5, ... are "holdout".
COCO_HALVES = ("tune", "holdout")


def coco_half(images: list[tuple[Path, int, int, np.ndarray]],
              half: str) -> list[tuple[Path, int, int, np.ndarray]]:
    """The ``tune`` or ``holdout`` half of ``coco_person_boxes`` output (see COCO_HALVES)."""
    if half not in COCO_HALVES:
        raise ImageSourceError(f"unknown image half {half!r} ({', '.join(COCO_HALVES)})")
    ordered = sorted(images, key=lambda image: image[0].name)
    return ordered[COCO_HALVES.index(half)::2]


class CocoClipSource:
    """Pan/zoom clips over annotated COCO images (COCO-format json, category 1 = person).

    Each still gives ``frames_per_image`` frames of ``size`` (W, H). The crop keeps the output's
    aspect ratio; it starts at ``zoom[0]`` of the largest such crop on one side and ends at
    ``zoom[1]`` on the other (alternating direction per image), so boxes drift and grow over the
    clip. A box is kept in a frame while at least ``min_visible`` of its area is inside the crop.
    ``half`` keeps only the tuning or the held-out half of the images (``coco_half``).
    """

    def __init__(self, root: Path, size: tuple[int, int] = (848, 480), fps: float = 25.0,
                 frames_per_image: int = 50, zoom: tuple[float, float] = (1.0, 0.85),
                 min_visible: float = 0.5, half: str | None = None) -> None:
        images = coco_person_boxes(root)
        self.stills = [_Still(*image) for image in (coco_half(images, half) if half else images)]
        self.size = size
        self.rate_hz = fps
        self.frames_per_image = frames_per_image
        self.zoom = zoom
        self.min_visible = min_visible
        self.name = f"coco-clips:{root}" + (f"@{half}" if half else "")
        self._cache: tuple[int, np.ndarray] | None = None

    def __len__(self) -> int:
        return len(self.stills) * self.frames_per_image

    def crop(self, index: int) -> tuple[int, np.ndarray]:
        """The still of frame ``index`` and its crop window [x0, y0, x1, y1] in still pixels."""
        k, j = divmod(index, self.frames_per_image)
        st = self.stills[k]
        u = j / max(self.frames_per_image - 1, 1)  # 0 → 1 over the clip
        if k % 2:
            u = 1.0 - u
        aspect = self.size[0] / self.size[1]
        full_w = min(st.width, st.height * aspect)
        z = self.zoom[0] + (self.zoom[1] - self.zoom[0]) * (u if k % 2 == 0 else 1.0 - u)
        cw, ch = full_w * z, full_w * z / aspect
        x0 = (st.width - cw) * u
        y0 = (st.height - ch) * 0.5
        return k, np.array([x0, y0, x0 + cw, y0 + ch])

    def boxes(self, index: int) -> np.ndarray:
        """Ground-truth person boxes of frame ``index`` in output pixels."""
        k, win = self.crop(index)
        b = self.stills[k].boxes
        if len(b) == 0:
            return b.copy()
        scale = self.size[0] / (win[2] - win[0])
        clipped = np.column_stack([np.maximum(b[:, 0], win[0]), np.maximum(b[:, 1], win[1]),
                                   np.minimum(b[:, 2], win[2]), np.minimum(b[:, 3], win[3])])
        area = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
        wh = np.clip(clipped[:, 2:] - clipped[:, :2], 0, None)
        vis = wh[:, 0] * wh[:, 1]
        keep = vis >= self.min_visible * np.maximum(area, 1e-9)
        out = (clipped[keep] - np.tile(win[:2], 2)) * scale
        return out.astype(np.float32)

    def read(self, index: int) -> ImageFrame:
        import cv2

        k, win = self.crop(index)
        if self._cache is None or self._cache[0] != k:
            self._cache = (k, _imread(self.stills[k].path))
        still = self._cache[1]
        # One affine warp does crop + resize with sub-pixel placement (boxes use the same map)
        scale = self.size[0] / (win[2] - win[0])
        m = np.array([[scale, 0, -win[0] * scale], [0, scale, -win[1] * scale]], np.float64)
        img = cv2.warpAffine(still, m, self.size, flags=cv2.INTER_LINEAR, borderValue=(0, 0, 0))
        return ImageFrame(index, img, self.boxes(index))


ImageSource: TypeAlias = (
    "ImageFolderSource | VideoFileSource | CocoClipSource | Ros2ImageSource | BagImageSource")


def open_image_source(spec: str, rate_hz: float | None = None, ros2: Ros2Link | None = None) -> ImageSource:
    """``coco-clips`` (the shared COCO person images), ``coco-clips:FOLDER``, either with ``@tune`` or
    ``@holdout`` for one half of the images (``coco_half``), an image folder, or a video file."""
    if spec.startswith(("coco-clips:", "coco-clips@")) or spec == "coco-clips":
        half = None
        if "@" in spec and spec.rsplit("@", 1)[1] in COCO_HALVES:
            spec, half = spec.rsplit("@", 1)
        default = (Path(os.environ["ZOFFLOAD_DATA"]) / "coco-person-dev" if os.environ.get("ZOFFLOAD_DATA")
                   else SHARED_COCO)
        root = Path(spec.split(":", 1)[1]).expanduser() if ":" in spec else default
        if not root.is_dir():
            raise ImageSourceError(f"COCO clip folder {root} does not exist (give coco-clips:FOLDER)")
        return CocoClipSource(root, fps=rate_hz or 25.0, half=half)
    if spec.startswith(("ros2:", "bag:")):  # a ROS 2 topic or bag: sources/ros2_images.py
        from zoffload.sources.ros2_images import open_ros_image_source

        return open_ros_image_source(spec, rate_hz, ros2)
    path = Path(spec).expanduser()
    if not path.exists():
        raise ImageSourceError(f"image source {path} does not exist")
    if path.is_dir():
        return ImageFolderSource(path, rate_hz or 10.0)
    return VideoFileSource(path, rate_hz)
