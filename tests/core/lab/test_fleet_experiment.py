"""The fleet experiment's pure parts: the events and traces script, the per-robot figures read
from the robot's files (with and without the fleet section), the aggregation and the report."""

from __future__ import annotations

from pathlib import Path

import pytest

from zoffload.lab import fleet_report as fr
from zoffload.lab.fleet_scenario import (
    EdgeEvent,
    ScenarioError,
    kills,
    parse_edge_cpu,
    parse_events,
    parse_traces,
)

EDGES = ["edge1", "edge2"]
ROBOTS = ["robot1", "robot2", "robot3"]


def test_events_parse_in_time_order() -> None:
    ev = parse_events("drain:edge2@12, kill:edge1@5,restart:edge1@8", EDGES)
    assert ev == [EdgeEvent("kill", "edge1", 5.0), EdgeEvent("restart", "edge1", 8.0),
                  EdgeEvent("drain", "edge2", 12.0)]
    assert [e.label() for e in ev] == ["kill:edge1@5", "restart:edge1@8", "drain:edge2@12"]
    assert kills(ev) == 1
    assert parse_events("", EDGES) == [] and parse_events(None, EDGES) == []


def test_five_kills_with_restarts() -> None:
    text = ",".join(f"kill:edge{1 + i % 2}@{3 * i + 2},restart:edge{1 + i % 2}@{3 * i + 3}" for i in range(5))
    ev = parse_events(text, EDGES)
    assert kills(ev) == 5 and len(ev) == 10


@pytest.mark.parametrize(("text", "message"), [
    ("kill:edge3@5", "no edge 'edge3'"),
    ("stop:edge1@5", "expected ACTION:EDGE@SECONDS"),
    ("kill:edge1@-1", "expected ACTION:EDGE@SECONDS"),
    ("kill:edge1", "expected ACTION:EDGE@SECONDS"),
    ("restart:edge1@3", "is running then"),
    ("kill:edge1@3,drain:edge1@4", "is not running then"),
    ("restart:edge1@9,kill:edge1@5,kill:edge1@7", "is not running then"),
])
def test_bad_events_are_refused_with_the_item(text: str, message: str) -> None:
    with pytest.raises(ScenarioError, match=message):
        parse_events(text, EDGES)


def test_traces_for_every_robot_and_per_robot() -> None:
    assert parse_traces(None, ROBOTS) == {}
    assert parse_traces(["wifi-congested"], ROBOTS) == dict.fromkeys(ROBOTS, "wifi-congested")
    assert parse_traces(["robot2=outage", "capped"], ROBOTS) == {
        "robot1": "capped", "robot2": "outage", "robot3": "capped"}
    assert parse_traces(["capped", "robot3=none"], ROBOTS) == {"robot1": "capped", "robot2": "capped"}
    with pytest.raises(ScenarioError, match="no robot 'robot9'"):
        parse_traces(["robot9=capped"], ROBOTS)
    with pytest.raises(ScenarioError, match="name a trace"):
        parse_traces(["robot1="], ROBOTS)


def test_edge_cpu_for_every_edge_and_per_edge() -> None:
    edges = ["edge1", "edge2"]
    assert parse_edge_cpu("", edges) == {}
    assert parse_edge_cpu("0.5", edges) == {"edge1": 0.5, "edge2": 0.5}
    assert parse_edge_cpu("edge2=1.5, 0.5", edges) == {"edge1": 0.5, "edge2": 1.5}
    assert parse_edge_cpu("edge1=0.4", edges) == {"edge1": 0.4}
    for bad, message in (("edge3=1", "no edge 'edge3'"), ("edge1=lots", "CORES or EDGE=CORES"),
                         ("0", "between 0.01"), ("edge1=1,edge1=2", "given twice"), ("1,2", "given twice")):
        with pytest.raises(ScenarioError, match=message):
            parse_edge_cpu(bad, edges)


def test_settled_phase_starts_after_the_last_move() -> None:
    """robot2 moves from edge1 to edge2 at its 10th scan (t = 101.0): the settled phase starts 5 s
    later; robot1 stays on edge1 and is late for half of it, robot2 on time on edge2."""
    r1 = _rows("a" * 100)
    for r in r1[80:]:
        r["rtt"] = "0.3" if int(r["seq"]) % 2 else "0.05"
    r2 = _rows("a" * 100)
    for r in r2[10:]:
        r["edge"] = "edge2"
    assert fr.last_move({"robot1": r1, "robot2": r2}) == pytest.approx(101.0)
    s = fr.settled_phase({"robot1": r1, "robot2": r2}, 0.1, start=100.0)
    assert s["from_s"] == pytest.approx(6.0)
    assert s["robots"]["robot2"] == {"scans": 40, "on_time": 1.0, "edge": "edge2"}
    assert s["robots"]["robot1"]["edge"] == "edge1"
    assert s["robots"]["robot1"]["on_time"] == pytest.approx(0.5 + 0.5 * 20 / 40)
    assert s["on_time_min"] == pytest.approx(0.75) and s["starving"] == 0
    r1[95]["rtt"] = "0.3"
    for r in r1[60:]:
        r["status"] = "lost"
    assert fr.settled_phase({"robot1": r1, "robot2": r2}, 0.1, start=100.0)["starving"] == 1
    # a move in the run's last seconds: an empty settled phase says nothing, nobody starves
    r3 = _rows("a" * 100)
    for r in r3[98:]:
        r["edge"] = "edge2"
    empty = fr.settled_phase({"robot3": r3}, 0.1, start=100.0)
    assert empty["on_time_min"] is None and empty["starving"] is None
    # nobody moved: from the start
    assert fr.settled_phase({"robot1": _rows("aaaa")}, 0.1, start=100.0)["from_s"] == 0.0


def _rows(statuses: str, period: float = 0.1) -> list[dict[str, object]]:
    """One row per character: a = acked by the edge, l = registered locally, x = no pose."""
    code = {"a": ("acked", "edge"), "l": ("local", "local"), "x": ("lost", "")}
    return [{"seq": str(i), "capture_stamp": str(100 + i * period), "status": code[c][0],
             "pose_source": code[c][1], "rtt": "0.05", "edge": "edge1" if c == "a" else ""}
            for i, c in enumerate(statuses)]


def test_pose_gaps_count_consecutive_scans_without_a_pose() -> None:
    assert fr.pose_gaps(_rows("aaaa"), 0.1) == (0, 0.0)
    n, s = fr.pose_gaps(_rows("aaxxxlaxa"), 0.1)
    assert n == 3 and s == pytest.approx(0.4)  # from the pose before (0.1 s) to the one after (0.5 s)
    assert fr.pose_gaps(_rows("aaxx"), 0.1) == (2, pytest.approx(0.3))  # the run's end closes it
    assert fr.pose_gaps(_rows("xxxaaxxaaxx"), 0.1)[0] == 2  # before the first pose: start-up, not a gap
    assert fr.pose_gaps([], 0.1) == (0, 0.0)


def test_on_time_share_after_warmup() -> None:
    rows = _rows("aaaaxaaaaa")
    rows[1]["rtt"] = "0.3"
    assert fr.on_time_share(rows, 0.1) == (pytest.approx(0.8), 1)
    assert fr.on_time_share(rows, 0.1, warmup=2) == (pytest.approx(7 / 8), 1)
    assert fr.on_time_share([], 0.1) == (None, 0)


def test_robot_figures_without_the_fleet_section_come_from_the_rows() -> None:
    metrics = {"balance": {"produced": 9, "acked": 5, "lost": 3, "late": 1}, "balanced": True,
               "dropped_source": {"window": 0}, "cpu": {"process_ms_per_scan": 2.5}}
    rows = _rows("aaxxxaxaa")
    fig = fr.robot_figures(metrics, rows, 0.1, {"ate_rmse": 0.1})
    assert fig["produced"] == 9 and fig["lost"] == 4 and fig["balanced"]
    assert fig["max_pose_gap_scans"] == 3 and fig["per_edge"] == {"edge1": 5}
    assert fig["failover_s"] == [] and fig["cpu_ms_per_scan"] == 2.5
    assert fr.robot_figures({}, [], 0.1)["produced"] == 0  # a robot that wrote nothing


def test_robot_figures_prefer_the_robots_fleet_section() -> None:
    metrics = {"balance": {"produced": 9, "acked": 6, "local": 3}, "balanced": True,
               "fleet": {"attaches": 2, "failovers": 1, "failover_s": [0.8, "nan"], "local_scans": 3,
                         "local_cpu_ms_per_scan": {"median": 12.0, "mean": 14.0}, "max_pose_gap_scans": 1,
                         "max_pose_gap_s": 0.1, "switch_jumps_m": [0.02, 0.04],
                         "per_edge": {"edge1": 3, "edge2": 3}}}
    fig = fr.robot_figures(metrics, _rows("aaalllaaa"), 0.1)
    assert fig["local"] == 3 and fig["failover_s"] == [0.8] and fig["local_cpu_ms_per_scan"] == 12.0
    assert fig["max_pose_gap_scans"] == 1 and fig["per_edge"] == {"edge1": 3, "edge2": 3}
    s = fr.run_summary({"robot1": fig, "robot2": fig}, {"edge1": {"cores": 0.5}, "edge1.2": {"cores": 0.3},
                                                         "robot1": {"cores": 0.2}, "router": {"cores": 0.1}})
    assert s["local"] == 6 and s["failovers"] == 2 and s["failover_s_max"] == 0.8
    assert s["switch_jump_m_max"] == 0.04 and s["edge_cores"] == pytest.approx(0.4)
    assert s["balanced_all"] is True and s["robot_cores"] == 0.2


def test_aggregate_mean_sd_and_the_ate_ratio() -> None:
    runs: list[dict[str, object]] = [{"ate_rmse_mean": 0.10, "balanced_all": True, "failover_s_max": None},
                                     {"ate_rmse_mean": 0.14, "balanced_all": False, "failover_s_max": 1.0}]
    agg = fr.aggregate(runs)
    assert agg["ate_rmse_mean"]["mean"] == pytest.approx(0.12) and agg["ate_rmse_mean"]["n"] == 2
    assert agg["ate_rmse_mean"]["sd"] == pytest.approx(0.0283, abs=1e-4)
    assert agg["balanced_all"]["mean"] == 0.5
    assert agg["failover_s_max"] == {"mean": 1.0, "sd": None, "n": 1}
    base = fr.aggregate([{"ate_rmse_mean": 0.1}])
    assert fr.ate_ratio(agg, base) == pytest.approx(1.2)
    assert fr.ate_ratio(agg, {}) is None


def test_markdown_report_has_the_figures_and_the_verdict() -> None:
    agg = fr.aggregate([{"ate_rmse_mean": 0.11, "acked": 100}, {"ate_rmse_mean": 0.13, "acked": 110}])
    base = fr.aggregate([{"ate_rmse_mean": 0.1}])
    per_robot = {"robot1": fr.aggregate([fr.robot_scalars(fr.robot_figures({}, _rows("aaxa"), 0.1))])}
    text = fr.markdown("Fleet", "setup line", agg, base, per_robot, fr.ate_ratio(agg, base), 5)
    assert "| ATE RMSE, mean over robots (m) | 0.120 ± 0.014 | 0.100 |" in text
    assert "**1.20×** (target ≤ 1.2× with 5 kills: met)" in text
    assert "| robot1 | 4 |" in text
    assert "is for 5" in fr.markdown("Fleet", "", agg, base, per_robot, 1.5, 1)


def test_a_resumed_series_keeps_runs_made_under_the_same_variables_only(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A complete run is kept when the ZOFFLOAD_* variables are what they were (normalised: 0 is
    false), run again (its old results removed first) when they differ; a variable naming no
    setting fails before any run."""
    import json

    import zoffload.lab.fleet_experiment as fe
    from zoffload.runtime.errors import ConfigError

    ran: list[str] = []

    def once(exp: object, run: Path, *args: object) -> dict[str, object]:
        ran.append(run.name)
        assert not (run / "results.json").exists()
        return {"summary": {}, "environment": fe.environment_settings()}

    monkeypatch.setattr(fe, "_run_once", once)
    monkeypatch.setattr(fe, "summary_line", lambda summary: "")
    monkeypatch.setenv("ZOFFLOAD_ROBOT__PERCEPTION__OVERFLOW", "false")
    for i, env in ((1, {"robot": {"perception": {"overflow": False}}}), (2, {})):
        (tmp_path / f"run{i}").mkdir()
        (tmp_path / f"run{i}" / "results.json").write_text(json.dumps({"summary": {}, "environment": env}))
    monkeypatch.setenv("ZOFFLOAD_ROBOT__PERCEPTION__OVERFLOW", "0")
    runs = fe._series(fe.FleetExperiment(out=str(tmp_path), repeat=2), tmp_path, [], {}, {}, {})
    assert ran == ["run2"] and len(runs) == 2
    monkeypatch.setenv("ZOFFLOAD_ROBOT__PERCEPTION__OVERFLOWS", "false")
    with pytest.raises(ConfigError, match="overflows"):
        fe.run_fleet_experiment(fe.FleetExperiment(out=str(tmp_path / "x")))
