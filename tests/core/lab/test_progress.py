"""The progress line a scan run prints every few seconds (lab/runner.py ``progress_line``)."""

from __future__ import annotations

from zoffload.lab.runner import progress_line


def test_the_progress_line_names_a_raw_scan_and_shows_no_voxel_before_the_first() -> None:
    # the rate policy sends a fast link's scans without a grid (voxel 0): "raw", not "0.00 m"
    assert "voxel – |" in progress_line({}, 0.3, 300)
    assert "voxel raw |" in progress_line({"published": 3, "voxel": 0.0}, 5.0, 300)
    line = progress_line({"published": 40, "acked": 38, "voxel": 0.125, "last_T": 0.1, "cpu_ms": 1.2,
                          "rtt_ms": 44.0, "map_points": 98172}, 10.3, 300)
    assert "scans 40/300 sent, 38 acked, 0 lost | voxel 0.12 m | T 0.100 s" in line
    assert line.endswith("RTT 44 ms | map 98,172 pts")
