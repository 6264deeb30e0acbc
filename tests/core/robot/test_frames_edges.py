"""Which edge detects the robot's frames (robot/edgechoice.py) and how the book holds a frame to the
edge it was sent to: pure, no Zenoh."""

from __future__ import annotations

import numpy as np

from zoffload.policy.offload import EDGE, EdgeOnly
from zoffload.robot.edgechoice import EdgeChoice
from zoffload.robot.frames import FallbackRules, FrameBook

NONE = (np.zeros((0, 4), np.float32), np.zeros(0, np.float32))


def test_the_choice_is_stable_spread_and_sticky() -> None:
    edges = frozenset({"edge1", "edge2"})
    picks = {}
    for k in range(40):
        c = EdgeChoice(f"robot{k}")
        c.present(edges)
        picks[k] = c.pick(0.0)
        assert all(c.pick(t) == picks[k] for t in (1.0, 2.0))  # the same every frame
        c.present(edges | {"edge3"})  # an edge comes: a robot never moves for it
        assert c.pick(3.0) == picks[k] and c.switches == 0
    assert 10 <= sum(p == "edge1" for p in picks.values()) <= 30  # idle edges share the robots


def test_moves_when_its_edge_goes_or_drains_and_only_when_full_for_a_while() -> None:
    c = EdgeChoice("robot1", full_below=0.1, dwell=5.0)
    c.present(frozenset({"edge1", "edge2"}))
    first = c.pick(0.0)
    assert first is not None
    other = ({"edge1", "edge2"} - {first}).pop()
    c.status(first, {"detector.free": 0.05})  # full
    assert c.pick(1.0) == other and c.switches == 1  # room elsewhere: moves
    c.status(other, {"detector.free": 0.02})
    c.status(first, {"detector.free": 0.9})
    assert c.pick(2.0) == other  # full too, but it just moved: stays for the dwell
    assert c.pick(6.5) == first and c.switches == 2
    c.status(other, {"detector.free": 0.01})
    c.status(first, {"detector.free": 0.01})
    assert c.pick(20.0) == first  # every edge full: staying costs nothing
    c.status(first, {"detector.free": 0.5, "draining": 1.0})
    assert c.pick(20.1) == other and c.switches == 3  # draining: at once, even to a full edge
    c.present(frozenset({first}))  # the other goes; only the draining one is left: better than none
    assert c.pick(20.2) == first
    c.present(frozenset())
    assert c.pick(21.0) is None
    c.status("edge9", {"detector.free": 0.0})  # status of an edge whose token is not held: ignored
    assert "edge9" not in c.edges


def test_a_frame_is_answered_only_by_the_edge_it_was_sent_to_and_lost_when_that_edge_goes() -> None:
    b = FrameBook(EdgeOnly(), FallbackRules(reply_timeout=0.5))
    b.edges_changed(True, 0.0)
    for seq, edge in enumerate(("edge1", "edge1", "edge2", "")):
        side, probe = b.decide(seq, seq, capture=0.0, now=0.0)
        assert side == EDGE
        b.sent(seq, 0.0, probe, edge=edge)
        assert b.edge_of(seq) == edge
    # Another edge answering frame 0: counted, the frame still waits for edge1
    assert b.edge_result(0, "ok", 0.1, 0.02, 0.0, *NONE, edge="edge2") == "wrong_edge"
    assert b.counters["wrong_edge_results"] == 1 and 0 in b.in_flight
    assert b.edge_result(0, "ok", 0.1, 0.02, 0.0, *NONE, edge="edge1") == "edge_done"
    assert b.edge_result(3, "ok", 0.1, 0.02, 0.0, *NONE, edge="edge2") == "edge_done"  # "" = any edge
    # edge1 goes while edge2 stays: its frame is lost at once, edge2's waits, no fallback
    assert b.edge_gone("edge1", 0.2) == [1]
    b.edges_changed(True, 0.2)
    assert b.records[1]["status"] == "edge_lost" and 2 in b.in_flight and not b.fallback
    assert b.edge_result(2, "ok", 0.3, 0.02, 0.0, *NONE, edge="edge2") == "edge_done"
    assert b.per_edge == {"edge1": 1, "edge2": 2} and b.balanced()
    assert b.summary()["per_edge"] == {"edge1": 1, "edge2": 2}


def test_frames_are_shrunk_for_an_edge_only_once_it_says_what_its_detector_takes() -> None:
    choice = EdgeChoice("r1")
    choice.present(frozenset({"e1", "e2"}))
    assert choice.send_size("e1", 848, 480) == (848, 480)  # nothing said yet: whole
    choice.status("e1", {"detector.free": 1.0, "detector.input_w": 416.0, "detector.input_h": 416.0,
                         "detector.stretch": 1.0})
    choice.status("e2", {"detector.input_w": 416.0, "detector.input_h": 416.0, "detector.stretch": 0.0})
    assert choice.send_size("e1", 848, 480) == (416, 416)  # stretched to the input
    assert choice.send_size("e2", 848, 480) == (416, 235)  # letterboxed at one scale
    assert choice.send_size("e2", 320, 240) == (320, 240)  # never enlarged
    assert choice.send_size("", 848, 480) == (848, 480) and choice.send_size("gone", 848, 480) == (848, 480)
    # What is not a believable input size changes nothing (the last good one stays)
    for bad in ({"detector.input_w": float("nan"), "detector.input_h": 416.0},
                {"detector.input_w": 1e9, "detector.input_h": 416.0},
                {"detector.input_w": 416.5, "detector.input_h": 416.0},
                {"detector.input_w": 8.0, "detector.input_h": 8.0}, {"detector.input_w": 416.0}):
        choice.status("e1", bad)
        assert choice.send_size("e1", 848, 480) == (416, 416)
    choice.present(frozenset({"e2"}))
    choice.present(frozenset({"e1", "e2"}))  # back after going: it says again before frames shrink
    assert choice.send_size("e1", 848, 480) == (848, 480)
