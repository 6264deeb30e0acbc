from __future__ import annotations

import pytest

from zoffload.lab.eval.report import SEED_TABLE_I, table_markdown
from zoffload.lab.scan_experiment import policy_voxel
from zoffload.runtime.errors import ConfigError


def test_policies() -> None:
    assert policy_voxel("local") is None and policy_voxel("raw") == 0.0
    assert policy_voxel("fixed:0.05") == 0.05 and policy_voxel("dqn") == 0.05
    for bad in ("fixed:", "fixed:-1", "dqn-someday", "fixed:abc"):
        with pytest.raises(ConfigError):
            policy_voxel(bad)


def row(policy: str, map_points: int, received: int = 90) -> dict:
    return {"policy": policy, "trace": "wifi-locations", "scans": "sim", "S_kB": 190.0,
            "points_before": 28000.0, "points_after": 16000.0, "scans_sent": 95, "scans_produced": 100,
            "scans_received": received, "T_mean": 0.12, "T_le_0.11": 0.8, "map_points": map_points,
            "trajectory_error": {"ate_rmse": 0.25}}


def test_table_has_our_rows_the_papers_rows_and_map_ratio_to_local() -> None:
    md = table_markdown([row("local", 200_000, 100), row("raw", 80_000)])
    lines = md.splitlines()
    assert lines[0].startswith("| run | trace | S (kB/scan)")
    assert "| local | (no network) |" in lines[2]
    assert "| raw | wifi-locations |" in lines[3] and "-60 %" in lines[3] and "90 / 100 (95)" in lines[3]
    assert "0.250" in lines[3]
    assert len(lines) == 4 + len(SEED_TABLE_I)
    assert "529" not in md and "528" in md and "92,644" in md and "-28 %" in md  # the paper's own
