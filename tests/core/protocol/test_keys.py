from __future__ import annotations

import pytest

from zoffload.protocol.keys import Keys


def test_layout_and_prefixes() -> None:
    k = Keys()
    assert k.scan("r1") == "zoffload/data/r1/scan"
    assert k.scan_ack("r1", "e1") == "zoffload/data/r1/scan_ack/e1"
    assert k.scan_acks("r1") == "zoffload/data/r1/scan_ack/**"
    assert k.checkpoints("r1") == "zoffload/data/r1/checkpoint/**"
    assert k.map("r1", "e1") == "zoffload/ctrl/r1/map/e1"
    assert k.all_maps("e1") == "zoffload/ctrl/*/map/e1"
    assert k.map_before("r1") == "zoffload/ctrl/r1/map"
    assert k.edge_alive("e1") == "zoffload/alive/edge/e1"
    assert k.robot_status("r1") == "zoffload/status/r1"
    assert Keys("lab").all_scans() == "lab/data/*/scan"


def test_robot_of_parses_only_its_namespace() -> None:
    k = Keys()
    assert k.robot_of("zoffload/data/r-2/scan") == "r-2"
    assert k.robot_of("zoffload/ctrl/r.3/map") == "r.3"
    assert k.robot_of("other/data/r1/scan") is None
    assert k.robot_of("zoffload/status/r1") is None


def test_an_answer_key_names_its_edge() -> None:
    k = Keys()
    assert k.answering_edge(k.scan_ack("r1", "e-1")) == "e-1"
    assert k.answering_edge(k.checkpoint("r1", "e2")) == "e2"
    assert k.answering_edge("zoffload/data/r1/detections") == ""  # the key before per-edge answers
    for bad in ("zoffload/data/r1/scan_ack/e1/x", "zoffload/data/r1/scan/e1", "lab/data/r1/scan_ack/e1",
                "zoffload/ctrl/r1/scan_ack/e1", "zoffload/data/r1"):
        assert k.answering_edge(bad) is None, bad
    with pytest.raises(ValueError, match="edge id"):
        k.scan_ack("r1", "*")


def test_one_builder_makes_every_answer_key_and_its_one_chunk_wildcards() -> None:
    k = Keys("lab")
    assert k.answer("detections", "r1", "e1") == k.detections("r1", "e1") == "lab/data/r1/detections/e1"
    assert k.answer("scan_ack", "*", "e1") == "lab/data/*/scan_ack/e1"  # what edge e1 may put
    assert k.answer("checkpoint", "r1", "*") == "lab/data/r1/checkpoint/*"  # what reaches robot r1
    assert k.answer("scan_ack", "*", "*") == "lab/data/*/scan_ack/*"
    # a subscription: every edge's, and the key before per-edge answers (no edge chunk)
    assert k.answers("scan_ack", "r1") == k.scan_acks("r1") == "lab/data/r1/scan_ack/**"
    assert k.answers("detections") == "lab/data/*/detections/**"
    assert k.detections_to("r1") == "lab/data/r1/detections/**"
    for kind in Keys.ANSWERS:  # every key it makes is an answer key naming its edge
        assert k.answering_edge(k.answer(kind, "r1", "e-2")) == "e-2"
    with pytest.raises(ValueError, match="not an answer"):
        k.answer("scan", "r1", "e1")
    with pytest.raises(ValueError, match="edge id"):
        k.answer("scan_ack", "r1", "e*")
    with pytest.raises(ValueError, match="robot id"):
        k.answers("checkpoint", "**")
    with pytest.raises(ValueError, match="robot id"):
        k.checkpoint("*", "e1")  # the named keys are for one robot and one edge: never a wildcard


def test_a_map_key_names_one_edge() -> None:
    k = Keys()
    assert k.robot_of(k.map("r1", "e1")) == "r1" and k.last_chunk(k.map("r1", "e1")) == "e1"
    assert k.robot_of(k.map_before("r1")) == "r1"
    for bad in ("*", "e/1", ""):
        with pytest.raises(ValueError, match="edge id"):
            k.map("r1", bad)
        with pytest.raises(ValueError, match="edge id"):
            k.all_maps(bad)


@pytest.mark.parametrize("bad", ["", "a/b", "r*", "r$", "r#", "r?", "with space"])
def test_ids_that_would_break_key_expressions_are_rejected(bad: str) -> None:
    with pytest.raises(ValueError, match="invalid"):
        Keys().scan(bad)
