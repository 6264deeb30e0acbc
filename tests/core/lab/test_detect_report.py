"""The detection report: repeated runs make one row (mean ± sd), ours against the best fixed one."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest

from zoffload.lab.eval.detect_report import aggregate, run_settings, table, targets, write_detect_report


def _run(folder: Path, strategy: str, ap: float, trace: str = "detect-capped", quota: float = 0.25,
         old: bool = False) -> Path:
    """A run's results; ``old``: as written before runs named their settings (edge_apart ...)."""
    folder.mkdir(parents=True)
    (folder / "results.json").write_text(json.dumps({**({} if old else {"edge_apart": True}),
        "kind": "detect", "strategy": strategy, "trace": trace, "cpu_quota": quota, "encoding": "bgr8",
        "images": "coco-clips@holdout", "max_frames": None, "ap50_async": ap, "ap50_sync": 80.0,
        "processed_pct": 70.0, "offloaded_pct": 60.0, "skipped_pct": 5.0, "robot_rtt_ms": 50.0,
        "edge_rtt_ms": 120.0, "cpu_process_pct": 25.0, "mbps_out": 150.0, "power_w": None,
        "power_available": False, "balanced": True, "robot_exit_code": 0, "cut_short": False}))
    return folder


def test_repeated_runs_are_one_row_with_mean_and_sd(tmp_path: Path) -> None:
    folders = [_run(tmp_path / "q0.25" / "detect-capped" / s.replace(":", "_") / f"run{i}", s, ap)
               for s, aps in (("dispatch", (55.0, 57.0, 59.0)), ("ratio:0.9", (50.0, 52.0, 54.0)),
                              ("edge", (45.0, 46.0, 47.0)))
               for i, ap in enumerate(aps, 1)]
    folders.append(_run(tmp_path / "q1" / "detect-capped" / "edge" / "run1", "edge", 40.0, quota=1.0))
    runs = [dict(json.loads((f / "results.json").read_text()), folder=f) for f in folders]
    rows = {(r["strategy"], r["cpu_quota"]): r for r in aggregate(runs)}
    assert len(rows) == 4
    ours = rows[("dispatch", 0.25)]
    assert ours["n"] == 3 and ours["ap50_async"] == pytest.approx(57.0)
    assert ours["sd"]["ap50_async"] == pytest.approx(2.0)
    assert rows[("edge", 1.0)]["n"] == 1 and "ap50_async" not in rows[("edge", 1.0)]["sd"]
    summary = targets(list(rows.values()))
    assert "57.0 ± 2.0" in summary and "ratio 0.9: 52.0 ± 2.0" in summary and "| +5.0 |" in summary
    path = write_detect_report(folders, tmp_path)
    text = path.read_text()
    assert "robot 0.25 core" in text and "robot 1 core" in text
    assert "| **Dispatch (ours)** | 3 | 57.0 ± 2.0 |" in text
    assert "every frame in exactly one bucket in all of them" in text
    assert (tmp_path / "ap_vs_ratio_0.25core.png").exists()
    # a frame left pending at the end is in no final bucket, whatever the ledger's own check says
    left = tmp_path / "q1" / "detect-capped" / "edge" / "run1" / "results.json"
    left.write_text(json.dumps(dict(json.loads(left.read_text()), balance={"frames_in": 10, "pending": 1})))
    assert "all but " in write_detect_report(folders, tmp_path).read_text()


def test_jpeg_variants_are_rows_of_their_own_and_ours_meets_its_own_kind(tmp_path: Path) -> None:
    """``S@jpeg`` strategies (the sweep's JPEG variants) make their own rows; ours with JPEG frames
    is set against the fixed strategies with JPEG frames, ours on raw frames against the raw ones."""
    cells = (("dispatch", 47.0), ("ratio:0.7", 48.0), ("edge", 33.0), ("dispatch@jpeg", 55.0),
             ("ratio:0.7@jpeg", 53.0), ("edge@jpeg", 50.0))
    folders = [_run(tmp_path / s.replace(":", "_").replace("@", "_") / "run1", s, ap) for s, ap in cells]
    text = write_detect_report(folders, tmp_path).read_text()
    assert "| Ratio 0.7 + JPEG | 1 | 53.0 |" in text and "| Dispatch (ours) + JPEG | 1 | 55.0 |" in text
    order = [text.index(row) for row in ("| Ratio 0.7 | 1 |", "| Ratio 0.7 + JPEG | 1 |", "| Edge only |")]
    assert order == sorted(order)
    summary = targets(aggregate([json.loads((f / "results.json").read_text()) for f in folders]))
    assert "| 47.0 | ratio 0.7: 48.0 | 33.0 | -1.0 | +14.0 |" in summary  # raw against raw
    assert ("(JPEG frames, against the JPEG ones) | 0.25 core | 55.0 | ratio 0.7 + JPEG: 53.0 | 50.0 "
            "| +2.0 | +5.0 |") in summary


def test_ours_choosing_the_encoding_per_frame_meets_the_best_fixed_of_either_encoding(tmp_path: Path) -> None:
    """``dispatch@auto`` (the default encoding) is set against every fixed strategy, raw or JPEG,
    and its edge-only column is the better of raw and JPEG edge-only."""
    cells = (("ratio:0.7", 48.0), ("edge", 33.0), ("ratio:0.9@jpeg", 59.0), ("edge@jpeg", 50.0),
             ("dispatch@auto", 58.0))
    folders = [_run(tmp_path / s.replace(":", "_").replace("@", "_") / "run1", s, ap) for s, ap in cells]
    text = write_detect_report(folders, tmp_path).read_text()
    assert "| **Dispatch (ours)** + encoding per frame | 1 | 58.0 |" in text
    summary = targets(aggregate([json.loads((f / "results.json").read_text()) for f in folders]))
    assert ("(encoding per frame, against raw and JPEG ones) | 0.25 core | 58.0 | ratio 0.9 + JPEG: 59.0 "
            "| 50.0 | -1.0 | +8.0 |") in summary


def test_runs_with_another_edge_model_or_threads_are_another_row(tmp_path: Path) -> None:
    """The models, the edge's threads and further settings are part of what a run measured:
    runs that differ in them are not averaged into one row, and the tables name them; runs older
    than the fields ran the defaults."""
    runs = []
    for i, (model, threads) in enumerate([("picodet-s", 1), ("picodet-s", 1), ("picodet-s", 2),
                                          ("yolox-nano", 1)]):
        f = _run(tmp_path / f"run{i}", "edge", 50.0 + i)
        row = dict(json.loads((f / "results.json").read_text()), edge_model=model, edge_threads=threads,
                   local_model="nanodet-m", extra="{}")
        runs.append(row)
    runs.append(json.loads((_run(tmp_path / "old", "edge", 42.0, old=True) / "results.json").read_text()))
    runs.append(json.loads((_run(tmp_path / "new", "edge", 43.0) / "results.json").read_text()))
    rows = aggregate(runs)
    assert sorted(r["n"] for r in rows) == [1, 1, 1, 3]
    assert [r["ap50_async"] for r in rows if r["n"] == 3] == [pytest.approx((50 + 51 + 43) / 3)]
    text = table(rows, "detect-capped", "0.25 core")
    assert "| Edge only (edge_threads 2) | 1 |" in text
    assert "| Edge only (edge_model yolox-nano) | 1 |" in text
    # an older run: the defaults but for the edge on its own core, which it was not
    assert "| Edge only (edge_apart False) | 1 | 42.0 |" in text
    ours = dict(runs[0], strategy="dispatch", ap50_async=60.0, edge_model="yolox-nano")
    summary = targets(aggregate([*runs, ours]))
    assert "(edge_model yolox-nano)" in summary and "| +7.0 |" in summary  # against its own model's edge (53)


def test_a_resumed_sweep_runs_again_a_folder_made_with_another_link_seed(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Repeat i runs with link seed + i - 1; a complete folder of an older sweep (seed 0 in every
    repeat) is run again, one with the planned seed is reused."""
    import zoffload.lab.detect_experiment as de

    ran: list[int] = []
    monkeypatch.setattr(de, "run_detect_experiment", lambda exp: ran.append(exp.seed) or {"strategy": "edge"})
    monkeypatch.setattr(de, "summary_line", lambda row: "")
    plan = de.sweep_runs(tmp_path, ["detect-capped"], ["edge"], [0.25], 2)
    assert [e.seed for e in plan] == [0, 1]
    for exp in plan:
        _run(Path(exp.out), "edge", 50.0)  # complete, made by an older sweep: no seed (0)
    assert de.run_or_reuse(dataclasses.replace(plan[0], edge_apart=False)) == {"strategy": "edge"}
    assert ran == [0]  # made with the edge apart: run again for a plan without
    ran.clear()
    assert de.run_or_reuse(plan[0])["ap50_async"] == 50.0 and ran == []
    de.run_or_reuse(plan[1])
    assert ran == [1]
    other = dataclasses.replace(plan[0], edge_model="yolox-nano")  # the same folder, another model
    de.run_or_reuse(other)
    assert ran == [1, 0]


def test_settings_from_the_environment_are_recorded_and_make_runs_of_their_own(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A ``ZOFFLOAD_ROBOT__*`` variable reaches the robot over the settings the run writes: the run's
    row records it, the report keeps such runs apart and names the setting, and a resumed sweep
    reuses a folder only under the same variables; a variable naming no setting fails up front."""
    import zoffload.lab.detect_experiment as de
    from zoffload.runtime.errors import ConfigError

    monkeypatch.delenv("ZOFFLOAD_ROBOT__PERCEPTION__OVERFLOW", raising=False)
    plain = de._settings(de.DetectExperiment(trace="none", strategy="dispatch", out=str(tmp_path)))
    assert plain["environment"] == {}
    monkeypatch.setenv("ZOFFLOAD_ROBOT__PERCEPTION__OVERFLOW", "false")
    off = de._settings(de.DetectExperiment(trace="none", strategy="dispatch", out=str(tmp_path)))
    assert off["environment"] == {"robot": {"perception": {"overflow": False}}}  # an object, as a scan run's
    monkeypatch.setenv("ZOFFLOAD_ROBOT__PERCEPTION__OVERFLOW", "0")  # the same setting, said otherwise
    assert de._settings(de.DetectExperiment(trace="none", strategy="dispatch", out=str(tmp_path))) == off
    runs = [dict(json.loads((_run(tmp_path / f"r{i}", "dispatch", 50.0 + i) / "results.json").read_text()),
                 **settings) for i, settings in enumerate((plain, plain, off))]
    rows = aggregate(runs)
    assert sorted(r["n"] for r in rows) == [1, 2]
    # a run of 2026-12-07 stored them as JSON text: the same run
    older = dict(runs[2], environment=json.dumps(off["environment"]), extra="{}")
    assert run_settings(older) == run_settings(runs[2]) and len(aggregate([runs[2], older])) == 1
    text = table(rows, "detect-capped", "0.25 core")
    assert '(environment {"robot": {"perception": {"overflow": false}}})' in text
    ran: list[str] = []
    monkeypatch.setattr(de, "run_detect_experiment", lambda exp: ran.append(exp.out) or {"strategy": "x"})
    monkeypatch.setattr(de, "summary_line", lambda row: "")
    folder = tmp_path / "made_plain" / "run1"
    (folder.parent).mkdir()
    _run(folder, "dispatch", 50.0)
    (folder / "results.json").write_text(json.dumps(dict(json.loads((folder / "results.json").read_text()),
                                                         seed=0, **plain)))
    exp = de.DetectExperiment(trace="detect-capped", strategy="dispatch", out=str(folder))
    de.run_or_reuse(exp)
    assert ran == [str(folder)]  # made without the variable: run again with it
    monkeypatch.delenv("ZOFFLOAD_ROBOT__PERCEPTION__OVERFLOW")
    assert de.run_or_reuse(exp)["ap50_async"] == 50.0 and ran == [str(folder)]
    monkeypatch.setenv("ZOFFLOAD_ROBOT__PERCEPTION__OVERFLOWS", "false")
    with pytest.raises(ConfigError, match="did you mean 'overflow'"):
        de.run_or_reuse(exp)
