from __future__ import annotations

import pytest

from zoffload.protocol.keys import Keys


def test_layout_and_prefixes() -> None:
    k = Keys()
    assert k.scan("r1") == "zoffload/data/r1/scan"
    assert k.scan_ack("r1", "e1") == "zoffload/data/r1/scan_ack/e1"
    assert k.scan_acks("r1") == "zoffload/data/r1/scan_ack/**"
    assert k.all_detections("e1") == "zoffload/data/*/detections/e1"
    assert k.checkpoints("r1") == "zoffload/data/r1/checkpoint/**"
    assert k.map("r1") == "zoffload/ctrl/r1/map"
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


@pytest.mark.parametrize("bad", ["", "a/b", "r*", "r$", "r#", "r?", "with space"])
def test_ids_that_would_break_key_expressions_are_rejected(bad: str) -> None:
    with pytest.raises(ValueError, match="invalid"):
        Keys().scan(bad)
