"""Admission of robots to the edge: allowlist, max_robots, idle expiry, the refusal budget."""

from __future__ import annotations

from zoffload.edge.admission import Admission


def test_without_an_allowlist_the_first_max_robots_ids_are_served() -> None:
    a = Admission(max_robots=2)
    assert a.admit("r1", 0.0) and a.admit("r2", 0.0) and a.admit("r1", 1.0)
    assert not a.admit("r3", 1.0) and "at most 2 robots" in a.why_refused("r3")
    assert sorted(a.robots) == ["r1", "r2"] and a.counters["refused_full"] == 1


def test_the_allowlist_is_the_only_way_in() -> None:
    a = Admission(allow=["r1", "r2"], max_robots=8)
    assert a.admit("r1") and not a.admit("intruder")
    assert "not in this edge's allowlist" in a.why_refused("intruder")
    a2 = Admission(allow=["r1", "r2", "r3"], max_robots=2)  # both bounds hold
    assert a2.admit("r1") and a2.admit("r2") and not a2.admit("r3")


def test_idle_robots_expire_and_free_their_place() -> None:
    a = Admission(max_robots=1, idle_timeout=10.0)
    assert a.admit("r1", 0.0) and not a.admit("r2", 5.0)
    assert a.expire(9.0) == [] and a.admit("r1", 9.0)  # activity keeps it
    assert a.expire(15.0) == [] and a.expire(19.5) == ["r1"]
    assert not a.is_admitted("r1") and a.admit("r2", 20.0)
    assert a.status()["admission.evicted"] == 1 and a.status()["admission.robots"] == 1


def test_refusals_are_answered_within_a_budget_per_second() -> None:
    a = Admission(max_robots=1, refusals_per_s=5.0)
    answered = sum(a.answer_refusal(100.0) for _ in range(1000))  # a flood in one instant
    assert answered == 5
    assert a.counters["refusals_silent"] == 995
    assert sum(a.answer_refusal(100.0 + 0.1 * i) for i in range(1, 11)) == 5  # 5 per second after
