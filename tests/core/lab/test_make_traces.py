"""The generated traces: the committed files are what the seeded script writes, and each holds
what it claims (the cellular rates, delays, jitter and outages; the Wi-Fi bursts)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from zoffload.lab.link.make_traces import TRACES, cellular, main, to_csv
from zoffload.lab.link.trace import load_trace, parse_trace


def test_committed_traces_are_what_the_script_writes(tmp_path: Path) -> None:
    main(["--out", str(tmp_path)])
    shipped = Path(__file__).parents[3] / "zoffload" / "lab" / "link" / "traces"
    for name in TRACES:
        assert (tmp_path / f"{name}.csv").read_text() == (shipped / f"{name}.csv").read_text(), name
        load_trace(name)  # parses


def test_cellular_is_a_bounded_random_walk_with_outages() -> None:
    for name in ("cellular", "cellular-heldout", "cellular-3", "cellular-4", "cellular-5"):
        t = load_trace(name)
        live = [s for s in t.states if not s.outage]
        assert all(2.0 <= s.up_mbps <= 40.0 and 30 <= s.delay_ms <= 70 and 5 <= s.jitter_ms <= 20
                   for s in live)
        outages = [(t0, t1) for t0, t1, s in zip(t.times, t.times[1:], t.states, strict=False) if s.outage]
        assert len(outages) >= 2 and all(1.0 <= t1 - t0 <= 4.05 for t0, t1 in outages)
        assert t.duration >= 85
        assert not t.states[-1].outage, name  # the last row holds for ever: an outage there never ends


def test_an_outage_at_the_end_of_the_trace_still_ends() -> None:
    for seed in range(1, 40):  # seed 2 (cellular-heldout) started an outage 0.9 s before the end
        rows = cellular(seed, duration=60.0)
        assert not rows[-1][5], seed
        spans = [(a[0], b[0]) for a, b in zip(rows, rows[1:], strict=False) if a[5]]
        assert all(1.0 <= b - a <= 4.0 for a, b in spans), seed


def test_congested_wifi_alternates_bursts_and_quiet_spells() -> None:
    for name in ("wifi-congested", "wifi-congested-heldout"):
        t = load_trace(name)
        ups = np.array([s.up_mbps for s in t.states])
        low = ups < 0.3 * np.median(ups[ups > 40])
        assert 0.3 < low.mean() < 0.7 and (np.diff(low.astype(int)) != 0).sum() > 40
        assert all(s.jitter_ms >= 10 for s, b in zip(t.states, low, strict=True) if b)


def test_csv_round_trip() -> None:
    rows = [(0.0, 10.0, 20.0, 30.0, 5.0, 0), (1.5, 0.0, 0.0, 0.0, 0.0, 1)]
    t = parse_trace(to_csv(rows, "a comment"))
    assert t.times == (0.0, 1.5) and t.states[1].outage and t.states[0].down_mbps == 20.0


def test_satellite_has_a_half_second_round_trip_and_rain_fades() -> None:
    for name in ("satellite", "satellite-heldout"):
        t = load_trace(name)
        assert not any(s.outage for s in t.states) and t.duration >= 85
        assert all(260 <= s.delay_ms <= 360 and 5 <= s.jitter_ms <= 20 for s in t.states)
        assert all(0.4 <= s.up_mbps <= 20.0 and 20.0 <= s.down_mbps <= 50.0 for s in t.states)
        up = np.array([s.up_mbps for s in t.states])
        steps = up[1:] / up[:-1]  # a fade takes 60-85 % of the rate at once and gives it back
        assert ((steps < 0.5) | (steps > 2.0)).sum() >= 3
