"""Scale-out on Ray (``python -m sitl.sweep``, ``swarm_test paper --ray``) and the training's progress display.

The Ray tests share one local Ray of 2 CPUs for the whole module (starting one takes
10-20 s here) and shut it down at the end; they skip, saying why, where Ray is not
installed. The runs are tiny (16x16 depth, 2 UAVs, 15 updates), so the point is the
plumbing: every run's directory, the tables, the cells' files, identical numbers with and
without Ray.
"""

from __future__ import annotations

import io
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from companion.spec import DEFAULT_ACTION_SPEC, CameraSpec
from sitl.distributed import ray_available
from sitl.learn.progress import Progress, format_duration

REPO = Path(__file__).resolve().parents[1]

#: A training run of a few seconds (see tests/test_train.py), validated twice.
TINY_TRAIN = ["--num-uavs", "2", "--num-worlds", "2", "--image-size", "16", "--hidden-dim", "32", "--batch-size", "16",
              "--init-steps", "20", "--total-updates", "15", "--eval-every-updates", "10", "--eval-episodes", "2",
              "--final-eval-episodes", "2", "--max-episode-steps", "40", "--checkpoint-every-s", "1000"]

needs_ray = pytest.mark.skipif(not ray_available(), reason='Ray is not installed (pip install "swarmnav[ray]")')


def _env():
    return {**os.environ, "PYTHONPATH": str(REPO)}


@pytest.fixture(scope="module")
def local_ray():
    """One local Ray for the module: 2 CPUs, no dashboard; shut down after the last test."""
    from sitl.distributed import connect

    ray = connect("local", num_cpus=2)
    try:
        yield ray
    finally:
        ray.shutdown()


@pytest.fixture(scope="module")
def contract_policy(tmp_path_factory) -> Path:
    """A small untrained policy file (16x16 depth) for the evaluation cells."""
    from sitl.learn.agent import AgentConfig, SacAeAgent
    from sitl.learn.export import export_policy

    torch.manual_seed(0)
    agent = SacAeAgent(AgentConfig(hidden_dim=32), CameraSpec(width=16, height=16), DEFAULT_ACTION_SPEC)
    path = tmp_path_factory.mktemp("policy") / "policy.pt"
    export_policy(agent, path, 0.1, {"method": "sac_ae", "note": "untrained test policy"})
    return path


# --------------------------------------------------------------------------- Ray

@needs_ray
@pytest.mark.timeout(600)
def test_sweep_of_two_seeds_on_a_local_ray(local_ray, tmp_path, capsys):
    from sitl.learn.sweep import main

    out = tmp_path / "sweep"
    evals = ["--eval", "paper:random-medium,flown:obstacles", "--eval-episodes", "2"]
    code = main(["--seeds", "0,1", "--grid", "actor-lr=1e-3", "--out", str(out), *evals, "--", *TINY_TRAIN])
    printed = capsys.readouterr().out
    assert code == 0, printed
    for seed in (0, 1):
        run_dir = out / f"actor-lr=1e-3-s{seed}"
        config = json.loads((run_dir / "config.json").read_text())
        assert config["train"]["seed"] == seed and config["train"]["threads"] == 1  # one CPU, one thread
        assert config["agent"]["actor_lr"] == 1e-3 and config["train"]["run_dir"] == str(run_dir.resolve())
        final = json.loads((run_dir / "final_eval.json").read_text())
        assert final["updates"] == 15 and final["seed"] == seed
        assert (run_dir / "policy.pt").stat().st_size > 0 and (run_dir / "learning_curve.png").is_file()
        assert len(json.loads((run_dir / "learning_curve.json").read_text())["eval_success"]) == 1
    table = json.loads((out / "sweep.json").read_text())
    assert [r["seed"] for r in table["runs"]] == [0, 1] and all(r["result"] for r in table["runs"])
    finals = [r["result"]["final_success"]["random"] for r in table["runs"]]
    stats = table["groups"][0]["final_success"]["random"]
    assert stats["n"] == 2 and stats["mean"] == pytest.approx(sum(finals) / 2)
    assert stats["spread"] == pytest.approx(max(finals) - min(finals))
    assert "| actor-lr=1e-3-s1 | 1 |" in printed and "spread" in (out / "sweep.md").read_text()

    # Each run's policy was flown in both cells, as swarm_test flies them, into its own eval/ folder.
    for run in table["runs"]:
        cells = {c: json.loads((out / run["name"] / "eval" / "cells" / f"{c.replace(':', '-')}.json").read_text())
                 for c in ("paper:random-medium", "flown:obstacles")}
        assert {c: d["summary"]["success_rate"] for c, d in cells.items()} == run["result"]["eval_success"]
        assert cells["paper:random-medium"]["summary"]["episodes"] == 2
        assert cells["flown:obstacles"]["settings"]["scenario"]["name"] == "obstacles"
        assert cells["flown:obstacles"]["settings"]["camera_noise"] is True  # the flown protocol's noise
        assert cells["paper:random-medium"]["method"]["path"] == str(out / run["name"] / "policy.pt")
    rates = [r["result"]["eval_success"]["paper:random-medium"] for r in table["runs"]]
    assert table["groups"][0]["eval_success"]["paper:random-medium"]["spread"] == pytest.approx(max(rates) - min(rates))
    assert "paper:random-medium" in (out / "sweep.md").read_text()

    # Started again, the finished runs and their cells are reused, not trained or flown again.
    mtime = (out / "actor-lr=1e-3-s0" / "policy.pt").stat().st_mtime_ns
    cell_mtime = (out / "actor-lr=1e-3-s0" / "eval" / "cells" / "flown-obstacles.json").stat().st_mtime_ns
    assert main(["--seeds", "0,1", "--grid", "actor-lr=1e-3", "--out", str(out), *evals, "--", *TINY_TRAIN]) == 0
    assert (out / "actor-lr=1e-3-s0" / "policy.pt").stat().st_mtime_ns == mtime
    assert (out / "actor-lr=1e-3-s0" / "eval" / "cells" / "flown-obstacles.json").stat().st_mtime_ns == cell_mtime
    assert "in flown:obstacles: success" in capsys.readouterr().err


@pytest.mark.timeout(300)
def test_sweep_without_ray_flies_the_evaluation_cells_too(tmp_path, capsys):
    from sitl.learn.sweep import main

    out = tmp_path / "sweep"
    argv = ["--no-ray", "--seeds", "3", "--out", str(out), "--eval", "paper:circle-n8", "--eval-episodes", "2",
            "--", *TINY_TRAIN]
    assert main(argv) == 0
    table = json.loads((out / "sweep.json").read_text())
    cell = json.loads((out / "s3" / "eval" / "cells" / "paper-circle-n8.json").read_text())
    assert table["runs"][0]["result"]["eval_success"] == {"paper:circle-n8": cell["summary"]["success_rate"]}
    assert cell["settings"]["scenario"]["name"] == "circle" and cell["summary"]["episodes"] == 2
    assert table["evaluation"] == {"cells": ["paper:circle-n8"], "episodes": 2}
    assert (out / "sweep.png").stat().st_size > 0

    # A finished run whose policy file went missing: one line that names it, no traceback.
    (out / "s3" / "policy.pt").unlink()
    (out / "s3" / "eval" / "cells" / "paper-circle-n8.json").unlink()
    capsys.readouterr()
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "error: policy file" in err and "s3/policy.pt not found" in err and "Traceback" not in err


def test_a_recipe_run_reports_its_whole_recipe(tmp_path):
    """A recipe's row: all stages' updates, the end-to-end wall time, the last stage's last validation."""
    from sitl.learn.sweep import run_result

    run = tmp_path / "s0"
    (run / "stage2-b").mkdir(parents=True)
    stages = [{"run_dir": "stage1-a", "updates": 800}, {"run_dir": "stage2-b", "updates": 600}]
    # final_eval.json is the exported policy's provenance: the recipe's record there is what counts
    (run / "final_eval.json").write_text(json.dumps(
        {"updates": 600, "wall_time_s": 60.0, "evaluation": {"scenario": "random", "success_rate": 0.8},
         "recipe": {"stages": stages, "wall_time_s": 1795.0}}))
    (run / "stage2-b" / "learning_curve.json").write_text(json.dumps({"eval_success": [0.5, 0.7]}))
    (run / "recipe.json").write_text(json.dumps({"done": True, "wall_s": 1800.0, "stages": stages}))
    result = run_result(run)
    assert result["updates"] == 1400 and result["wall_time_s"] == 1795.0
    assert result["last_validation_success"] == 0.7 and result["final_success"] == {"random": 0.8}


def test_a_run_is_evaluated_as_the_method_its_policy_file_records(tmp_path, contract_policy):
    """A recipe whose first stages distil and whose last one is SAC (``flown-distill``): its run's
    config.json names the first stage's method, the exported file the one it was trained as."""
    from sitl.learn.sweep import eval_cells, evaluation_settings

    run = tmp_path / "s0"
    run.mkdir()
    (run / "config.json").write_text(json.dumps({"train": {"method": "distill"}}))
    settings = evaluation_settings(2)
    [(label, cell)] = eval_cells(run, ["flown:obstacles"], settings, policy=contract_policy)
    assert label == "flown:obstacles" and cell.method == "sac_ae"  # the file's provenance
    [(_, cell)] = eval_cells(run, ["flown:obstacles"], settings)  # no policy.pt yet: the run's config
    assert cell.method == "distill"


def test_sweep_refuses_an_unknown_evaluation_cell(capsys):
    from sitl.learn.sweep import parse_args

    with pytest.raises(SystemExit) as stop:
        parse_args(["--eval", "paper:random-medium,moon:crater", "--", *TINY_TRAIN])
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert "unknown evaluation cell(s) moon:crater" in err and "Traceback" not in err


@needs_ray
@pytest.mark.timeout(600)
def test_paper_cells_on_a_local_ray_equal_the_ones_computed_here(local_ray, tmp_path, contract_policy, capsys):
    from sitl.eval.cli import main

    common = ["--episodes", "1", "--table-episodes", "2", "--max-steps", "40", "--batch", "1", "--table-n", "3",
              "--densities", "medium", "--ns", "3", "--radius", "6", "--threads", "1", "--no-progress",
              "--policies", f"sac_ae={contract_policy},cnn={tmp_path / 'none.pt'},vae={tmp_path / 'none.pt'}"]
    assert main(["paper", "--out", str(tmp_path / "ray"), "--ray", *common]) == 0
    # sac_ae, orca and straight in Table II and in Fig. 6; cnn and vae have no policy file.
    assert "6 computed, 0 reused, 3 not trained" in capsys.readouterr().out
    assert main(["paper", "--out", str(tmp_path / "here"), *common]) == 0
    capsys.readouterr()
    cells = sorted(p.name for p in (tmp_path / "here" / "cells").iterdir())
    assert cells == sorted(p.name for p in (tmp_path / "ray" / "cells").iterdir()) and len(cells) == 6
    for name in cells:
        on_ray, here = (json.loads((tmp_path / d / "cells" / name).read_text()) for d in ("ray", "here"))
        assert on_ray["summary"] == here["summary"] and on_ray["key"] == here["key"], name
        assert on_ray["method"] == here["method"], name  # the policy's own path, not the task's copy
    assert (tmp_path / "ray" / "trajectories" / "fig6-n3-sac_ae.png").is_file()
    ray_json, here_json = (json.loads((tmp_path / d / "paper.json").read_text()) for d in ("ray", "here"))
    assert list(ray_json["cells"]) == list(here_json["cells"])
    assert (tmp_path / "ray" / "paper.md").read_text() == (tmp_path / "here" / "paper.md").read_text()
    # Started again with --ray, every cell is stored: nothing goes to Ray.
    assert main(["paper", "--out", str(tmp_path / "ray"), "--ray", *common]) == 0
    assert "0 computed, 6 reused" in capsys.readouterr().out


# --------------------------------------------------------------------------- without Ray

@pytest.mark.parametrize("argv", [
    ["-m", "sitl.swarm_test", "paper", "--ray", "--episodes", "1"],
    ["-m", "sitl.sweep", "--seeds", "0", "--", "--total-updates", "1"],
])
def test_without_ray_the_commands_say_how_to_install_it(tmp_path, argv):
    # ``sys.modules["ray"] = None`` makes ``import ray`` fail as it does where Ray is not installed.
    code = f"import sys, runpy; sys.modules['ray'] = None; sys.argv = {argv[1:]!r}; runpy.run_module({argv[1]!r}, run_name='__main__')"
    done = subprocess.run([sys.executable, "-c", code, ], capture_output=True, text=True, env=_env(), cwd=tmp_path,
                          timeout=120)
    assert done.returncode == 2, done.stderr
    assert done.stderr.strip().splitlines()[-1].endswith('pip install "swarmnav[ray]" (or pip install "ray[client]")')
    assert "Traceback" not in done.stderr


def test_sweep_refuses_what_it_sets_itself():
    from sitl.learn.sweep import parse_args

    for argv in (["--", "--seed", "3"], ["--grid", "seed=1,2"], ["--grid", "no-such-setting=1"],
                 ["--seeds", "1,1"], ["--", "--total-updates", "-5"]):
        with pytest.raises(SystemExit) as stop:
            parse_args(argv)
        assert stop.value.code == 2, argv


# --------------------------------------------------------------------------- progress and stages

def test_progress_prints_plain_lines_off_a_terminal():
    stream = io.StringIO()
    bar = Progress(total=200, initial=50, unit="update", desc="s0 | stage 2: mixed medium", stream=stream, every_s=0.0)
    assert not bar.tty
    bar.update(50)
    bar.set_fields(val="0.85", ep=12)
    bar.tick()
    line = stream.getvalue().strip().splitlines()[-1]
    assert line.startswith("s0 | stage 2: mixed medium: 100/200 updates (50 %)")
    assert "left; val 0.85, ep 12" in line and "\r" not in stream.getvalue()
    assert bar.eta_s(elapsed_s=10.0) == pytest.approx(20.0)  # 50 updates took 10 s here; 100 remain
    assert Progress(10, 0, "update", "x", stream=io.StringIO()).eta_s() == float("inf")


def test_format_duration():
    assert [format_duration(s) for s in (42, 750, 7500, float("inf"))] == ["42 s", "12.5 min", "2 h 05 min", "?"]


def test_a_second_stage_continues_the_learning_curve_with_its_boundary(tmp_path):
    run = lambda *a: subprocess.run([sys.executable, "-m", "sitl.train", *TINY_TRAIN, *a],  # noqa: E731
                                    capture_output=True, text=True, env=_env(), cwd=tmp_path, timeout=300)
    first = run("--run-dir", str(tmp_path / "one"), "--total-updates", "60", "--eval-every-updates", "30")  # 65 steps: episodes end
    assert first.returncode == 0, first.stderr
    second = run("--run-dir", str(tmp_path / "two"), "--init-from", str(tmp_path / "one"), "--scenario", "circle",
                 "--actor-lr", "3e-4", "--max-episode-steps", "10")  # short episodes: some end in its 20 steps
    assert second.returncode == 0, second.stderr
    # Not a terminal: plain progress lines naming the run and its stage, no carriage returns.
    assert "two | stage 2: circle medium, lr 0.0003: 15/15 updates (100 %)" in second.stderr
    assert "\r" not in second.stderr
    one = json.loads((tmp_path / "one" / "learning_curve.json").read_text())
    two = json.loads((tmp_path / "two" / "learning_curve.json").read_text())
    assert [s["name"] for s in two["stages"]] == ["random medium", "stage 2: circle medium, lr 0.0003"]
    boundary = two["stages"][1]["episode"]
    assert one["episode"] and boundary == one["episode"][-1] and two["stages"][1]["updates"] == 60
    assert two["episode"][:len(one["episode"])] == one["episode"]  # stage 1's curve, then stage 2's after it
    assert min(two["episode"][len(one["episode"]):]) > boundary
    assert two["eval_episode"][-1] >= boundary and len(two["eval_success"]) == len(one["eval_success"]) + 1 == 3
    assert (tmp_path / "two" / "learning_curve.png").stat().st_size > 10_000


@needs_ray
@pytest.mark.timeout(600)
def test_the_same_sweep_joins_an_existing_cluster_by_its_address(tmp_path):
    """A Ray head started with `ray start --head` (on loopback) is the existing cluster; the sweep
    joins it with --address, ships the code as py_modules, and the runs land in the same folders."""
    import signal
    import socket
    import time

    import secrets

    from tests.companion_helpers import free_tcp_port

    port = free_tcp_port()
    # Ray >= 2.59 authenticates with a token; a cluster's users get it with its address (docs/training.md).
    env = {**_env(), "RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN": secrets.token_hex(16)}
    head = subprocess.Popen(
        [sys.executable, "-m", "ray.scripts.scripts", "start", "--head", "--block", f"--port={port}",
         "--num-cpus=2", "--node-ip-address=127.0.0.1", "--include-dashboard=false", "--disable-usage-stats"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True, env=env)
    try:
        deadline = time.monotonic() + 120
        while True:  # the head's GCS takes 5-20 s to listen
            try:
                socket.create_connection(("127.0.0.1", port), timeout=1).close()
                break
            except OSError:
                if head.poll() is not None or time.monotonic() > deadline:
                    raise AssertionError(f"ray start --head did not come up: {head.stdout.read()[-2000:]}")
                time.sleep(0.5)
        out = tmp_path / "sweep"
        proc = subprocess.run([sys.executable, "-m", "sitl.sweep", "--address", f"127.0.0.1:{port}", "--seeds", "0",
                               "--out", str(out), "--eval", "paper:random-medium", "--eval-episodes", "2",
                               "--", *TINY_TRAIN], capture_output=True, text=True, env=env, cwd=tmp_path,
                              timeout=480)
        assert proc.returncode == 0, proc.stderr[-3000:]
        assert "Ray: 2 CPUs on 1 node(s)" in proc.stderr  # the head's (with an address Ray never starts its own)
        final = json.loads((out / "s0" / "final_eval.json").read_text())
        assert final["updates"] == 15 and (out / "s0" / "policy.pt").stat().st_size > 0
        table = json.loads((out / "sweep.json").read_text())
        assert table["runs"][0]["result"]["eval_success"]["paper:random-medium"] is not None
    finally:
        # The head and every Ray process it started. A graceful `--block` head takes ~30 s to wind down (measured
        # in session 56: 31 of this test's 46 s), so after 5 s the rest of the group is killed.
        os.killpg(head.pid, signal.SIGTERM)
        try:
            head.wait(timeout=5)
        except subprocess.TimeoutExpired:
            pass
        try:
            os.killpg(head.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass  # the whole group had gone
        head.wait(timeout=30)
