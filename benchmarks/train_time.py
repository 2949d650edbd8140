"""End-to-end training time of a recipe: the one command, from the first update to the exported policy.

Two ways to get the number:

* ``--run RUN``: read a recipe run's own record (``RUN/recipe.json``, written by ``python -m
  sitl.train --preset flown-fast``): each stage's updates and wall time, the rescoring and export
  after the last stage, and the total. Works on an unfinished run too (then it reports what
  is done). This is the real run's wall time, the number policy.json's
  ``provenance.recipe.wall_time_s`` records.
* default: run the recipe at ``--scale`` (every stage's updates, validation intervals and
  evaluation episodes times the scale: ``python -m sitl.train --recipe-scale``) in a scratch
  directory and extrapolate to the full recipe: each stage's seconds per update times its full
  update count, plus the rescoring and export time divided by the scale. The fixed costs
  (random warm-up transitions, process start) are counted as if they scaled, so the
  extrapolation errs on the long side at small scales.

The last line is one JSON object: ``wall_time_min`` (measured, ``--run``) or
``extrapolated_wall_time_min`` (at scale 1) and the per-stage rows.

Usage: ``python benchmarks/train_time.py [--preset flown-fast] [--scale 0.05] [--run RUN] [--smoke] [-- TRAIN FLAGS]``
(``--smoke``: the recipe at a tiny scale with tiny networks and worlds, seconds; what CI runs.)
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from sitl.learn.config import BUNDLE_PRESET, PRESETS  # noqa: E402
from sitl.learn.recipe import RECIPE_FILE  # noqa: E402

#: --smoke: the recipe's code path in seconds (tiny networks, worlds and budgets).
SMOKE_SCALE = 0.0005
SMOKE_FLAGS = ["--hidden-dim", "32", "--latent-dim", "8", "--num-filters", "8", "--num-worlds", "2",
               "--num-uavs", "3", "--init-steps", "48", "--batch-size", "16", "--max-episode-steps", "30",
               "--eval-episodes", "2", "--final-eval-episodes", "3", "--checkpoint-every-s", "1000000"]


def read_run(run_dir: Path) -> dict:
    """A recipe run's timing from its ``recipe.json``: per stage, and the rescoring + export after the stages."""
    path = run_dir / RECIPE_FILE
    if not path.is_file():
        raise SystemExit(f"error: {path} not found: not a recipe run directory")
    state = json.loads(path.read_text())
    stages = [{"name": s["name"], "updates": s["updates"], "wall_s": s["wall_s"],
               "s_per_update": round(s["wall_s"] / max(s["updates"], 1), 4)} for s in state["stages"]]
    stage_wall = sum(s["wall_s"] for s in stages)
    return {"run_dir": str(run_dir), "preset": state.get("preset"), "scale": state.get("scale", 1.0),
            "done": bool(state.get("done")), "stages": stages, "stages_wall_s": round(stage_wall, 1),
            "after_stages_s": round(state["wall_s"] - stage_wall, 1) if state.get("done") else None,
            "wall_s": round(state["wall_s"], 1)}


def extrapolate(timing: dict, preset: str) -> float:
    """Seconds the full-scale recipe would take, from a scaled run's ``timing`` (see the module doc)."""
    full = PRESETS[preset]["stages"]
    seconds = sum(row["s_per_update"] * stage.train["total_updates"] for row, stage in zip(timing["stages"], full))
    return seconds + (timing["after_stages_s"] or 0.0) / timing["scale"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    recipes = sorted(name for name, preset in PRESETS.items() if preset.get("stages"))
    parser.add_argument("--preset", default=BUNDLE_PRESET, choices=recipes,
                        help=f"the recipe (default {BUNDLE_PRESET}, the bundle's; flown was until 2026-11-25)")
    parser.add_argument("--scale", type=float, default=0.05, help="recipe scale of the timed trial (default 0.05)")
    parser.add_argument("--run", type=Path, default=None, help="report a recipe run's recorded times instead")
    parser.add_argument("--out", type=Path, default=None, help="where the trial trains (default: a scratch directory)")
    parser.add_argument("--smoke", action="store_true", help="CI check: a tiny recipe with tiny networks, seconds")
    parser.add_argument("train_flags", nargs="*", help="after --: extra flags for python -m sitl.train")
    args = parser.parse_args()
    if args.run is not None:
        timing = read_run(args.run)
        for row in timing["stages"]:
            print(f"{row['name']:14s} {row['updates']:6d} updates  {row['wall_s'] / 60:6.1f} min  "
                  f"{1000 * row['s_per_update']:6.0f} ms/update", flush=True)
        print(json.dumps({"benchmark": "train_time", **timing, "wall_time_min": round(timing["wall_s"] / 60, 1)}))
        return
    scale = SMOKE_SCALE if args.smoke else args.scale
    if not 0.0 < scale <= 1.0:
        parser.error(f"--scale must be in (0, 1], got {scale}")
    flags = (SMOKE_FLAGS if args.smoke else []) + args.train_flags
    with tempfile.TemporaryDirectory(prefix="train_time-") as scratch:
        run_dir = args.out or Path(scratch) / "run"
        cmd = [sys.executable, "-m", "sitl.train", "--preset", args.preset, "--recipe-scale", str(scale),
               "--run-dir", str(run_dir), *flags]
        print("running: " + " ".join(cmd[1:]), flush=True)
        proc = subprocess.run(cmd, cwd=REPO)
        if proc.returncode != 0:
            raise SystemExit(f"error: the recipe trial exited {proc.returncode}")
        timing = read_run(run_dir)
    estimate = extrapolate(timing, args.preset)
    for row in timing["stages"]:
        print(f"{row['name']:14s} {row['updates']:6d} updates  {row['wall_s']:7.1f} s  "
              f"{1000 * row['s_per_update']:6.0f} ms/update", flush=True)
    print(f"rescoring + export: {timing['after_stages_s']} s at scale {scale}; "
          f"full recipe extrapolated: {estimate / 60:.1f} min", flush=True)
    print(json.dumps({"benchmark": "train_time", **timing, "smoke": args.smoke,
                      "extrapolated_wall_time_min": round(estimate / 60, 1)}))


if __name__ == "__main__":
    main()
