"""The installed package: the onboard core does not depend on the simulator; the CLIs answer."""

from __future__ import annotations

import importlib.metadata
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

# Run in a fresh interpreter as if only the base install were there: a meta-path hook refuses every
# top-level module outside ALLOWED (argv[1], JSON), so an optional `try: import tqdm` inside torch
# falls back exactly as on the drone, while a plain `import matplotlib` in companion fails. Then
# import every companion module, answer `companion --help`, load the bundled policy, and print the
# top-level names of all modules imported. Further argv names are imported first (the test's own test).
_IMPORT_EVERYTHING = r"""
import contextlib, importlib, io, json, pkgutil, sys

ALLOWED = set(json.loads(sys.argv[1]))


class OutsideBaseInstall:
    def find_spec(self, name, path=None, target=None):
        top = name.partition(".")[0]
        if top not in ALLOWED and top not in sys.modules:
            raise ModuleNotFoundError(f"No module named {top!r} (outside the base install)", name=top)
        return None


sys.meta_path.insert(0, OutsideBaseInstall())
for name in sys.argv[2:]:
    importlib.import_module(name)
import companion
for info in pkgutil.walk_packages(companion.__path__, "companion."):
    importlib.import_module(info.name)
from companion.cli import main
with contextlib.redirect_stdout(io.StringIO()):
    try:
        main(["--help"])
    except SystemExit as stop:
        assert stop.code == 0, stop.code
from companion.policy import load_policy
load_policy("models/policy.pt")
print(json.dumps(sorted({name.partition(".")[0] for name in list(sys.modules)})))
"""


def _normalize(dist: str) -> str:
    return re.sub(r"[-_.]+", "-", dist).lower()


def _base_requirements() -> list[str]:
    """The `[project] dependencies` of this checkout's pyproject.toml (not a stale installed copy)."""
    tomllib = pytest.importorskip("tomllib")
    return tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["dependencies"]


def _closure(requirements: list[str]) -> set[str]:
    """Every distribution the requirements pull in, recursively, without any extra (normalized names)."""
    from packaging.requirements import Requirement

    seen: set[str] = set()
    todo = list(requirements)
    while todo:
        req = Requirement(todo.pop())
        if req.marker is not None and not req.marker.evaluate({"extra": ""}):
            continue
        name = _normalize(req.name)
        if name in seen:
            continue
        seen.add(name)
        try:
            todo.extend(importlib.metadata.requires(req.name) or [])
        except importlib.metadata.PackageNotFoundError:
            pass  # not installed here: nothing of it can have been imported either
    return seen


def _base_modules() -> set[str]:
    """Top-level module names the base install provides: stdlib, companion, the base closure's."""
    base = _closure(_base_requirements())
    owned = {module for module, dists in importlib.metadata.packages_distributions().items()
             if {_normalize(d) for d in dists} & base}
    return (set(sys.stdlib_module_names) | set(sys.builtin_module_names) | owned | {"companion"}) - {"sitl"}


def _import_companion_on_base(*extra_imports: str) -> subprocess.CompletedProcess:
    allowed = sorted(_base_modules())
    return subprocess.run([sys.executable, "-c", _IMPORT_EVERYTHING, json.dumps(allowed), *extra_imports],
                          cwd=REPO, capture_output=True, text=True, timeout=120)


def test_companion_imports_only_the_base_install():
    run = _import_companion_on_base()
    assert run.returncode == 0, f"companion needs a module outside the base install (pyproject dependencies):\n{run.stderr[-2000:]}"
    imported = json.loads(run.stdout.strip().splitlines()[-1])
    owners = importlib.metadata.packages_distributions()
    # Dunder names are interpreter/installer plumbing (__main__, __mp_main__, the editable finder).
    outside = {m: owners.get(m, ["<no distribution>"]) for m in imported
               if m not in _base_modules() and not m.startswith("__")}
    assert not outside, f"companion imported modules outside the base install: {outside}"


def test_the_base_install_check_catches_a_workstation_dependency():
    run = _import_companion_on_base("matplotlib")
    assert run.returncode != 0 and "No module named 'matplotlib' (outside the base install)" in run.stderr


def test_companion_describe_prints_the_contract():
    out = subprocess.run([sys.executable, "-m", "companion.cli", "--describe"], check=True, capture_output=True, text=True)
    contract = json.loads(out.stdout)
    assert contract["state"][0] == "goal_fwd_m" and contract["action"]["high"] == [2.0, 0.5, 0.5]


def test_demo_runs_and_rejects_bad_values(tmp_path):
    ok = subprocess.run([sys.executable, "-m", "sitl.demo", "--n", "4", "--episodes", "2", "--out", str(tmp_path)],
                        capture_output=True, text=True, timeout=120)
    assert ok.returncode == 0, ok.stderr
    assert "success rate" in ok.stdout and (tmp_path / "trajectories.png").stat().st_size > 1000
    assert json.loads((tmp_path / "metrics.json").read_text())["summary"]["uav_episodes"] == 8
    bad = subprocess.run([sys.executable, "-m", "sitl.demo", "--scenario", "spiral"], capture_output=True, text=True)
    assert bad.returncode == 2 and "invalid choice: 'spiral'" in bad.stderr
