"""The camera pipeline's simulation: the real FrameBook and strategies on a simulated clock."""

from __future__ import annotations

import pytest

from zoffload.lab.link.trace import constant
from zoffload.lab.offload_sim import SimConfig, Simulation
from zoffload.policy.offload import make_strategy


def _run(strategy: str, quota: float = 0.25, seed: int = 0) -> tuple[int, int]:
    """Frames processed, and of them answered within 250 ms of capture, out of 500 on a 160 Mbps
    link (raw frames take 61 ms each on it: 16 a second, of the camera's 25)."""
    book = Simulation(make_strategy(strategy), SimConfig(quota=quota, seed=seed),
                      constant(160, delay_ms=2), 500).run()
    assert book.balanced() and book.balance()["frames_in"] == 500 and book.balance()["pending"] == 0
    done = [r for r in book.records.values() if r["status"] in ("local_done", "edge_done")]
    return len(done), sum(1 for r in done if r["rtt_ms"] <= 250)


def test_on_a_capped_link_a_fixed_ratio_queues_frames_the_dispatcher_keeps_them_fresh() -> None:
    """The quarter-core robot's detector stalls the whole process, so ours leaves to the edge the
    frames it finishes in time: it processes fewer frames than ratio 0.9, which runs the detector
    beside a healthy edge (here 0.90 of them; 0.95 and more before that rule), but three times as
    many within 250 ms of capture."""
    for seed in (0, 1):
        ratio_done, ratio_fresh = _run("ratio:0.9", seed=seed)
        ours_done, ours_fresh = _run("dispatch", seed=seed)
        assert ours_done >= 0.85 * ratio_done  # nearly as many frames through ...
        assert ours_fresh >= 3 * ratio_fresh  # ... but not queued in the link's buffers


def test_a_full_core_robot_detects_every_frame_itself() -> None:
    done, fresh = _run("dispatch", quota=1.0)
    assert done >= 490 and fresh >= 490


def test_the_simulated_edge_serves_the_newest_frame_or_the_oldest() -> None:
    """Edge only on a link that carries every frame, the edge slower than the camera: with the
    newest frame served (the edge's default) its answers come sooner than first in, first out."""
    def median_rtt(serve: str) -> float:
        book = Simulation(make_strategy("edge"), SimConfig(edge_service=0.06, edge_serve=serve),
                          constant(1e4, delay_ms=2), 300).run()
        assert book.balanced() and book.balance()["pending"] == 0
        rtts = sorted(r["rtt_ms"] for r in book.records.values() if r["status"] == "edge_done")
        return rtts[len(rtts) // 2]
    assert median_rtt("newest") < median_rtt("oldest") - 20
    with pytest.raises(ValueError, match="edge_serve"):
        SimConfig(edge_serve="latest")
