"""Our link-aware scale policy: the byte budget follows the acks, the choice fits the budget,
lateness is told apart (size, capacity, jitter, stall), and when nothing fits the range widens and
the scan rate drops, each choice with its reason."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from zoffload.mapping.voxel import voxel_downsample
from zoffload.policy.onnx_scale import load_scale_policy
from zoffload.policy.rate import (
    AckInfo,
    LinkAwareScale,
    LinkView,
    candidate_grid,
    jitter_slots,
    late_cause,
    widened_grid,
)
from zoffload.sources.simulated import SimulatedSource


def _scan(i: int = 3) -> np.ndarray:
    pts = SimulatedSource(seed=0).read(i).points
    return pts[np.isfinite(pts).all(axis=1)]


def counter(points: np.ndarray, calls: list[float] | None = None):
    def count(v: float) -> int:
        if calls is not None:
            calls.append(v)
        return len(voxel_downsample(points, v))

    return count


def on_time(acks: int = -1) -> LinkView:
    return LinkView(0.1, 1_000_000.0, 12.0, 0.1, acks=acks)


def test_first_scan_uses_the_start_size_until_something_is_measured() -> None:
    p = LinkAwareScale((0.01, 0.2), start=0.05)
    assert p.reset() == 0.05
    v, down = p.choose_cloud(_scan(), LinkView(0.0, math.nan, math.nan, 0.1))
    assert v == 0.05 and len(down) == len(voxel_downsample(_scan(), 0.05))
    # the first measurement sets the budget to the start size's bytes; on time it grows, finer
    v, _ = p.choose_cloud(_scan(), LinkView(0.1, 2e6, 6.0, 0.1))
    assert p.budget == pytest.approx(len(voxel_downsample(_scan(), 0.05)) * 6.0 * 1.05)
    assert v <= 0.05


def test_choice_is_the_finest_candidate_that_fits_the_budget() -> None:
    pts = _scan()
    p = LinkAwareScale((0.01, 0.2), raw_share=1.0)
    p.choose_cloud(pts, LinkView(0.0, math.nan, math.nan, 0.1))  # calibrates the counts
    p.budget = 100_000.0
    # on time: the budget grows 5 %, then the finest size whose points x 6 B fit it
    v, down = p.choose_cloud(pts, LinkView(0.1, 2e6, 6.0, 0.1))
    assert p.budget == pytest.approx(105_000.0)
    fits = [c for c in p.candidates if len(voxel_downsample(pts, c)) * 6.0 <= p.budget]
    assert v == min(fits) and len(down) * 6.0 <= p.budget


def test_the_predicted_size_is_verified_with_few_grid_passes() -> None:
    """Counts are predicted from the last scans, and each choice is checked by a real pass: the
    chosen size always fits, is nearly always the exhaustive search's, and costs 1-3 passes."""
    p = LinkAwareScale((0.01, 0.2), raw_share=1.0, refresh=0)
    p.choose_cloud(_scan(0), LinkView(0.0, math.nan, math.nan, 0.1))
    same = 0
    for i in range(1, 21):
        pts = _scan(i)
        calls: list[float] = []
        p.budget = 60_000.0 + 4_000.0 * (i % 7)  # moving, as on a real link
        d = p.decide(len(pts), LinkView(0.1, 1e6, 6.0, 0.1, acks=0), counter(pts, calls))
        assert 1 <= len(calls) <= 3
        best = min(c for c in p.candidates if len(voxel_downsample(pts, c)) * 6.0 <= p.budget)
        assert len(voxel_downsample(pts, d.voxel)) * 6.0 <= p.budget
        same += d.voxel == best
    assert same >= 17


def test_a_scan_that_the_finest_size_would_barely_thin_is_sent_as_it_is() -> None:
    pts = _scan()
    p = LinkAwareScale((0.001, 0.2), refresh=0)  # 1 mm keeps every point of a simulated scan
    p.choose_cloud(pts, LinkView(0.0, math.nan, math.nan, 0.1))
    p.budget = 1e9
    calls: list[float] = []
    d = p.decide(len(pts), LinkView(0.1, 1e8, 6.0, 0.1, raw_bytes_per_point=6.0), counter(pts, calls))
    assert d.voxel == 0.0 and calls == [] and "as they are" in d.reason
    assert not d.compress  # and the link has room: no compression either
    p.budget = 100_000.0
    d = p.decide(len(pts), LinkView(0.1, 1e6, 6.0, 0.1, raw_bytes_per_point=6.0), counter(pts))
    assert d.voxel > 0 and d.compress


def test_a_late_scan_that_queued_cuts_the_budget_to_what_the_link_delivers() -> None:
    p = LinkAwareScale((0.01, 0.2), margin=0.85)
    p.budget = 400_000.0
    steady = tuple(AckInfo(50_000, 0.030 + 0.001 * (i % 3), 0.1) for i in range(10))
    queued = (*steady, AckInfo(80_000, 0.080, 0.14))  # 50 ms more on the network than any other
    assert late_cause(queued, 0.1) == "size"
    p.update_budget(LinkView(0.14, 1_000_000.0, 12.0, 0.1, recent=queued))  # 85 kB per period...
    assert p.budget == pytest.approx(200_000.0) and "size" in p.event  # ...but at most halved at once
    p.update_budget(LinkView(0.14, 1_000_000.0, 12.0, 0.1, recent=queued))
    assert p.budget == pytest.approx(100_000.0)
    p.update_budget(LinkView(0.14, 5_000_000.0, 12.0, 0.1, recent=queued))  # never more than 80 % of before
    assert p.budget == pytest.approx(80_000.0)
    v, _ = p.choose_cloud(_scan(), LinkView(0.1, 1e6, 12.0, 0.1))
    assert v > 0.05  # a tight budget means coarse voxels


def _acks_in(nets: list[float], acks: int, drops: int, delivered: float = 300_000.0,
             since_ack: float = 0.05) -> LinkView:
    """An on-time ack (T = one period) after ``nets``' scans, ``drops`` window drops so far; the
    ledger's floor the quickest of them (10 at least)."""
    recent = tuple(AckInfo(50_000, n, 0.1) for n in nets[-24:])
    return LinkView(0.1, delivered, 6.0, 0.1, acks=acks, recent=recent, since_ack=since_ack,
                    window_drops=drops, floor_net=min(nets[-100:]) if len(nets) >= 10 else math.nan)


def _run_in(p: LinkAwareScale, nets: list[float], drops: list[int], **kw: float) -> None:
    for i in range(len(nets)):
        p._scans += 1
        p.update_budget(_acks_in(nets[: i + 1], i, drops[i], **kw))


def test_a_standing_queue_caps_the_budget_at_what_the_link_delivers() -> None:
    """The window holds scans back while the edge keeps answering, and the network times stand a
    period above the path's floor: a queue stands, though no late scan rises above the last ones
    (so ``late_cause`` reads jitter). The budget drops to what the link delivered in the last
    second (x margin), once a second at most; growth resumes from there."""
    p = LinkAwareScale((0.01, 0.07), margin=0.85)
    p.budget = 70_000.0
    nets, drops = [0.08] * 12 + [0.26, 0.27], [0] * 12 + [0, 1]
    _run_in(p, nets, drops)
    assert p.budget == pytest.approx(300_000.0 * 0.1 * 0.85) and p.counts["queue"] == 1
    assert "queue" in p.event
    capped = p.budget  # the next drop within a second does not cap again (the rate is our own now)
    p._scans += 1
    p.update_budget(_acks_in([*nets, 0.26], 14, 2, delivered=200_000.0))
    assert p.budget == pytest.approx(capped * 1.05) and p.counts["queue"] == 1


@pytest.mark.parametrize("case", ["long path", "stall", "off", "no drop"])
def test_a_full_window_is_not_a_queue_on_a_long_path_nor_after_a_stall(case: str) -> None:
    p = LinkAwareScale((0.01, 0.07), margin=0.85, queue_cap=case != "off")
    p.budget = 70_000.0
    floor = 0.35 if case == "long path" else 0.08  # three scans in flight with no queue at all
    nets = [floor] * 12 + [0.36, 0.37, 0.36] if case == "long path" else [0.08] * 12 + [0.26, 0.27, 0.25]
    drops = [0] * 14 + [0 if case == "no drop" else 2]
    _run_in(p, nets, drops, since_ack=0.8 if case == "stall" else 0.05)
    assert p.counts["queue"] == 0 and p.budget > 70_000.0


def test_a_silence_is_not_a_queue_even_where_stalls_are_not_skipped() -> None:
    """Scans held back through an outage, then acks of scans that waited it out: the last second's
    deliveries are no rate, so no cap for a second after the silence, with stall skipping off
    (``stall_after`` 0) as with it on; a standing queue after that is capped."""
    pts = _scan()
    p = LinkAwareScale((0.01, 0.07), margin=0.85, stall_after=0.0)
    p.choose_cloud(pts, LinkView(0.0, math.nan, math.nan, 0.1))
    p.budget = 70_000.0
    nets = [0.08] * 12
    for i in range(12):
        p.decide(len(pts), _acks_in(nets[: i + 1], i, 0), counter(pts))
    silent = replace(_acks_in(nets, 11, 3, since_ack=0.8), in_flight=3)
    assert not p.decide(len(pts), silent, counter(pts)).skip  # stall skipping off
    for i in range(12, 30):  # acks again, a standing queue and the window full
        nets.append(0.3)
        p.decide(len(pts), _acks_in(nets, i, 3 + i), counter(pts))
        if i < 21:
            assert p.counts["queue"] == 0, i
    assert p.counts["queue"] >= 1


def test_late_within_the_jitter_holds_the_budget() -> None:
    jittery = [AckInfo(50_000, 0.060 + 0.012 * ((i * 7) % 5 - 2), 0.1) for i in range(10)]
    late = (*jittery, AckInfo(50_000, 0.072, 0.118))  # within what the network times did lately
    assert late_cause(late, 0.1) == "jitter"
    p = LinkAwareScale((0.01, 0.2))
    p.budget = 100_000.0
    p.update_budget(LinkView(0.118, 1e6, 12.0, 0.1, acks=1, recent=late))
    assert p.budget == 100_000.0 and "jitter" in p.event and p.counts["late_jitter"] == 1
    # without the distinction every late scan cuts at once (the earlier behaviour)
    q = LinkAwareScale((0.01, 0.2), jitter_aware=False)
    q.budget = 100_000.0
    q.update_budget(LinkView(0.118, 1e6, 12.0, 0.1, acks=1, recent=late))
    assert q.budget == pytest.approx(80_000.0)


def test_a_jittery_link_gets_a_longer_slot_a_steady_one_does_not() -> None:
    rng = np.random.default_rng(3)

    def acks(sd: float) -> tuple[AckInfo, ...]:
        return tuple(AckInfo(30_000, 0.05, 0.1 + d, 1) for d in rng.normal(0, sd, 30))

    assert jitter_slots(acks(0.002), 0.1, 2, 0.2)[0] == 1
    slots, sd = jitter_slots(acks(0.02), 0.1, 2, 0.2)
    assert slots == 2 and sd == pytest.approx(0.02, rel=0.35)
    assert jitter_slots(acks(0.02), 0.1, 1, 0.2)[0] == 1  # pacing for jitter off
    pts = _scan()
    assert not LinkAwareScale((0.01, 0.07)).decide(  # off by default
        len(pts), LinkView(0.1, 1e6, 6.0, 0.1, recent=acks(0.02)), counter(pts)).cause == "jitter"
    p = LinkAwareScale((0.01, 0.07), raw_share=1.0, jitter_pace=2)
    p.choose_cloud(pts, LinkView(0.0, math.nan, math.nan, 0.1))
    p.budget = 1e6
    d = p.decide(len(pts), LinkView(0.1, 1e6, 6.0, 0.1, recent=acks(0.02)), counter(pts))
    assert d.cause == "jitter" and "jitter" in d.reason and not d.skip
    assert p.decide(len(pts), LinkView(0.1, 1e6, 6.0, 0.1, recent=acks(0.02)), counter(pts)).skip


def test_a_skipped_slot_sets_the_deadline() -> None:
    p = LinkAwareScale((0.01, 0.2))
    p.budget = 100_000.0
    p.update_budget(LinkView(0.2, 1e6, 12.0, 0.1, acks=1, last_slot=2))  # meant to take two periods
    assert p.budget == pytest.approx(100_000.0 * 1.05**2)  # on time; grown for two periods


def test_rate_policy_is_loaded_by_name() -> None:
    p = load_scale_policy("rate", 0.05, (0.01, 0.3), widen=2.0, max_skip=3)
    assert isinstance(p, LinkAwareScale) and p.candidates[p.in_range - 1] == pytest.approx(0.3)
    assert p.candidates[-1] == pytest.approx(0.6) and p.max_skip == 3
    with pytest.raises(ValueError):
        candidate_grid(0.1, 0.05)
    assert widened_grid(0.01, 0.07, 1.0) == []


def test_nothing_in_range_fits_widen_first_then_lower_the_rate() -> None:
    pts = _scan()
    n = {v: len(voxel_downsample(pts, v)) for v in (0.07, 0.14)}
    p = LinkAwareScale((0.01, 0.07), widen=2.0, max_skip=2, raw_share=1.0)
    p.choose_cloud(pts, LinkView(0.0, math.nan, math.nan, 0.1))
    link = LinkView(0.1, 1e6, 6.0, 0.1)
    p.budget = 6.0 * (n[0.07] + n[0.14]) / 2 / 1.05  # between the range's end and the widened end
    d = p.decide(len(pts), link, counter(pts))
    assert 0.07 < d.voxel <= 0.14 and not d.skip and d.cause == "widen" and "widened" in d.reason
    p.budget = 6.0 * n[0.14] / 1.6 / 1.05  # the widened end needs 2 periods: send 1, skip 1
    d = p.decide(len(pts), link, counter(pts))
    assert d.cause == "skip" and "2 periods" in d.reason and not d.skip
    d = p.decide(len(pts), link, counter(pts))
    assert d.skip and d.cause == "pace"
    assert not p.decide(len(pts), link, counter(pts)).skip  # the next one is sent again


def test_a_stall_skips_scans_and_the_late_scan_after_it_does_not_cut() -> None:
    pts = _scan()
    p = LinkAwareScale((0.01, 0.07), stall_after=0.5)
    p.choose_cloud(pts, LinkView(0.0, math.nan, math.nan, 0.1))
    p.budget = 80_000.0
    d = p.decide(len(pts), LinkView(0.1, 1e6, 6.0, 0.1, acks=1, since_ack=0.8, in_flight=2), counter(pts))
    assert d.skip and d.cause == "stall" and "no ack" in d.reason
    # nothing in flight: no stall however long ago the last ack was
    assert not p.decide(len(pts), LinkView(0.1, 1e6, 6.0, 0.1, acks=1, since_ack=5, in_flight=0),
                        counter(pts)).skip
    # a long path whose window held scans back: the one in flight left 0.1 s ago, it is not due
    # for 1.7 s (the old silence clock, the last ack alone, read 0.8 s as a stall)
    due = LinkView(0.1, 1e6, 6.0, 0.1, acks=1, since_ack=0.8, in_flight=1, overdue=0.1 - 1.8)
    assert not p.decide(len(pts), due, counter(pts)).skip
    assert not p.held_back(due)
    late = replace(due, since_ack=0.6, overdue=0.05)  # an outage: no ack for 0.6 s, the oldest is due
    assert p.decide(len(pts), late, counter(pts)).cause == "stall" and p.held_back(late) is not None
    p._stalled = True
    p.update_budget(LinkView(2.5, 1e5, 6.0, 0.1, acks=2))
    assert p.budget == pytest.approx(80_000.0 * 1.05) and p.counts["late_stall"] == 1


def test_budget_moves_once_per_new_ack() -> None:
    p = LinkAwareScale((0.01, 0.2), grow_slow=0.007, jitter_aware=False)
    p.budget = 200_000.0
    late = LinkView(0.3, 1_000_000.0, 12.0, 0.1, acks=7)
    p.update_budget(late)
    assert p.budget == pytest.approx(85_000.0)
    p.update_budget(late)  # the same late ack seen by the next scan: no second cut
    assert p.budget == pytest.approx(85_000.0)
    p.update_budget(LinkView(0.1, 1_000_000.0, 12.0, 0.1, acks=7))
    assert p.budget == pytest.approx(85_000.0)  # nothing new, no growth either
    p.update_budget(LinkView(0.1, 1_000_000.0, 12.0, 0.1, acks=8))
    assert p.budget == pytest.approx(85_000.0 * 1.007)  # a new on-time ack: grows, slowly after a late
    p.update_budget(LinkView(0.1, 1_000_000.0, 12.0, 0.1))  # no ack count (-1): every call moves it
    assert p.budget == pytest.approx(85_000.0 * 1.007**2)


def test_growth_is_slow_while_late_scans_are_recent_and_fast_after_a_quiet_spell() -> None:
    p = LinkAwareScale((0.01, 0.2), grow_slow=0.007, quiet=50, jitter_aware=False)
    assert LinkAwareScale((0.01, 0.2)).grow_slow == 0.05  # off by default: 5 % either way
    p.budget = 100_000.0
    p.update_budget(LinkView(0.3, math.nan, 12.0, 0.1))  # late, nothing measured: 80 %
    assert p.budget == pytest.approx(80_000.0)
    for _ in range(49):
        p.update_budget(on_time())
    assert p.budget == pytest.approx(80_000.0 * 1.007**49)
    p.update_budget(on_time())  # the 50th on-time ack in a row: the link is quiet, probe fast
    assert p.budget == pytest.approx(80_000.0 * 1.007**49 * 1.05)


def test_late_share_the_budget_settles_at_on_a_jittery_link() -> None:
    """A link whose delay jitters (σ 12 ms) and that carries 300 kB per period: cutting on every
    late scan wastes the link; judged by its network time, jitter-made lateness costs no cut."""
    late_share, budgets = {}, {}
    for slow, quiet, aware in ((0.05, 10**9, False), (0.007, 10**9, False), (0.007, 50, False),
                               (0.05, 10**9, True)):
        rng = np.random.default_rng(0)
        p = LinkAwareScale((0.01, 0.2), grow_slow=slow, quiet=quiet, jitter_aware=aware)
        p.budget = 50_000.0
        lates, prev, mean_budget = 0, 0.0, 0.0
        recent: list[AckInfo] = []
        for _ in range(20_000):
            # the network time: the delay's jitter, plus queueing once scans outgrow the link
            net = 0.05 + max(0.0, rng.normal(0, 0.012)) + max(0.0, p.budget - 300_000.0) / 2e6
            t = 0.1 + net - prev  # the arrival is late by this scan's delay past the last one's
            prev = net
            lates += t > 0.105
            recent = [*recent[-23:], AckInfo(int(p.budget), net, t)]
            p.update_budget(LinkView(t, 3e6, 12.0, 0.1, recent=tuple(recent)))
            mean_budget += p.budget / 20_000
        late_share[slow, quiet, aware] = lates / 20_000
        budgets[slow, quiet, aware] = mean_budget
    # cutting on every late scan keeps the budget far below the 300 kB the link carries, for no
    # fewer late scans; telling the jitter apart holds it near what the link carries
    assert budgets[0.05, 10**9, False] < 100_000 < 250_000 < budgets[0.05, 10**9, True] < 400_000, budgets
    assert late_share[0.05, 10**9, True] < 0.5, late_share  # probing the capacity costs some


def test_late_share_with_every_late_scan_cut_at_once() -> None:
    """The equilibrium the README quotes: a link whose delay jitters makes a scan late with a
    probability that grows with its size; cutting on every late scan, the budget settles where
    cuts balance growth, at the late share ln(1+g)/(ln(1+g)-ln(1-c))."""
    rng = np.random.default_rng(0)
    late_share = {}
    for slow, quiet in ((0.05, 10**9), (0.007, 10**9), (0.007, 50)):
        p = LinkAwareScale((0.01, 0.2), grow_slow=slow, quiet=quiet, jitter_aware=False)
        p.budget = 50_000.0
        lates = 0
        for _ in range(20_000):
            late = rng.random() < min(1.0, p.budget / 200_000.0)  # bigger scans: more often late
            lates += late
            p.update_budget(LinkView(0.2 if late else 0.1, math.nan, 12.0, 0.1))
        late_share[slow, quiet] = lates / 20_000
    assert late_share[0.05, 10**9] == pytest.approx(0.18, abs=0.03)
    assert late_share[0.007, 10**9] == pytest.approx(0.03, abs=0.01)
    # the fast probe after a quiet spell (the default) adds a little: still under 5 %
    assert late_share[0.007, 10**9] < late_share[0.007, 50] < 0.05


def test_the_budget_grows_only_as_far_as_the_link_has_shown_it_carries() -> None:
    """Scans sent as they are (230 kB, HDL-64) on a 20 Mbps link, on time: the budget stops at 1.5
    times them instead of growing 5 % a period until compression goes off (KITTI-360, `capped`:
    budget 1.6 MB, 730 kB scans, 8 of 100 lost). On a fast link the same scans, whose bytes move
    in 2 ms, let it grow on."""
    def grow(net: float) -> float:
        p = LinkAwareScale((0.02, 0.5))
        p.budget = 250_000.0
        acks = tuple(AckInfo(230_000, net, 0.1) for _ in range(20))
        for i in range(100):
            p.update_budget(LinkView(0.1, 2.3e6, 2.0, 0.1, acks=i, recent=acks))
        return p.budget

    slow = grow(0.092 + 0.010)  # 20 Mbps: 92 ms on the wire, plus the delay
    assert slow == pytest.approx(1.5 * 230_000)
    assert grow(0.002) > 20 * 230_000  # 115 MB/s shown: no cap in sight
    # with nothing acked yet (or the cap off) the budget grows as before
    p = LinkAwareScale((0.02, 0.5), headroom=0)
    p.budget = 250_000.0
    for i in range(100):
        p.update_budget(LinkView(0.1, 2.3e6, 2.0, 0.1, acks=i, recent=(AckInfo(230_000, 0.102, 0.1),)))
    assert p.budget == pytest.approx(250_000.0 * 1.05**100)
    # a budget already above the cap is not lowered by it: only a late scan cuts
    q = LinkAwareScale((0.02, 0.5))
    q.budget = 1e6
    q.update_budget(LinkView(0.1, 2.3e6, 2.0, 0.1, acks=1, recent=(AckInfo(230_000, 0.102, 0.1),)))
    assert q.budget == 1e6


def test_a_scan_the_window_holds_back_in_a_stall_is_a_stall_skip() -> None:
    pts = _scan()
    p = LinkAwareScale((0.01, 0.07), stall_after=0.5)
    p.choose_cloud(pts, LinkView(0.0, math.nan, math.nan, 0.1))
    p.budget = 80_000.0
    p.decide(len(pts), LinkView(0.1, 1e6, 6.0, 0.1, acks=1), counter(pts))
    budget = p.budget
    # the edge still answering: a window drop, not the policy's
    assert p.held_back(LinkView(0.1, 1e6, 6.0, 0.1, acks=1, since_ack=0.2, in_flight=3)) is None
    d = p.held_back(LinkView(0.1, 1e6, 6.0, 0.1, acks=1, since_ack=0.7, in_flight=3))
    assert d is not None and d.skip and d.cause == "stall" and "window full" in d.reason
    # the late scan after the outage is held, as after the policy's own stall skips (not cut)
    queued = tuple(AckInfo(50_000, 0.030, 0.1) for _ in range(10)) + (AckInfo(50_000, 0.9, 1.0),)
    p.update_budget(LinkView(1.0, 1e5, 6.0, 0.1, acks=2, recent=queued))
    assert p.counts["late_stall"] == 1 and p.counts["late_size"] == 0 and p.budget == budget
    # stall skipping off: the window's
    q = LinkAwareScale((0.01, 0.07), stall_after=0.0)
    assert q.held_back(LinkView(0.1, 1e6, 6.0, 0.1, acks=1, since_ack=5.0, in_flight=3)) is None


def test_a_deep_queue_on_the_link_is_a_stall_and_its_late_scans_still_cut() -> None:
    """A rain fade on a satellite path (floor 0.6 s, window 7 scans): acks kept coming, so no
    silence, but each one later than the last, up to 3.7 s, most after the ack timeout (so the
    window no longer counted their scans); every scan the window let through queued behind them.
    Now, with scans queued (sent after the newest answered one, expired ones too) and the newest
    ack's network time (late ones too) stall_after above the floor, the scan is skipped as a stall
    (announced); not a silence, so the late scans after it still cut the budget."""
    pts = _scan()
    p = LinkAwareScale((0.01, 0.07), stall_after=0.5, queue_stall=True, queue_stall_max=3)
    p.choose_cloud(pts, LinkView(0.0, math.nan, math.nan, 0.1))
    p.budget = 80_000.0
    floor = tuple(AckInfo(40_000, 0.60, 0.1) for _ in range(10))
    link = LinkView(0.1, 4e5, 6.0, 0.1, acks=10, recent=floor, in_flight=5, queued=5, floor_net=0.6)
    p.update_budget(link)
    p.budget = 80_000.0
    assert not p.decide(len(pts), link, counter(pts)).skip  # at the floor: sent
    queued = floor + (AckInfo(40_000, 1.2, 0.5),)
    deep = replace(link, acks=11, recent=queued, last_t=0.5, newest_net=1.2)
    d = p.decide(len(pts), deep, counter(pts))
    assert d.skip and d.cause == "stall" and "queue" in d.reason and p.counts["queue_stall"] == 1
    assert p.counts["late_size"] == 1 and p.budget < 80_000.0  # the late one cut: not a silence
    assert not p._stalled
    # the scans the ack timeout expired still queue: nothing in flight, a stall all the same
    assert p.decide(len(pts), replace(deep, in_flight=0), counter(pts)).cause == "stall"
    # nothing queued behind the newest answer: the queue has drained, send
    assert not p.decide(len(pts), replace(deep, queued=0), counter(pts)).skip
    # the window full behind the queue: a stall skip too (announced), not a window drop
    d = p.held_back(replace(deep, since_ack=0.1))
    assert d is not None and d.cause == "stall" and "queue" in d.reason
    # within stall_after of the floor: no stall
    assert p.held_back(replace(link, newest_net=1.0)) is None
    # no floor known yet on this route (fewer than 10 acks, or a move): no queue to judge
    assert p.held_back(replace(link, newest_net=3.0, floor_net=math.nan)) is None
    # and off with queue_stall=False
    q = LinkAwareScale((0.01, 0.07), stall_after=0.5, queue_stall=False)
    q.choose_cloud(pts, LinkView(0.0, math.nan, math.nan, 0.1))
    q.update_budget(link)
    q.budget = 80_000.0
    assert not q.decide(len(pts), deep, counter(pts)).skip


def test_a_queue_stall_lets_a_scan_through_after_a_few_and_ends_pacing() -> None:
    """The newest network time is a scan's that waited: on a path whose delay rose for good it
    stays above the old floor until the floor follows. At most ``queue_stall_max`` stall skips in
    a row, then a scan goes; and a queue stall takes the place of a pacing skip left from before."""
    pts = _scan()
    p = LinkAwareScale((0.01, 0.07), stall_after=0.5, queue_stall=True, queue_stall_max=3)
    p.choose_cloud(pts, LinkView(0.0, math.nan, math.nan, 0.1))
    floor = tuple(AckInfo(40_000, 0.60, 0.1) for _ in range(10))
    link = LinkView(0.1, 4e5, 6.0, 0.1, acks=10, recent=floor, in_flight=2, queued=2, floor_net=0.6,
                    newest_net=1.8)
    p.update_budget(link)
    skips = [p.decide(len(pts), link, counter(pts)).skip for _ in range(9)]
    assert skips == [True, True, True, False] * 2 + [True]
    assert p.counts["queue_stall"] == 7 and p.counts["queue_stall_cap"] == 2
    p._skip_left = 2  # a scan paced over three periods...
    assert p.decide(len(pts), link, counter(pts)).cause == "stall" and p._skip_left == 0  # ...ends
