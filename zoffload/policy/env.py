"""A fast simulated environment for training the scale policy, built from recorded runs.

The recordings are the experiment harness's ``scans.csv`` files (per scan: voxel size, bytes
sent, points kept, receive time T, the link rate at that moment). From them:

* ``Retention``: bytes and kept-point fraction as functions of the voxel size (interpolated);
* ``LinkModel``: per link level, the effective rate a scan of B bytes meets and the extra delay,
  fitted so that ``T = max(period, B * 8 / rate) + noise`` reproduces the recorded receive times.

``ScaleEnv`` then plays the paper's MDP: one step = one scan = one episode.
"""

from __future__ import annotations

import csv
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from zoffload.policy.mdp import ScaleMDP


def read_records(paths: Iterable[Path]) -> list[dict[str, str]]:
    out: list[dict[str, str]] = []
    for p in paths:
        with open(p) as f:
            out.extend(csv.DictReader(f))
    return out


def _num(x: str | None) -> float:
    try:
        return float(x) if x not in (None, "") else float("nan")
    except ValueError:
        return float("nan")


@dataclass(frozen=True)
class Retention:
    """Voxel size -> (bytes per scan, fraction of points kept), from recordings."""

    voxels: np.ndarray
    bytes: np.ndarray
    ratios: np.ndarray

    @classmethod
    def fit(cls, records: list[dict[str, str]]) -> Retention:
        by_v: dict[float, list[tuple[float, float]]] = {}
        for r in records:
            v, b, kept, raw = (_num(r.get(k)) for k in ("voxel", "bytes", "n_sent", "n_raw"))
            if all(np.isfinite(x) for x in (v, b, kept, raw)) and raw > 0 and v > 0:
                by_v.setdefault(round(v, 4), []).append((b, kept / raw))
        if len(by_v) < 2:
            raise ValueError("retention needs recordings at two voxel sizes or more")
        vs = np.array(sorted(by_v))
        return cls(voxels=vs, bytes=np.array([np.median([b for b, _ in by_v[v]]) for v in vs]),
                   ratios=np.array([np.median([r for _, r in by_v[v]]) for v in vs]))

    def at(self, v: float) -> tuple[float, float]:
        return float(np.interp(v, self.voxels, self.bytes)), float(np.interp(v, self.voxels, self.ratios))


@dataclass(frozen=True)
class LinkLevel:
    rate_mbps: float  # effective rate a scan meets at this level
    extra_s: float  # median receive time beyond the transmission/sensor-period model
    jitter_s: float  # spread of that extra time


@dataclass(frozen=True)
class LinkModel:
    period: float
    levels: tuple[LinkLevel, ...]

    @classmethod
    def fit(cls, records: list[dict[str, str]], period: float = 0.1,
            edges_mbps: tuple[float, ...] = (15.0, 60.0)) -> LinkModel:
        """Group acked scans by the recorded link rate into levels (weak < 15 <= medium < 60 <=
        strong Mbps by default) and fit each level's effective rate and delay spread."""
        groups: dict[int, list[tuple[float, float, float]]] = {}
        for r in records:
            b, t, link = _num(r.get("bytes")), _num(r.get("interarrival")), _num(r.get("link_up_mbps"))
            if r.get("status") != "acked" or not all(np.isfinite(x) for x in (b, t, link)) or link <= 0:
                continue
            level = int(np.searchsorted(edges_mbps, link, side="right"))
            groups.setdefault(level, []).append((b, t, link))
        if not groups:
            raise ValueError("no acked scans with a link rate in the recordings")
        levels = []
        for lvl in sorted(groups):
            rows = np.array(groups[lvl])
            nb, rt, lk = rows[:, 0], rows[:, 1], rows[:, 2]
            # Scans that waited on the link (T above the period) reveal the effective rate
            slow = rt > period * 1.15
            if int(slow.sum()) >= 5:
                rate = float(np.median(nb[slow] * 8 / rt[slow]) / 1e6)
            else:
                rate = float(np.median(lk))
            extra = rt - np.maximum(period, nb * 8 / (rate * 1e6))
            levels.append(LinkLevel(rate, float(np.median(extra)), float(np.std(extra))))
        return cls(period=period, levels=tuple(levels))

    def receive_time(self, level: int, nbytes: float, rng: np.random.Generator) -> float:
        lv = self.levels[level]
        t = max(self.period, nbytes * 8 / (lv.rate_mbps * 1e6)) + lv.extra_s + rng.normal(0, lv.jitter_s)
        return float(max(0.0, t))


class ScaleEnv:
    """The MDP over the fitted link: ``step(state, action, level)`` -> (reward, next state)."""

    def __init__(self, mdp: ScaleMDP, retention: Retention, link: LinkModel, seed: int = 0) -> None:
        self.mdp, self.retention, self.link = mdp, retention, link
        self.rng = np.random.default_rng(seed)

    def step(self, state: tuple[float, float], action: int, level: int) -> tuple[float, tuple[float, float]]:
        _, v = self.mdp.clamp_state(*state)
        v_new = self.mdp.apply(v, action)
        nbytes, ratio = self.retention.at(v_new)
        t = self.link.receive_time(level, nbytes, self.rng)
        return self.mdp.reward(t, action, v_new, ratio), (t, v_new)
