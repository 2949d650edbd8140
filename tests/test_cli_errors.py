"""Every bad command-line value is a one-line ``error: ...`` and a non-zero exit, never a traceback (issue 16).

Walks the options of ``companion``, ``sitl.vehicle``, ``sitl.world``, ``sitl.swarm_test`` (and
its ``paper`` subcommand) and ``sitl.train`` with NaN, inf, negative, zero, huge, wrong-type
values, unwritable paths and missing files. Most cases run in-process (the parser, or
``main`` where the error comes after parsing); one real process per command shows the
installed entry point behaves the same.
"""

from __future__ import annotations

import re
import subprocess
import sys

import pytest

from tests.companion_helpers import env

UNWRITABLE_DIR = "/proc/swarmnav-no-such-dir"  # /proc refuses new entries, even to root
MISSING_DIR = "/nonexistent-swarmnav-dir"


def _companion(argv):
    from companion import cli

    return cli.main(["--connect", "udp:14540", "--model", "policy.pt", *argv])


def _vehicle(argv):
    from sitl.realtime import vehicle

    return vehicle.parse_args(argv)  # main would start the simulation had the value been accepted


def _world(argv):
    from sitl.realtime import depth_bridge as world

    return world.parse_args(argv)


def _swarm_test(argv):
    from sitl.eval import cli as swarm_test

    return swarm_test.parse_args(argv)


def _swarm_test_main(argv):  # errors found after parsing (the policy file, the output folder)
    from sitl.eval import cli as swarm_test

    return swarm_test.main(argv)


def _paper(argv):
    from sitl.eval import cli as swarm_test

    return swarm_test.parse_paper_args(argv)


def _train(argv):
    from sitl.learn import cli as train

    return train.parse_args(argv)


def _train_main(argv):  # errors found after parsing (run directory, resume)
    from sitl.learn import cli as train

    return train.main(argv)


COMMANDS = {  # name: (entry, the program's error prefix)
    "companion": (_companion, "companion"),
    "vehicle": (_vehicle, "python -m sitl.vehicle"),
    "world": (_world, "python -m sitl.world"),
    "swarm_test": (_swarm_test, "python -m sitl.swarm_test"),
    "swarm_test_main": (_swarm_test_main, "python -m sitl.swarm_test"),
    "paper": (_paper, "python -m sitl.swarm_test paper"),
    "train": (_train, "python -m sitl.train"),
    "train_main": (_train_main, "python -m sitl.train"),
}

CASES = {
    "companion": [
        ["--heartbeat-timeout", "inf"], ["--heartbeat-timeout", "1e9"], ["--heartbeat-timeout", "0"],
        ["--link-timeout", "inf"], ["--link-timeout", "nan"], ["--link-timeout", "0"], ["--link-timeout", "1e9"],
        ["--stream-rate", "nan"], ["--stream-rate", "-1"], ["--stream-rate", "1e9"], ["--stream-rate", "fast"],
        ["--arm", "--takeoff", "1e6"], ["--arm", "--takeoff", "inf"], ["--arm", "--takeoff", "-3"],
        ["--timeout", "-5"], ["--timeout", "inf"], ["--timeout", "nan"],
        ["--connect", "udp:70000"], ["--connect", "udpout:no-such-host.invalid:14550"], ["--connect", "bogus"],
        ["--camera", "sitl:0"], ["--camera", "sitl:99999"], ["--camera", "realsense:0x0@30"], ["--camera", "kinect"],
        ["--goal", "nan,0,-3"], ["--goal", "1,2"],
        ["--log", f"{MISSING_DIR}/companion.jsonl"], ["--record", f"{MISSING_DIR}/flight.rec"], ["--record", "/tmp"],
        ["--signing-key", f"{MISSING_DIR}/key"], ["--takeoff", "3"], ["--bogus-flag"],
    ],
    "vehicle": [
        ["--n", "0"], ["--n", "100000"], ["--n", "abc"], ["--n", "2", "--base-port", "65535"], ["--base-port", "0"],
        ["--depth-port", "70000"], ["--depth-port", "65535", "--n", "3"], ["--gcs-port", "-1"],
        ["--camera-size", "1000x1000"], ["--camera-size", "100000x100000"], ["--camera-size", "0x5"],
        ["--camera-size", "big"], ["--camera-hz", "1e9"], ["--camera-hz", "0"], ["--camera-hz", "nan"],
        ["--camera-hz", "inf"], ["--hfov", "nan"], ["--hfov", "200"], ["--max-range", "inf"], ["--max-range", "-1"],
        ["--supersample", "0"], ["--supersample", "1000"], ["--cylinder", "1,2,-3"], ["--cylinder", "1,2,3,0"],
        ["--cylinder", "nan,0,1"], ["--box", "0,0,0,1,1,-1"], ["--box", "1,2"], ["--spacing", "inf"],
        ["--yaw-deg", "nan"], ["--start", "0,0,-5"], ["--airborne"], ["--starts", f"{MISSING_DIR}/starts.json"],
        ["--signing-key", f"{MISSING_DIR}/key"], ["--log", f"{MISSING_DIR}/v.jsonl"],
        ["--trace", f"{UNWRITABLE_DIR}/trace.jsonl"], ["--trace", "/tmp"], ["--duration", "0"],
        ["--duration", "nan"], ["--host", "no-such-host.invalid"], ["--dynamics", "warp"], ["--autopilot", "inav"],
        ["--camera", "kinect"], ["--camera", "realsense_d435", "--hfov", "nan"],
    ],
    "world": [
        ["--px4", "0"], ["--px4", "300"], ["--px4", "2", "--px4-first-instance", "-1"],
        ["--connect", "bogus"], ["--px4", "1", "--sysid", "0"], ["--px4", "1", "--sysid", "256"],
        ["--px4", "1", "--sysid", "abc"], ["--px4", "1", "--spacing", "nan"], ["--px4", "1", "--camera-hz", "1e9"],
        ["--px4", "1", "--cylinder", "0,0,-1"], ["--px4", "1", "--host", "no-such-host.invalid"],
        ["--px4", "1", "--gcs-port", "0"], ["--px4", "2", "--depth-port", "65535"],
        ["--px4", "1", "--log", f"{MISSING_DIR}/w.jsonl"], ["--px4", "1", "--stream-rate", "inf"],
        ["--px4", "1", "--spawn-offsets", "a,b,c"], ["--px4", "1", "--camera-size", "1000x1000"],
        ["--px4", "1", "--supersample", "1000"], ["--px4", "1", "--duration", "-1"], [],
    ],
    "swarm_test": [
        ["--n", "0"], ["--n", "100000"], ["--radius", "nan"], ["--radius", "-1"], ["--radius", "1e300"],
        ["--density", "inf"], ["--density", "nan"], ["--density", "-2"], ["--density", "thick"],
        ["--episodes", "0"], ["--episodes", "1e3"], ["--seed", "-1"], ["--seed", "abc"], ["--batch", "0"],
        ["--batch", "10000000"], ["--threads", "100000"], ["--max-steps", "0"], ["--plot-episodes", "-1"],
        ["--out", f"{UNWRITABLE_DIR}/out"], ["--json", f"{UNWRITABLE_DIR}/m.json"], ["--scenario", "maze"],
        ["--mavlink", "--base-port", "80"], ["--mavlink", "--n", "200", "--base-port", "65500"],
        ["--camera", "kinect"], ["--camera", ""],
    ],
    "swarm_test_main": [["--policy", f"{MISSING_DIR}/policy.pt", "--no-progress"]],
    "paper": [
        ["--out", f"{UNWRITABLE_DIR}/paper"], ["--ns", "0"], ["--ns", "8,100000"], ["--ns", "x"],
        ["--densities", "nan"], ["--densities", "inf"], ["--table-n", "0"], ["--radius", "inf"],
        ["--policies", "foo=bar.pt"], ["--policies", "sac_ae"], ["--table-episodes", "0"], ["--threads", "0"],
    ],
    "train": [
        ["--discount", "nan"], ["--discount", "1.5"], ["--discount", "0"], ["--n-step", "0"], ["--n-step", "x"],
        ["--num-uavs", "0"], ["--num-worlds", "abc"], ["--image-size", "8"], ["--image-size", "100000"],
        ["--camera", "kinect"], ["--mount-pitch-jitter-deg", "nan"], ["--mount-pitch-jitter-deg", "90"],
        ["--replay-capacity", "0"], ["--replay-capacity", "1e12"], ["--critic-lr", "-1"], ["--actor-lr", "inf"],
        ["--hidden-dim", "1000000000"], ["--seed", "-1"], ["--threads", "0"], ["--device", "warp9"],
        ["--density", "inf"], ["--checkpoint-every-s", "0"], ["--checkpoint-every-s", "inf"],
        ["--circle-fraction", "nan"], ["--method", "ppo"], ["--preset", "huge"], ["--updates-per-env-step", "inf"],
        ["--yaw-jitter-deg", "-1"], ["--arrival-radius-m", "nan"], ["--critic-tau", "2"], ["--drq-pad", "-1"],
        ["--init-temperature", "0"], ["--batch-size", "many"], ["--select-best", "yes"],
    ],
    "train_main": [["--run-dir", f"{UNWRITABLE_DIR}/run"], ["--resume", f"{MISSING_DIR}/run"]],
}


def _check_one_line_error(code, err: str, prefix: str) -> None:
    assert code not in (0, None), err
    assert "Traceback" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert re.match(rf"({re.escape(prefix)}: )?error: \S", lines[0]), lines[0]


@pytest.mark.parametrize("command, argv", [(c, a) for c, cases in CASES.items() for a in cases],
                         ids=[f"{c}:{' '.join(a)}" for c, cases in CASES.items() for a in cases])
def test_a_bad_value_is_a_one_line_error(command, argv, capsys):
    entry, prefix = COMMANDS[command]
    try:
        code = entry(argv)
    except SystemExit as stop:
        code = stop.code
    else:
        assert isinstance(code, int), f"{argv} was accepted"
    _check_one_line_error(code, capsys.readouterr().err, prefix)


def test_the_real_processes_print_one_line_and_exit_non_zero(tmp_path):
    """One bad value per command through ``python -m``: the same one line, exit 2, no traceback."""
    runs = {
        "companion": (["companion.cli", "--connect", "udp:14540", "--model", "p.pt", "--link-timeout", "inf"],
                      "companion"),
        "vehicle": (["sitl.vehicle", "--n", "2", "--base-port", "65535"], "python -m sitl.vehicle"),
        "world": (["sitl.world", "--px4", "1", "--camera-hz", "1e9"], "python -m sitl.world"),
        "swarm_test": (["sitl.swarm_test", "--out", f"{UNWRITABLE_DIR}/out"], "python -m sitl.swarm_test"),
        "paper": (["sitl.swarm_test", "paper", "--ns", "0"], "python -m sitl.swarm_test paper"),
        "train": (["sitl.train", "--discount", "nan"], "python -m sitl.train"),
    }
    procs = {name: subprocess.Popen([sys.executable, "-m", *argv], cwd=tmp_path, env=env(),
                                    stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for name, (argv, _) in runs.items()}
    try:
        for name, proc in procs.items():
            out, err = proc.communicate(timeout=120)
            assert proc.returncode == 2, (name, err)
            assert out == "", (name, out)
            _check_one_line_error(proc.returncode, err, runs[name][1])
    finally:
        for proc in procs.values():
            proc.kill()
            proc.wait()
