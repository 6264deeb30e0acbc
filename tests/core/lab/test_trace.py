from __future__ import annotations

from pathlib import Path

import pytest

from zoffload.lab.link.trace import TraceError, load_trace, parse_trace, shipped_traces

HEAD = "time_s, up_mbps, down_mbps, delay_ms, jitter_ms, outage\n"


def test_piecewise_constant_lookup_and_loop() -> None:
    t = parse_trace(HEAD + "0, 100, 50, 2, 1, 0\n10, 0, 0, 0, 0, 1\n12, 20, 20, 30, 5, 0\n", "t")
    assert t.at(0).up_mbps == 100 and t.at(0).down_mbps == 50 and t.at(9.99).delay_ms == 2
    assert t.at(10).outage and t.at(10).rate_bps("up") == 0
    assert t.at(100).up_mbps == 20  # the last row holds
    assert t.at(5).rate_bps("up") == 100e6 / 8 and t.at(5).rate_bps("down") == 50e6 / 8
    assert t.next_change(3) == 7 and t.next_change(11) == 1 and t.next_change(50) is None
    looped = parse_trace(HEAD + "0, 10, 10, 0, 0, 0\n5, 20, 20, 0, 0, 0\n10, 10, 10, 0, 0, 0\n", loop=True)
    assert looped.at(12).up_mbps == 10 and looped.at(17).up_mbps == 20


@pytest.mark.parametrize(
    "body, message",
    [
        ("", "empty trace"),
        ("time, up\n", "t:1: header must be"),
        (HEAD, "no rows"),
        (HEAD + "0, 10, 10, 0, 0\n", "t:2: 5 values"),
        (HEAD + "0, ten, 10, 0, 0, 0\n", "t:2: not a number"),
        (HEAD + "0, 10, 10, 0, 0, maybe\n", "t:2: outage must be 0 or 1"),
        (HEAD + "0, -1, 10, 0, 0, 0\n", "t:2: values must be non-negative"),
        (HEAD + "0, 0, 10, 0, 0, 0\n", "t:2: a rate of 0 Mbps"),
        (HEAD + "1, 10, 10, 0, 0, 0\n", "t:2: the first row must start at time 0"),
        (HEAD + "# comment\n0, 10, 10, 0, 0, 0\n\n0, 5, 5, 0, 0, 0\n", "t:5: time 0.0 does not increase"),
    ],
)
def test_malformed_traces_name_the_line(body: str, message: str) -> None:
    with pytest.raises(TraceError, match=message):
        parse_trace(body, "t")


def test_shipped_traces_load_and_say_what_the_issue_asks() -> None:
    assert set(shipped_traces()) >= {"ethernet", "capped", "wifi-locations", "outage"}
    eth = load_trace("ethernet")
    assert eth.at(0).up_mbps >= 1000 and eth.at(0).delay_ms == 0
    capped = load_trace("capped")
    assert capped.at(0).delay_ms == 50 and capped.at(0).up_mbps < 27  # raw sim scans need ~27 Mbps
    wifi = load_trace("wifi-locations")
    rates = [wifi.at(t).up_mbps for t in range(0, 80) if not wifi.at(t).outage]
    assert rates[0] == max(rates) and min(rates) < 15 and wifi.at(79).up_mbps == rates[0]
    assert any(wifi.at(t / 10).outage for t in range(800))
    out = load_trace("outage")
    assert sum(out.at(t / 10).outage for t in range(300)) >= 30  # at least 3 s of drops
    dead = load_trace("deadzone")  # dead zones longer than the backfill's ring (5 s) and max_gap
    spans = [round(t1 - t0) for t0, t1, st in zip(dead.times, dead.times[1:], dead.states, strict=False)
             if st.outage]
    assert spans == [12, 25] and not dead.states[-1].outage


def test_trace_files_and_missing_names(tmp_path: Path) -> None:
    f = tmp_path / "mine.csv"
    f.write_text(HEAD + "0, 5, 5, 10, 0, 0\n")
    assert load_trace(str(f)).at(3).delay_ms == 10
    with pytest.raises(TraceError, match="no trace 'nope'"):
        load_trace("nope")
