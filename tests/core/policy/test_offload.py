"""The offloading strategies: the thesis' rules and ours."""

from __future__ import annotations

import pytest

from zoffload.policy.offload import EDGE, HOLD, LOCAL, OffloadState, make_strategy


def _st(**kw: float) -> OffloadState:
    base = {"now": 0.0, "edge_available": True}
    base.update(kw)
    return OffloadState(**base)  # type: ignore[arg-type]


def test_fixed_ratio_is_algorithm_1() -> None:
    s = make_strategy("ratio:0.3")
    sides = [s.decide(_st()) for _ in range(100)]
    assert sides.count(EDGE) == 30
    assert sides[:4] == [EDGE, LOCAL, LOCAL, EDGE]  # offload while offloaded/total < r
    with pytest.raises(ValueError):
        make_strategy("ratio:1.5")
    with pytest.raises(ValueError):
        make_strategy("sometimes")


def test_thesis_rule_constraints_then_rtt() -> None:
    s = make_strategy("thesis", cpu_max=80, bw_max_mbps=100)
    s.on_local_result(0.05)
    s.on_edge_result(0.10)
    assert s.decide(_st()) == LOCAL  # local is faster
    assert s.decide(_st(cpu_percent=85)) == EDGE  # CPU bound first
    s.on_edge_result(0.01)
    s.on_edge_result(0.01)
    assert s.decide(_st()) == EDGE  # edge average 0.04 < 0.05
    assert s.decide(_st(mbps_out=120)) == LOCAL  # bandwidth bound
    assert s.decide(_st(edge_available=False)) == LOCAL  # no edge: local whatever the rule says


def test_frames_that_never_return_count_in_our_rule_but_not_in_the_thesis() -> None:
    """The thesis' failure under a cap: the few edge frames that return look fast."""
    thesis, ours = make_strategy("thesis"), make_strategy("dynamic", max_in_flight=10)
    for s in (thesis, ours):
        s.on_local_result(0.15)
        for _ in range(3):
            s.on_edge_result(0.08)  # the frames that made it
        for _ in range(7):
            s.on_edge_timeout(0.5)  # the ones the link dropped
    assert thesis.decide(_st()) == EDGE
    assert ours.decide(_st()) == LOCAL


def test_our_rule_sees_an_edge_that_stopped_answering() -> None:
    ours = make_strategy("dynamic", max_in_flight=5)
    ours.on_local_result(0.15)
    ours.on_edge_result(0.08)
    assert ours.decide(_st()) == EDGE
    assert ours.decide(_st(in_flight=1, oldest_in_flight_age=0.3)) == LOCAL  # already slower than local
    # window full: held back while local is the slower side ...
    assert ours.decide(_st(in_flight=5, oldest_in_flight_age=0.01)) == HOLD
    # ... detected locally when only the CPU bound sent it to the edge and local is faster
    cpu_bound = make_strategy("dynamic", cpu_max=90, max_in_flight=5)
    cpu_bound.on_local_result(0.03)
    cpu_bound.on_edge_result(0.04)
    assert cpu_bound.decide(_st(cpu_percent=95)) == EDGE
    assert cpu_bound.decide(_st(cpu_percent=95, in_flight=5, oldest_in_flight_age=0.01)) == LOCAL
    # while local, one frame in probe_every goes to the edge once nothing is in flight
    ours.on_edge_timeout(0.5)
    sides = [ours.decide(_st()) for _ in range(20)]
    assert sides.count(EDGE) == 2


def test_our_window_halves_on_losses_and_grows_back() -> None:
    ours = make_strategy("dynamic", max_in_flight=4)
    assert ours.flight_window == 4  # type: ignore[attr-defined]
    ours.on_local_result(0.5, service=0.5)
    ours.on_edge_result(0.1)
    ours.on_edge_timeout(0.5)
    assert ours.flight_window == 2  # type: ignore[attr-defined]
    ours.on_edge_timeout(0.5)
    assert ours.flight_window == 2  # type: ignore[attr-defined]  # never below two
    assert ours.decide(_st(in_flight=2, oldest_in_flight_age=0.05)) == HOLD  # local is slower
    for _ in range(8):
        ours.on_edge_result(0.1)
    assert ours.flight_window == 4  # type: ignore[attr-defined]
