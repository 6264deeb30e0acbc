"""Our link-aware scale policy: the byte budget follows the acks, the choice fits the budget."""

from __future__ import annotations

import math

import numpy as np
import pytest

from zoffload.mapping.voxel import voxel_downsample
from zoffload.policy.onnx_scale import load_scale_policy
from zoffload.policy.rate import LinkAwareScale, LinkView, candidate_grid
from zoffload.sources.simulated import SimulatedSource


def _scan() -> np.ndarray:
    pts = SimulatedSource(seed=0).read(3).points
    return pts[np.isfinite(pts).all(axis=1)]


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
    p = LinkAwareScale((0.01, 0.2))
    p.budget = 100_000.0
    # on time: the budget grows 5 %, then the finest size whose points x 6 B fit it
    v, down = p.choose_cloud(pts, LinkView(0.1, 2e6, 6.0, 0.1))
    assert p.budget == pytest.approx(105_000.0)
    fits = [c for c in p.candidates if len(voxel_downsample(pts, c)) * 6.0 <= p.budget]
    assert v == min(fits) and len(down) * 6.0 <= p.budget
    finer = [c for c in p.candidates if c < v]
    assert all(len(voxel_downsample(pts, c)) * 6.0 > p.budget for c in finer)


def test_a_late_scan_cuts_the_budget_to_what_the_link_delivers() -> None:
    p = LinkAwareScale((0.01, 0.2), margin=0.85)
    p.budget = 400_000.0
    p.update_budget(LinkView(0.3, 1_000_000.0, 12.0, 0.1))  # 1 MB/s acked: 85 kB per period
    assert p.budget == pytest.approx(85_000.0)
    p.update_budget(LinkView(0.3, 5_000_000.0, 12.0, 0.1))  # never more than 80 % of before
    assert p.budget == pytest.approx(68_000.0)
    v, _ = p.choose_cloud(_scan(), LinkView(0.1, 1e6, 12.0, 0.1))
    assert v > 0.05  # a tight budget means coarse voxels
    tiny = LinkAwareScale((0.01, 0.2))
    tiny.budget = 10.0
    assert tiny.choose_cloud(_scan(), LinkView(0.1, 1e6, 12.0, 0.1))[0] == tiny.candidates[-1]


def test_rate_policy_is_loaded_by_name() -> None:
    p = load_scale_policy("rate", 0.05, (0.01, 0.3))
    assert isinstance(p, LinkAwareScale) and p.candidates[-1] == pytest.approx(0.3)
    with pytest.raises(ValueError):
        candidate_grid(0.1, 0.05)


def test_budget_moves_once_per_new_ack() -> None:
    p = LinkAwareScale((0.01, 0.2), grow_slow=0.007)
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
    p = LinkAwareScale((0.01, 0.2), grow_slow=0.007, quiet=50)
    assert LinkAwareScale((0.01, 0.2)).grow_slow == 0.05  # off by default: 5 % either way
    p.budget = 100_000.0
    p.update_budget(LinkView(0.3, math.nan, 12.0, 0.1))  # late, nothing measured: 80 %
    assert p.budget == pytest.approx(80_000.0)
    on_time = LinkView(0.1, 1e6, 12.0, 0.1)
    for _ in range(49):
        p.update_budget(on_time)
    assert p.budget == pytest.approx(80_000.0 * 1.007**49)
    p.update_budget(on_time)  # the 50th on-time ack in a row: the link is quiet, probe fast
    assert p.budget == pytest.approx(80_000.0 * 1.007**49 * 1.05)


def test_late_share_the_budget_settles_at_on_a_jittery_link() -> None:
    """A link whose delay jitters makes a scan late with a probability that grows with its size:
    the budget settles where cuts balance growth, at the late share ln(1+g)/(ln(1+g)-ln(1-c))."""
    rng = np.random.default_rng(0)
    late_share = {}
    for slow, quiet in ((0.05, 10**9), (0.007, 10**9), (0.007, 50)):
        p = LinkAwareScale((0.01, 0.2), grow_slow=slow, quiet=quiet)
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
