"""`zoffload experiment soak`, short: both daemons sampled, a CSV row per period, the plot, the
summary with the robot's counters balanced. The real soak (1 h) is the lead's to run."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.system
pytest.importorskip("kiss_icp")
pytest.importorskip("matplotlib")


def run(out: Path, duration: float, period: float, camera: str = "off") -> dict:
    r = subprocess.run([sys.executable, "-m", "zoffload.cli", "experiment", "soak", "--duration",
                        str(duration), "--period", str(period), "--camera", camera, "--out", str(out)],
                       capture_output=True, text=True, timeout=duration + 180)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "soak" in r.stdout and "Traceback" not in r.stderr
    return json.loads((out / "soak.json").read_text())


def test_a_short_soak_records_resources_and_counters(tmp_path: Path) -> None:
    s = run(tmp_path, 8, 1.2)
    rows = list(csv.DictReader(open(tmp_path / "soak.csv")))
    assert len(rows) == s["samples"] >= 5
    assert all(float(r["edge.rss_mb"]) > 50 and int(r["robot.threads"]) > 0 and int(r["edge.fds"]) > 0
               for r in rows)
    assert float(rows[-1]["robot.acked"]) > 20 and float(rows[-1]["edge.samples"]) > 20
    assert s["exit_codes"] == {"robot": 0, "edge": 0} and s["balanced"] is True
    assert set(s["rss_growth"]) == {"edge", "robot"}
    assert (tmp_path / "soak.png").stat().st_size > 10_000
    assert (tmp_path / "robot" / "robot_metrics.json").exists() and (tmp_path / "maps").is_dir()


@pytest.mark.slow
def test_a_two_minute_soak_keeps_threads_and_fds_flat(tmp_path: Path) -> None:
    s = run(tmp_path, 120, 10, camera="auto")
    for name in ("edge", "robot"):
        lo, hi = s["threads"][name]
        assert hi - lo <= 4, s
        lo, hi = s["fds"][name]
        assert hi - lo <= 4, s
    assert s["balanced"] is True
