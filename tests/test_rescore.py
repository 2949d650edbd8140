"""sitl.rescore: re-validating a run's snapshots and letting that choose the exported networks."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from sitl.learn.rescore import selection_score
from sitl.learn.trainer import select_snapshot

REPO = Path(__file__).resolve().parent.parent


def _env():
    return {**os.environ, "PYTHONPATH": str(REPO)}


def _run(tmp_path, *args):
    return subprocess.run([sys.executable, *args], capture_output=True, text=True, env=_env(), cwd=tmp_path,
                          timeout=300)


def test_score_weighs_each_kind_of_scene_equally():
    results = {"random-medium": {"success_rate": 0.9}, "circle-n8": {"success_rate": 1.0},
               "circle-n12": {"success_rate": 0.8}, "circle-n14": {"success_rate": 0.6}}
    assert selection_score(results) == pytest.approx(0.5 * 0.9 + 0.5 * 0.8)
    assert selection_score({"circle-n8": {"success_rate": 0.7}}) == pytest.approx(0.7)
    # an obstacle scene is a third kind, not one more random scene
    assert selection_score({**results, "obstacles": {"success_rate": 0.6}}) == pytest.approx((0.9 + 0.8 + 0.6) / 3)


def test_rescored_rows_compete_only_among_themselves():
    rows = [{"updates": 5, "score": 0.9}, {"updates": 10, "score": 0.5, "rescored": {"score": 0.6}},
            {"updates": 15, "score": 0.4, "rescored": {"score": 0.7}}]
    assert select_snapshot(rows)["updates"] == 15
    assert select_snapshot([{k: v for k, v in r.items() if k != "rescored"} for r in rows])["updates"] == 5


def test_rescore_writes_every_snapshot_and_resume_exports_its_choice(tmp_path):
    run_dir = tmp_path / "run"
    done = _run(tmp_path, "-m", "sitl.train", "--run-dir", str(run_dir), "--num-uavs", "2", "--num-worlds", "2",
                "--image-size", "16", "--hidden-dim", "32", "--batch-size", "16", "--init-steps", "20",
                "--max-episode-steps", "40", "--scenario", "mixed", "--total-updates", "12",
                "--eval-every-updates", "4", "--eval-episodes", "2", "--select-best", "--final-eval-episodes", "2")
    assert done.returncode == 0, done.stderr

    done = _run(tmp_path, "-m", "sitl.rescore", str(run_dir), "--episodes", "3", "--random-uavs", "3",
                "--circle-uavs", "3,4", "--densities", "small,large", "--threads", "1")
    assert done.returncode == 0, done.stderr
    rows = json.loads((run_dir / "snapshots" / "validation.json").read_text())
    assert [r["updates"] for r in rows] == [4, 8, 12]
    for row in rows:
        scenes = row["rescored"]["scenes"]
        assert list(scenes) == ["random-small", "random-large", "circle-n3", "circle-n4"]
        assert row["rescored"]["episodes"] == 3
        assert row["rescored"]["score"] == pytest.approx(selection_score(scenes))
        for result in scenes.values():
            assert 0.0 <= result["success_rate"] <= 1.0 and 0.0 <= result["spl"] <= result["success_rate"] + 1e-9
    assert "best:" in done.stdout

    # The rescored score, not the training-time one, decides what `--resume` exports: make the
    # training-time loser the rescored winner.
    loser = min(rows, key=lambda r: (r["score"], -r["updates"]))
    for row in rows:
        row["rescored"]["score"] = 1.0 if row is loser else 0.0
    (run_dir / "snapshots" / "validation.json").write_text(json.dumps(rows))
    done = _run(tmp_path, "-m", "sitl.train", "--resume", str(run_dir))
    assert done.returncode == 0, done.stderr
    assert f"selected the snapshot at {loser['updates']} updates (rescored 1.000)" in done.stderr
    assert json.loads((run_dir / "final_eval.json").read_text())["selected_snapshot"]["updates"] == loser["updates"]

    # A corrupt snapshot is skipped with the reason; the others keep their rescoring.
    (run_dir / "snapshots" / "agent_8.pt").write_bytes(b"not a snapshot")
    done = _run(tmp_path, "-m", "sitl.rescore", str(run_dir), "--episodes", "1", "--random-uavs", "3",
                "--circle-uavs", "", "--updates", "8", "--threads", "1")
    assert done.returncode == 0, done.stderr
    assert "skipped" in done.stdout and "not a snapshot of this run's networks" in done.stdout
    assert json.loads((run_dir / "snapshots" / "validation.json").read_text()) == rows


@pytest.mark.parametrize("args, message", [
    (["--circle-uavs", "1"], "expected integers of at least 2"),
    (["--densities", "huge"], "densities are small, medium or large"),
    (["--episodes", "0"], "--episodes must be at least 1"),
])
def test_bad_arguments_are_refused(tmp_path, args, message):
    done = _run(tmp_path, "-m", "sitl.rescore", str(tmp_path), *args)
    assert done.returncode == 2 and message in done.stderr


def test_a_directory_without_snapshots_is_refused(tmp_path):
    done = _run(tmp_path, "-m", "sitl.rescore", str(tmp_path))
    assert done.returncode == 2 and "not a training run directory" in done.stderr
    (tmp_path / "config.json").write_text("{}")
    done = _run(tmp_path, "-m", "sitl.rescore", str(tmp_path))
    assert done.returncode == 2 and "has no validated snapshots" in done.stderr
