"""Where detector weights come from: a configured path, a model directory, or a verified download.

Resolution order: an explicit path → ``$ZOFFLOAD_MODELS/<file>`` →
``$ZOFFLOAD_DATA/models`` → ``../shared/data/models``
when that folder exists → a download from a URL the user configures, checked against the
checksum pinned here (the SHA-256 of the files this project is tested with). A model that cannot be
found is a ``ModelError`` naming every place that was tried.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import tempfile
import urllib.request
from dataclasses import dataclass
from pathlib import Path


class ModelError(Exception):
    """A detector model that cannot be found, downloaded, verified or loaded (exit code 3)."""


@dataclass(frozen=True)
class ModelSpec:
    """One supported detector family: its default file (with that file's input size and pinned
    checksum) and its decoder. Another export of the family, at any input size, loads from a
    configured path: the detector reads the size from the graph (detector.py)."""

    name: str
    file: str
    size: int  # the default file's square network input [px]; documentation only
    decoder: str  # "gfl" (NanoDet / PicoDet heads) or "yolox"
    sha256: str
    release: str  # where the official weights are published (for the user to pick a URL)


MODELS: dict[str, ModelSpec] = {
    "nanodet-m": ModelSpec(
        "nanodet-m", "nanodet_m_320.onnx", 320, "gfl",
        "88e9fb97a54bb0030127ad323a10f88b4531b6aa82617e7ef79e35ffcc9bb3e1",
        "https://github.com/RangiLyu/nanodet/releases"),
    "picodet-s": ModelSpec(
        "picodet-s", "picodet_s_416_coco.onnx", 416, "gfl",
        "cdab77bdde16e4f76bec734c4e5791801d1739e4c7ec1995e0e110e04300d0c2",
        "https://github.com/PaddlePaddle/PaddleDetection/tree/release/2.8/configs/picodet"),
    "yolox-nano": ModelSpec(
        "yolox-nano", "yolox_nano_416.onnx", 416, "yolox",
        "695e750a5d5754bb5a8d5325643b59282191a7e7a564e435a415fd3c578eab14",
        "https://github.com/Megvii-BaseDetection/YOLOX/releases"),
}

SHARED_MODELS = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "models"


def spec(name: str) -> ModelSpec:
    try:
        return MODELS[name]
    except KeyError:
        raise ModelError(f"unknown detector {name!r}; choose one of {', '.join(MODELS)}") from None


def model_dirs() -> list[Path]:
    """The model directories searched, in order."""
    dirs = []
    if os.environ.get("ZOFFLOAD_MODELS"):
        dirs.append(Path(os.environ["ZOFFLOAD_MODELS"]))
    if os.environ.get("ZOFFLOAD_DATA"):
        dirs.append(Path(os.environ["ZOFFLOAD_DATA"]) / "models")
    if SHARED_MODELS.is_dir():
        dirs.append(SHARED_MODELS)
    return dirs


def sha256_of(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def download(url: str, dest: Path, sha256: str) -> Path:
    """Fetch ``url`` to ``dest`` and keep it only if its SHA-256 matches the pinned one."""
    dest.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.NamedTemporaryFile(dir=dest.parent, delete=False) as tmp:
        try:
            with urllib.request.urlopen(url, timeout=60) as resp:
                shutil.copyfileobj(resp, tmp)
        except OSError as exc:
            os.unlink(tmp.name)
            raise ModelError(f"cannot download {url}: {exc}") from exc
    got = sha256_of(Path(tmp.name))
    if got != sha256:
        os.unlink(tmp.name)
        raise ModelError(f"download {url}: SHA-256 {got} is not the pinned {sha256}; file discarded")
    os.replace(tmp.name, dest)
    return dest


def resolve(name: str, path: str | None = None, url: str | None = None,
            cache: Path | None = None) -> Path:
    """The ONNX file of detector ``name`` (see the module docstring for the order)."""
    s = spec(name)
    tried: list[str] = []
    if path:
        p = Path(path).expanduser()
        if p.is_file():
            return p
        raise ModelError(f"detector {name}: configured model path {p} does not exist")
    for d in model_dirs():
        p = d / s.file
        if p.is_file():
            return p
        tried.append(str(p))
    if url:
        dest = (cache or Path.home() / ".cache" / "zoffload" / "models") / s.file
        if dest.is_file() and sha256_of(dest) == s.sha256:
            return dest
        return download(url, dest, s.sha256)
    where = ", ".join(tried) if tried else "no model directory (set ZOFFLOAD_MODELS, or ZOFFLOAD_DATA)"
    raise ModelError(
        f"detector {name}: {s.file} not found (looked in {where}). Put the file there, set "
        f"ZOFFLOAD_MODELS to its folder, configure its path, or give a download URL (official "
        f"weights: {s.release}; the file must have SHA-256 {s.sha256})"
    )
