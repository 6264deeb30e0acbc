"""The detection sweep's plan: the grid, its folders, repeats, resuming and stopping."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from zoffload.lab import detect_experiment as de
from zoffload.lab.detect_experiment import SWEEP_QUOTAS, SWEEP_STRATEGIES, SWEEP_TRACES, run_sweep, sweep_runs


def test_the_default_grid_is_every_strategy_link_and_quota_three_times(tmp_path: Path) -> None:
    plan = sweep_runs(tmp_path, SWEEP_TRACES, SWEEP_STRATEGIES, SWEEP_QUOTAS, 3, images="coco-clips@holdout",
                      max_frames=None, encoding="bgr8", seed=0)
    assert len(plan) == 14 * 4 * 2 * 3
    assert "dispatch" in SWEEP_STRATEGIES and "mmwave-blockage" in SWEEP_TRACES
    assert len({p.out for p in plan}) == len(plan)
    first = plan[0]
    assert Path(first.out) == tmp_path / "q0.25" / "none" / "robot" / "run1" and first.cpu_quota == 0.25
    # repeat-major: the whole grid once before any second run
    assert all(p.out.endswith("run1") for p in plan[:len(plan) // 3])
    assert {p.images for p in plan} == {"coco-clips@holdout"} and {p.max_frames for p in plan} == {None}
    # each repeat its own link seed: the spread of a cell is the link's jitter too, not the host's alone
    assert {p.seed for p in plan if p.out.endswith("run2")} == {1} and first.seed == 0
    jpeg = sweep_runs(tmp_path, ["detect-capped"], ["dispatch@jpeg"], [1.0], 1, encoding="bgr8")[0]
    assert jpeg.encoding == "jpeg" and jpeg.strategy == "dispatch" and jpeg.out.endswith("dispatch_jpeg/run1")


def _done(folder: Path, **extra: Any) -> None:
    folder.mkdir(parents=True)
    (folder / "results.json").write_text(json.dumps({"kind": "detect", "robot_exit_code": 0,
                                                     "cut_short": False, "edge_apart": True, **extra}))


def test_complete_runs_are_kept_and_an_interrupted_run_ends_the_sweep(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    ran: list[str] = []

    def fake(exp: de.DetectExperiment) -> dict[str, Any]:
        ran.append(exp.out)
        return {"strategy": exp.strategy, "trace": exp.trace, "cut_short": len(ran) == 3}

    monkeypatch.setattr(de, "run_detect_experiment", fake)
    _done(tmp_path / "q0.25" / "none" / "edge" / "run1")  # complete: kept
    _done(tmp_path / "q0.25" / "none" / "robot" / "run1", cut_short=True)  # interrupted: run again
    rows = run_sweep(tmp_path, ["none"], ["robot", "edge", "dispatch"], [0.25, 1.0], 2)
    assert [Path(o).relative_to(tmp_path).as_posix() for o in ran] == [
        "q0.25/none/robot/run1", "q0.25/none/dispatch/run1", "q1/none/robot/run1"]
    assert len(rows) == 4 and rows[-1]["cut_short"]  # the third run was interrupted: the sweep stops


def test_a_run_whose_edge_never_starts_is_reported_and_the_sweep_goes_on(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A fake for a fault this test cannot cause on demand: every start of one run failing (its
    edge's port taken each time, after the runner's own restarts on other ports)."""
    from zoffload.lab.runner import StartError

    ran: list[str] = []

    def fake(exp: de.DetectExperiment) -> dict[str, Any]:
        if exp.strategy == "edge":
            raise StartError("the edge did not start:\nAddress already in use")
        ran.append(exp.strategy)
        return {"strategy": exp.strategy, "trace": exp.trace}

    monkeypatch.setattr(de, "run_detect_experiment", fake)
    rows = run_sweep(tmp_path, ["none"], ["robot", "edge", "dispatch"], [0.25], 1)
    assert ran == ["robot", "dispatch"]
    assert [r.get("error") for r in rows] == [None, "start failed: the edge did not start:", None]
    assert rows[1]["out"].endswith("edge/run1") and rows[1]["start_failed"]


def test_a_single_experiment_repeats_into_run_folders(tmp_path: Path,
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    seen: list[str] = []
    real = de.run_detect_experiment

    def fake(exp: de.DetectExperiment) -> dict[str, Any]:
        if exp.repeat > 1:
            return real(exp)
        seen.append(exp.out)
        return {"strategy": exp.strategy, "trace": exp.trace}

    monkeypatch.setattr(de, "run_detect_experiment", fake)
    de.run_detect_experiment(de.DetectExperiment(trace="none", strategy="dispatch", out=str(tmp_path),
                                                 repeat=3))
    assert seen == [str(tmp_path / f"run{i}") for i in (1, 2, 3)]
