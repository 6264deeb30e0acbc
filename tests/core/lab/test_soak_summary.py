"""The soak's growth figures: windows of samples against the heap trim's saw-tooth, and the time
the robot's record rings are full."""

from __future__ import annotations

from pathlib import Path

from zoffload.lab.soak import SoakOptions, _summarise, growth_window, rings_full


def test_a_saw_tooth_without_a_trend_shows_no_growth_and_a_trend_does() -> None:
    tooth = [600.0 + 10 * (i % 6) for i in range(360)]  # a trim every minute, flat underneath
    a, b = growth_window(tooth, 10.0)
    assert abs(b - a) / a < 0.01
    # one sample at each end would have said +8 % (600 -> 650)
    assert (tooth[-1] - tooth[0]) / tooth[0] > 0.08
    trend = [v + i for i, v in enumerate(tooth)]  # +1 MB per sample: a leak
    a, b = growth_window(trend, 10.0)
    assert (b - a) / a > 0.4


def test_rings_fill_at_the_slower_of_scans_and_frames() -> None:
    opts = SoakOptions(duration=3600, out=Path("."), rate_hz=10, fps=2)
    assert rings_full(opts, camera=False) == 4096 / 10
    assert rings_full(opts, camera=True) == 4096 / 2


def test_the_summary_reports_growth_after_the_rings_are_full(tmp_path: Path) -> None:
    opts = SoakOptions(duration=3600, out=tmp_path, period=10, rate_hz=10, fps=2, warmup=300)
    # the robot grows while its frame ring fills (until 2,048 s), then stays flat
    rows = [{"t": float(t), "robot.rss_mb": 300 + min(t, 2048) / 50, "robot.threads": 28, "robot.fds": 29,
             "edge.rss_mb": 650.0, "edge.threads": 22, "edge.fds": 24} for t in range(0, 3610, 10)]
    s = _summarise(rows, opts, 300, True, {"robot": 0, "edge": 0}, tmp_path)
    assert s.rings_full_s == 2048
    assert s.rss_growth["robot"] > 0.05  # after the 5-minute warmup: the ring still filling
    assert abs(s.rss_growth_full["robot"]) < 0.001 and abs(s.rss_growth_full["edge"]) < 0.001
    assert "rings full at 2048 s" in s.line()
