from __future__ import annotations

import pytest

from zoffload.protocol.keys import Keys


def test_layout_and_prefixes() -> None:
    k = Keys()
    assert k.scan("r1") == "zoffload/data/r1/scan"
    assert k.scan_ack("r1") == "zoffload/data/r1/scan_ack"
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


@pytest.mark.parametrize("bad", ["", "a/b", "r*", "r$", "r#", "r?", "with space"])
def test_ids_that_would_break_key_expressions_are_rejected(bad: str) -> None:
    with pytest.raises(ValueError, match="invalid"):
        Keys().scan(bad)
