from __future__ import annotations

from pathlib import Path

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
    # against the local run of the same scans only: a local run of another length is not compared
    other = dict(row("local", 150_000, 60), scans_produced=60)
    assert "-60 %" in table_markdown([other, row("local", 200_000, 100), row("raw", 80_000)]).splitlines()[4]
    assert "| raw | wifi-locations |" in table_markdown([other, row("raw", 80_000)]).splitlines()[3]
    assert table_markdown([other, row("raw", 80_000)]).splitlines()[3].split("|")[9].strip() == ""
    # a run whose final map query went unanswered has no map: no ratio, and no crash; cut short: said
    lost = dict(row("raw", None), trajectory_error=None, cut_short=True)  # type: ignore[arg-type]
    line = table_markdown([row("local", 200_000, 100), lost]).splitlines()[3]
    assert line.startswith("| raw (1 cut short) |")
    assert [c.strip() for c in line.split("|")[8:10]] == ["–", ""]
    # a run made with settings from ZOFFLOAD_* variables says so in its name
    env = dict(row("rate", 80_000), environment={"robot": {"coding": "f32"}})
    named = '| rate (environment {"robot": {"coding": "f32"}}) |'
    assert table_markdown([env]).splitlines()[2].startswith(named)


def test_the_scans_the_edge_registered_stand_beside_those_it_received() -> None:
    """Received counts the scans that reached the edge; the ones it dropped late or overloaded are
    among them, so the registered ones are shown beside (older results without the figure: not)."""
    md = table_markdown([row("local", 200_000, 100), dict(row("rate", 80_000), scans_registered=61),
                         row("raw", 80_000)])
    lines = md.splitlines()
    assert "received (registered)" in lines[0]
    assert "| 90 (61) / 100 (95) |" in lines[3] and "| 90 / 100 (95) |" in lines[4]
    assert "| 100 / 100 (95) |" in lines[2]  # local: no edge


def test_runs_of_one_experiment_make_one_row_with_mean_and_sd(tmp_path: Path) -> None:
    from zoffload.lab.eval.report import aggregate, expand_runs

    runs = []
    for i, (received, ate, cpu) in enumerate(((90, 0.25, 1.0), (94, 0.35, 3.0)), start=1):
        folder = tmp_path / "rate" / f"run{i}"
        folder.mkdir(parents=True)
        (folder / "results.json").write_text("{}")
        r = row("rate", 100_000, received)
        r.update(folder=folder, trajectory_error={"ate_rmse": ate}, robot_cpu_ms=cpu, on_time_slot=0.9,
                 skipped_share=0.1)
        runs.append(r)
    assert expand_runs([tmp_path / "rate"]) == [tmp_path / "rate" / "run1", tmp_path / "rate" / "run2"]
    single = dict(row("local", 200_000, 100), folder=tmp_path / "local")
    rows = aggregate([single, *runs])
    assert [r["n"] for r in rows] == [1, 2]
    agg = rows[1]
    assert agg["scans_received"] == 92 and agg["sd"]["scans_received"] == pytest.approx(2.828, abs=1e-3)
    md = table_markdown(rows)
    line = md.splitlines()[3]
    assert "rate (2 runs)" in line and "92 ± 3 / 100" in line and "0.300 ± 0.071" in line
    assert "2.00 ± 1.41" in line and "10 ± 0 %" in line and "90 ± 0 %" in line and "-50 %" in line
    assert "| 80 ± 0 % |" in line  # T <= 0.11 s
    assert "runs)" not in line.replace("rate (2 runs)", "")
    # 1-byte scans on the runs' emulated link, beside their on-time share
    assert "(1-byte" not in line
    runs[0]["on_time_tiny"], runs[1]["on_time_tiny"] = 0.8, 0.7
    assert "| 90 ± 0 % (1-byte 75 ± 7 %) |" in table_markdown(aggregate(runs)).splitlines()[2]
    # a figure only some runs know (an edge summary unreadable): their mean, and how many they are
    runs[0]["delivered_skipped_or_backfilled"] = 0.97
    runs[1]["delivered_skipped_or_backfilled"] = None
    line = table_markdown(aggregate(runs)).splitlines()[2]
    assert "| 97 % (1 of 2 runs) |" in line, line


def test_scans_an_outage_kept_local_are_counted_beside_the_delivered_and_skipped(tmp_path: Path) -> None:
    """A run from before the figure gets it from its records: scans booked ``local`` with the
    robot's own pose are bridged, not lost; a local one without a pose, or a lost one, is not."""
    import csv
    import json

    from zoffload.lab.eval.report import load_run

    folder = tmp_path / "run1"
    folder.mkdir()
    (folder / "results.json").write_text(json.dumps({"delivered_or_skipped": 0.5, "scans_produced": 10}))
    statuses = [("acked", "edge")] * 4 + [("source:stall", "")] + [("local", "local")] * 3 + [
        ("local", ""), ("lost", "local")]
    with open(folder / "scans.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["seq", "status", "pose_source"])
        w.writeheader()
        w.writerows({"seq": i, "status": s, "pose_source": p} for i, (s, p) in enumerate(statuses))
    run = load_run(folder)
    assert run["scans_kept_local"] == 3 and run["delivered_skipped_or_local"] == pytest.approx(0.8)
    r = dict(row("rate", 100_000), delivered_or_skipped=0.5, delivered_skipped_or_local=0.8)
    line = table_markdown([r]).splitlines()[2]
    assert line.endswith("| 50 % | 80 % | – |  |"), line  # no trajectories: nothing against local
    r["delivered_skipped_or_backfilled"] = 0.7
    assert table_markdown([r]).splitlines()[2].endswith("| 50 % | 80 % | 70 % |  |")


def test_scans_an_edge_took_in_a_backfill_are_counted_once() -> None:
    """A backfilled scan reached the edge later (the attach after its outage): counted beside the
    delivered and skipped, once, also when it was booked skipped (a stall) or received as well."""
    from zoffload.lab.scan_experiment import _slot_figures

    recs = [{"seq": str(i), "status": s, "pose_source": p, "backfill": b, "interarrival": "0.1"}
            for i, (s, p, b) in enumerate([("acked", "edge", "")] * 4 + [("source:stall", "local", "1"),
                                           ("local", "local", "1"), ("local", "local", "1"),
                                           ("lost", "local", "1"), ("local", "local", ""),
                                           ("acked", "edge", "1")])]
    received = [r for r in recs if r["status"] == "acked"]
    fig = _slot_figures(recs, received, 0.1, 10)
    assert fig["delivered_or_skipped"] == pytest.approx(0.6)  # 5 received, 1 skipped
    assert fig["scans_skipped"] == fig["scans_stalled"] == 1  # held back in an ack silence
    assert fig["delivered_skipped_or_local"] == pytest.approx(0.9)  # + the 3 kept local with a pose
    assert fig["delivered_skipped_or_backfilled"] == pytest.approx(0.9)  # + 2 local and the lost one
    # the marks say which scans an edge accepted in a backfill; what it registered, it says itself
    fig = _slot_figures(recs, received, 0.1, 10, registered={4, 5, 9})
    assert fig["delivered_skipped_or_backfilled"] == pytest.approx(0.7)  # + 5 only: 6 and 7 left unused
    assert _slot_figures(recs, received, 0.1, 10, registered=set())["delivered_skipped_or_backfilled"] == 0.6


def test_the_edges_word_on_its_backfill_is_read_from_its_counters(tmp_path: Path) -> None:
    """The experiment reads the registered backfill from the edge's ``<robot>_edge.json``: an
    edge that does not list them, the robot's marks count; no file or an unreadable one, unknown
    (said why; the run's "+ backfilled" left out, not counted as none)."""
    import json

    from zoffload.lab.scan_experiment import _backfilled

    path = tmp_path / "r1_edge.json"
    figures, registered = _backfilled(path)
    assert figures["scans_backfilled"] is None and "r1_edge.json" in figures["backfill_unknown"]
    assert registered is None
    path.write_text(json.dumps({"backfilled": 3, "backfilled_seqs": [7, 8, 9]}))
    assert _backfilled(path) == ({"scans_backfilled": 3}, {7, 8, 9})
    path.write_text(json.dumps({"backfilled": 3}))
    assert _backfilled(path) == ({"scans_backfilled": 3}, None)
    for bad in ("[1, 2", "[1, 2]"):
        path.write_text(bad)
        figures, registered = _backfilled(path)
        assert figures["scans_backfilled"] is None and figures["backfill_unknown"] and registered is None


def test_trajectory_against_local_is_taken_over_the_same_scans(tmp_path: Path) -> None:
    """Local registers every scan; an offloaded run only those its edge did. Here local drifts
    10 % of the distance and the offloaded run 20 %, but only over the first half of the drive,
    where local's error is still small: over all scans the offloaded run looks 8 % better than
    local, over the same scans it is twice local's error (+100 %)."""
    import numpy as np

    from zoffload.lab.eval.report import aggregate, same_scans_vs_local

    def poses(xs: np.ndarray) -> np.ndarray:
        out = np.tile(np.eye(4), (len(xs), 1, 1))
        out[:, 0, 3] = xs
        return out

    seqs = np.arange(10)
    local_dir, run_dir = tmp_path / "local", tmp_path / "rate" / "run1"
    for d in (local_dir, run_dir):
        d.mkdir(parents=True)
    np.savez(local_dir / "trajectory.npz", seqs=seqs, poses=poses(1.1 * seqs))
    np.savez(run_dir / "trajectory.npz", seqs=seqs[:5], poses=poses(1.2 * seqs[:5]))
    np.savez(run_dir / "robot_poses.npz", gt_seqs=seqs, gt_poses=poses(seqs.astype(float)))
    sim = {"trajectory_reference": "simulator ground truth"}
    local = dict(row("local", 200_000, 100), folder=local_dir, **sim,
                 trajectory_error={"ate_rmse": float(np.sqrt(np.mean((0.1 * seqs) ** 2)))})
    rate = dict(row("rate", 100_000), folder=run_dir, **sim,
                trajectory_error={"ate_rmse": float(np.sqrt(np.mean((0.2 * seqs[:5]) ** 2)))})
    rows = aggregate([local, rate])
    same = same_scans_vs_local(rows[1], rows[0])
    assert same is not None and same[0] == pytest.approx(1.0) and same[1] is None
    assert rows[1]["trajectory_error"]["ate_rmse"] < rows[0]["trajectory_error"]["ate_rmse"]
    assert table_markdown(rows).splitlines()[3].endswith("| +100 % |")
    # no ground truth (KITTI-360's reference is KISS-ICP itself): no figure
    kitti = dict(rows[1], trajectory_reference="KISS-ICP run locally on every raw scan")
    assert same_scans_vs_local(kitti, rows[0]) is None


def test_a_late_refusal_is_booked_late_and_not_counted_as_received() -> None:
    """A late ack keeps what the edge said (``late_status``): the experiment counts a late scan as
    received by the edge unless the edge refused it."""
    import numpy as np

    from zoffload.lab.scan_experiment import ScanExperiment, _table_row
    from zoffload.protocol import wire
    from zoffload.robot.ledger import ScanLedger

    def ack(seq: int, stamp: float, status: str = "ok") -> wire.ScanAck:
        return wire.ScanAck(robot="r", seq=seq, send_stamp=stamp, status=status, interarrival=0.1,
                            queue_time=0.001, proc_time=0.02, icp_time=0.015, map_points=10, keypoints=5,
                            sigma=0.3, pose=np.eye(4))

    led = ScanLedger()
    for seq in range(3):
        led.produced()
        led.published(seq, 100.0 + seq, {"bytes": 100, "n_raw": 1000})
    assert led.expire(now=110.0, timeout=1.0) == 3
    assert led.on_ack(ack(0, 100.0), 110.1) == "late"
    assert led.on_ack(ack(1, 101.0, "refused"), 110.2) == "late"
    assert [led.records[s].get("late_status") for s in range(3)] == ["ok", "refused", None]
    assert led.balance()["late"] == 2 and led.balanced()
    recs = [dict(led.records[s], seq=str(s)) for s in range(3)]
    exp = ScanExperiment(trace="ethernet", policy="fixed:0.1")
    row = _table_row(exp, recs, None, None, "", led.balance())
    assert row["scans_received"] == 1 and row["scans_sent"] == 3


def test_a_run_with_the_edge_apart_is_its_own_row_and_needs_two_cores(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``--edge-apart`` (taskset: the edge on a core of its own) names its rows apart from the
    co-located ones, and a host with no two cores to split says so before anything starts."""
    from zoffload.lab import scan_experiment
    from zoffload.lab.scan_experiment import ScanExperiment, _table_row

    apart = ScanExperiment(trace="ethernet", policy="rate", coding="q16d", attach=True, edge_apart=True)
    assert _table_row(apart, [], None, None, "", None)["policy"] == "rate+q16d+attach+apart"
    assert _table_row(ScanExperiment(trace="ethernet", policy="local", edge_apart=True), [], None, None, "",
                      None)["policy"] == "local"
    monkeypatch.setattr(scan_experiment, "edge_apart_cores", lambda: {})
    started: list[object] = []
    monkeypatch.setattr(scan_experiment, "run_offload", lambda *a, **k: started.append(a))
    with pytest.raises(ConfigError, match="core of its own"):
        scan_experiment.run_scan_experiment(
            ScanExperiment(trace="ethernet", policy="fixed:0.1", edge_apart=True, out=str(tmp_path / "a")))
    assert started == []


def test_a_run_from_before_the_streams_gets_them_from_its_trace(tmp_path: Path) -> None:
    import json

    from zoffload.lab.eval.report import load_run
    from zoffload.lab.link.ceiling import stream_shares
    from zoffload.lab.link.trace import load_trace

    def run(name: str, trace: str) -> Path:
        folder = tmp_path / name
        folder.mkdir()
        (folder / "results.json").write_text(json.dumps(
            {"trace": trace, "S_kB": 40.0, "link_seed": 2, "on_time_slot": 0.7, "scans_produced": 100}))
        (folder / "experiment.json").write_text(json.dumps({"max_scans": 200, "rate_hz": None, "seed": 0}))
        (folder / "scans.csv").write_text("seq,status\n")
        return folder

    old = load_run(run("old", "/a/tree/that/is/gone/cellular-heldout.csv"))
    want = stream_shares(load_trace("cellular-heldout"), period=0.1, size=40_000, start=0.0, duration=20.0)
    assert (old["on_time_tiny"], old["on_time_steady_size"]) == pytest.approx(want)
    assert "(1-byte" in table_markdown([dict(row("rate", 100_000), **old)]).splitlines()[2]
    lost = load_run(run("lost", "/nowhere/no-such-trace.csv"))  # unknown: left out, no error
    assert "on_time_tiny" not in lost


def test_a_run_from_before_the_registered_figure_gets_it_from_its_scan_records(tmp_path: Path) -> None:
    """Registered: acked, or acked after the robot gave up waiting (late, the edge's answer ok);
    not dropped, nor late and dropped. A run written before the figure is counted from its records,
    so a row's mean is over all its runs."""
    import json

    from zoffload.lab.eval.report import load_run
    from zoffload.lab.scan_experiment import edge_registered

    recs = [{"status": "acked", "late_status": ""}, {"status": "late", "late_status": "ok"},
            {"status": "late", "late_status": "dropped"}, {"status": "edge_dropped", "late_status": ""},
            {"status": "acked", "late_status": ""}]
    assert edge_registered(recs) == 3
    (tmp_path / "results.json").write_text(json.dumps(row("rate", 100_000)))
    (tmp_path / "scans.csv").write_text("seq,status,late_status\n" + "".join(
        f"{i},{r['status']},{r['late_status']}\n" for i, r in enumerate(recs)))
    assert load_run(tmp_path)["scans_registered"] == 3
