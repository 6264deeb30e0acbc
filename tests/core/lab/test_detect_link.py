"""The detection experiments' held-out link: the shipped file is what the seeded script writes."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from zoffload.lab.detect_link import NAME, main
from zoffload.lab.link.trace import load_trace


def test_the_shipped_trace_is_the_scripts_output(tmp_path: Path) -> None:
    main(["--out", str(tmp_path)])
    shipped = Path(__file__).parents[3] / "zoffload" / "lab" / "link" / "traces" / f"{NAME}.csv"
    assert (tmp_path / f"{NAME}.csv").read_text() == shipped.read_text()


def test_the_link_is_above_and_below_the_raw_stream_with_short_blockages() -> None:
    t = load_trace(NAME)
    live = [s for s in t.states if not s.outage]
    assert all(60 <= s.up_mbps <= 400 and 5 <= s.delay_ms <= 20 and 2 <= s.jitter_ms <= 8 for s in live)
    rates = np.array([t.at(x).up_mbps for x in np.arange(0, 50, 0.1)])
    assert 0.2 < (rates > 244).mean() < 0.8  # the raw 848x480 stream at 25 FPS needs 244 Mbps
    blocks = [(a, b) for a, b, s in zip(t.times, t.times[1:], t.states, strict=False) if s.outage]
    assert len(blocks) >= 3 and all(0.2 <= b - a <= 0.8 + 1e-9 for a, b in blocks)
    assert t.duration >= 60 and not t.states[-1].outage  # the last row holds for ever
