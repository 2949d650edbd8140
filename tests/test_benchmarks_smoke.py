"""Every benchmark script's ``--smoke`` run, as CI runs it: exit 0 and a JSON object as the last line.

Project rule: performance is measured with scripts under ``benchmarks/`` that print a JSON
summary as their last line, each with a smoke mode CI runs. The scripts are discovered, so a
new one is covered (or flagged, when it has no ``--smoke``) without editing this file.
``fuzz_companion.py`` and ``depth_preprocess.py`` check their own results in their own tests
(test_fuzz_smoke.py, test_depth_preprocess.py) and are not run twice here.
"""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from tests.companion_helpers import REPO, env

BENCHMARKS = REPO / "benchmarks"
#: Scripts whose smoke run has its own test with stronger assertions.
OWN_TESTS = {"fuzz_companion.py": "test_fuzz_smoke.py", "depth_preprocess.py": "test_depth_preprocess.py"}
#: Seconds one smoke run may take (they take 2-15 s on a busy 2-core machine; imports dominate).
SMOKE_TIMEOUT_S = 120


def _is_script(source: str) -> bool:
    """A runnable benchmark, not a helper module (fuzz_inputs.py) the scripts import."""
    return 'if __name__ == "__main__":' in source


def _has_smoke(source: str) -> bool:
    return 'add_argument("--smoke"' in source


SCRIPTS = sorted(p.name for p in BENCHMARKS.glob("*.py") if _is_script(p.read_text()))
SMOKE_SCRIPTS = [name for name in SCRIPTS if _has_smoke((BENCHMARKS / name).read_text()) and name not in OWN_TESTS]


def test_every_benchmark_script_has_a_smoke_mode():
    missing = [name for name in SCRIPTS if not _has_smoke((BENCHMARKS / name).read_text())]
    assert not missing, f"benchmark scripts without --smoke (CI cannot run them): {missing}"
    assert all((REPO / "tests" / test).is_file() for test in OWN_TESTS.values())
    assert len(SMOKE_SCRIPTS) >= 5, SMOKE_SCRIPTS  # discovery still finds the five this file was written for


@pytest.mark.parametrize("script", SMOKE_SCRIPTS)
def test_smoke_run_prints_a_json_summary_last(script: str):
    proc = subprocess.run([sys.executable, str(BENCHMARKS / script), "--smoke"], cwd=REPO, env=env(),
                          capture_output=True, text=True, timeout=SMOKE_TIMEOUT_S)
    assert proc.returncode == 0, f"{script} --smoke exited {proc.returncode}:\n{proc.stderr[-3000:]}"
    lines = proc.stdout.strip().splitlines()
    assert lines, f"{script} --smoke printed nothing; stderr:\n{proc.stderr[-3000:]}"
    try:
        summary = json.loads(lines[-1])
    except json.JSONDecodeError as exc:
        raise AssertionError(f"{script} --smoke: last line is not JSON ({exc}): {lines[-1]!r}") from None
    assert isinstance(summary, dict) and summary, f"{script} --smoke: last line is not a JSON object: {lines[-1]!r}"


def test_train_speed_measures_copies_side_by_side():
    """``--copies 2``: two processes time the same configuration at once; the headline is their sum."""
    proc = subprocess.run([sys.executable, str(BENCHMARKS / "train_speed.py"), "--smoke", "--copies", "2",
                           "--threads", "1"], cwd=REPO, env=env(), capture_output=True, text=True,
                          timeout=SMOKE_TIMEOUT_S)
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads(proc.stdout.strip().splitlines()[-1])
    per_copy = summary["updates_per_s_per_copy"]
    assert summary["copies"] == 2 and len(per_copy) == 2 and all(rate > 0 for rate in per_copy)
    assert summary["updates_per_s"] == pytest.approx(sum(per_copy), abs=0.02)


@pytest.mark.skipif(__import__("torch").cuda.is_available(), reason="this machine has a GPU: nothing to refuse")
def test_train_speed_refuses_a_gpu_it_does_not_have():
    """``--device cuda`` without a CUDA device: one line, exit 2, no traceback (the GPU path itself
    was run on a lent H200, docs/training.md 'On a GPU')."""
    proc = subprocess.run([sys.executable, str(BENCHMARKS / "train_speed.py"), "--smoke", "--device", "cuda"],
                          cwd=REPO, env=env(), capture_output=True, text=True, timeout=SMOKE_TIMEOUT_S)
    assert proc.returncode == 2 and "torch sees no CUDA device" in proc.stderr and "Traceback" not in proc.stderr


@pytest.mark.parametrize("args, message", [
    (["--batch-size", "0"], "--batch-size in 1..4096"),
    (["--copies", "2", "--batch-size", "64"], "leave out --device and --batch-size"),
    (["--num-filters", "0"], "--num-filters must be in 1..256"),
    (["--copies", "2", "--profile"], "leave out --sizes, --methods, --hidden, --num-filters and --profile"),
])
def test_train_speed_refuses_bad_options_in_one_line(args, message):
    proc = subprocess.run([sys.executable, str(BENCHMARKS / "train_speed.py"), "--smoke", *args],
                          cwd=REPO, env=env(), capture_output=True, text=True, timeout=SMOKE_TIMEOUT_S)
    assert proc.returncode == 2 and message in proc.stderr and "Traceback" not in proc.stderr


def test_train_speed_measures_another_batch_size():
    proc = subprocess.run([sys.executable, str(BENCHMARKS / "train_speed.py"), "--smoke", "--batch-size", "32"],
                          cwd=REPO, env=env(), capture_output=True, text=True, timeout=SMOKE_TIMEOUT_S)
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads(proc.stdout.strip().splitlines()[-1])
    assert summary["batch_size"] == 32 and summary["updates_per_s"] > 0


def test_train_speed_profiles_a_narrower_encoder():
    """``--num-filters 16 --profile``: the measured agent has 16 filters, and the update's time by part
    adds up to the whole, most of it in convolutions and matrix products (not a constant: read from
    torch.profiler on this run)."""
    proc = subprocess.run([sys.executable, str(BENCHMARKS / "train_speed.py"), "--smoke", "--num-filters", "16",
                           "--profile"], cwd=REPO, env=env(), capture_output=True, text=True, timeout=SMOKE_TIMEOUT_S)
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads(proc.stdout.strip().splitlines()[-1])
    shares = summary["profile_shares"]
    assert summary["num_filters"] == 16 and summary["updates_per_s"] > 0
    assert sum(shares.values()) == pytest.approx(1.0, abs=0.01)
    assert shares["convolution forward"] + shares["convolution backward"] + shares["matrix products"] > 0.3


def test_low_flight_refuses_a_policy_it_cannot_fly_in_one_line(tmp_path):
    """A file that is no policy, a policy whose camera no simulated sensor carries (120 deg wide), and a vehicle
    response the simulator cannot fly: one line naming the problem, exit 1, no traceback and no flight."""
    import dataclasses

    from companion.spec import REALSENSE_D435
    from tests.companion_helpers import make_policy

    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a policy")
    odd = make_policy(tmp_path / "odd.pt", camera=dataclasses.replace(REALSENSE_D435, hfov_deg=120.0))
    bundled = REPO / "models" / "policy.pt"
    for path, extra, message in ((junk, [], "not a TorchScript policy file"),
                                 (odd, [], "no camera preset has a 120 x 58.0 deg field of view with a 10 m range"),
                                 (bundled, ["--vehicle-response", "command_delay_s=2"], "command_delay_s must be")):
        proc = subprocess.run([sys.executable, str(BENCHMARKS / "low_flight.py"), "--smoke", "--policy", str(path),
                               *extra], cwd=REPO, env=env(), capture_output=True, text=True, timeout=SMOKE_TIMEOUT_S)
        assert proc.returncode == 1 and message in proc.stderr, proc.stderr[-2000:]
        assert "Traceback" not in proc.stderr and len(proc.stderr.strip().splitlines()) == 1 and proc.stdout == ""
