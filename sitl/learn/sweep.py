"""``python -m sitl.sweep``: several training runs (seeds, a small grid) as Ray tasks, one table of results.

Every run is ``python -m sitl.train`` with the flags given after the sweep's own, plus its
seed and grid values, and writes the same run directory as that command, here under one
sweep directory (``OUT/<grid values>-s<seed>``)::

    python -m sitl.sweep --seeds 0,1,2 -- --total-updates 25000          # a local Ray on this machine
    python -m sitl.sweep --seeds 0,1,2 --grid actor-lr=1e-3,3e-4 -- ...  # 6 runs
    python -m sitl.sweep --address ray://head:10001 --seeds 0,1,2 -- ... # the same on a cluster

Each run is one Ray task holding ``--cpus-per-run`` CPUs (default 1) with as many torch
threads. When the workers see the sweep directory (this machine, or a cluster with a shared
file system) they write their runs there directly; otherwise each run trains in a
temporary directory on its node and its files come back here when it ends — all but
``checkpoint.pt`` (its replay buffer is hundreds of MiB), which stays on the node.

The sweep writes ``sweep.json``, ``sweep.md`` and ``sweep.png``: per run the last validation success and
the final (test-seed) success of every evaluation scenario; per grid point their mean,
standard deviation and spread (max - min) over the seeds. A finished run (its
``final_eval.json`` exists) is not trained again when the sweep is started again, so an
interrupted sweep resumes; an unfinished one starts afresh. ``--no-ray`` runs the same
runs one after another in this process (no Ray needed).

``--eval CELLS`` also flies every finished run's ``policy.pt`` in named evaluation cells of
``python -m sitl.swarm_test`` (the paper protocol's ``paper:random-medium``, ...; the flown
protocol's ``flown:circle-n8``, ...; ``--eval-episodes`` each, held-out test seeds), one Ray
task of one CPU per run and cell, started as soon as the run has finished training. Each
cell's JSON goes to ``OUT/<run>/eval/cells/`` (reused when the policy file and settings
match) and its success into the tables, with mean, std and spread over the seeds::

    python -m sitl.sweep --seeds 0,1,2 --eval paper:random-medium,flown:random-medium,flown:circle-n8,flown:obstacles \
        --cpus-per-run 2 -- --preset flown-fast
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import math
import shutil
import sys
import tempfile
import time
import uuid
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from sitl.cli_args import MAX_THREADS, ArgumentParser, int_range, output_dir, positive_int
from sitl.distributed import LOCAL, RayUnavailable, connect, describe_cluster, log, single_thread
from sitl.eval.methods import EvaluationError
from sitl.eval.report import write_json
from sitl.learn.agent import AgentConfig
from sitl.learn.config import TrainConfig

if TYPE_CHECKING:
    from sitl.eval.evaluate import EvalSettings
    from sitl.eval.paper import PaperCell

PROG = "python -m sitl.sweep"

#: Training flags the sweep sets itself for each run.
RESERVED_FLAGS = ("--seed", "--run-dir", "--threads", "--resume")

#: File in the sweep directory whose content tells a worker it sees the same directory.
TOKEN_FILE = ".sweep_token"

#: Files a run on a node that does not share the sweep directory keeps there.
LEFT_ON_NODE = ("checkpoint.pt",)


@dataclasses.dataclass(frozen=True)
class SweepRun:
    """One training run of a sweep."""

    name: str  # its directory under the sweep directory
    seed: int
    grid: dict  # flag name (dashes) -> value text
    argv: tuple[str, ...]  # ``python -m sitl.train`` flags, run directory and threads excluded


def _seed_list(text: str) -> list[int]:
    parse = int_range(0, 2**32 - 1)
    seeds = [parse(v.strip()) for v in text.split(",") if v.strip()]
    if not seeds:
        raise argparse.ArgumentTypeError("expected at least one seed")
    if len(set(seeds)) != len(seeds):
        raise argparse.ArgumentTypeError(f"seeds repeat in {text!r}")
    return seeds


#: Flag names (dashes) of every training and agent setting.
SETTING_FLAGS = {f.name.replace("_", "-") for cls in (TrainConfig, AgentConfig) for f in dataclasses.fields(cls)}


def _grid_item(text: str) -> tuple[str, list[str]]:
    name, sep, values = text.partition("=")
    name = name.strip().lstrip("-").replace("_", "-")
    items = [v.strip() for v in values.split(",") if v.strip()]
    if not sep or not items:
        raise argparse.ArgumentTypeError(f"expected NAME=V1,V2,..., got {text!r}")
    if name not in SETTING_FLAGS or f"--{name}" in RESERVED_FLAGS:
        raise argparse.ArgumentTypeError(f"{name!r} is not a training setting the sweep can vary "
                                         "(see python -m sitl.train --help; seeds go in --seeds)")
    return name, items


#: Episodes per evaluation cell unless ``--eval-episodes`` says otherwise (the protocols' own default).
DEFAULT_EVAL_EPISODES = 500


def evaluation_settings(episodes: int) -> dict[str, "EvalSettings"]:
    """The cells ``--eval`` can name, as ``swarm_test`` flies them: ``paper:<cell>`` as ``swarm_test paper``
    (N = 8, perfect depth; Table II's random scenes and Fig. 6's circle of 8) and ``flown:<cell>``
    as ``swarm_test flown`` (its camera noise, jitter and altitudes; :func:`sitl.eval.flown.flown_cells`)."""
    from sitl.eval.evaluate import EvalSettings
    from sitl.eval.flown import flown_cells
    from sitl.sim.config import CIRCLE_RADIUS_M, DENSITIES, ScenarioConfig

    common = dict(num_uavs=8, episodes=episodes, seed=0, camera_noise=False, record_paths=False)
    cells = {f"paper:random-{name}": EvalSettings(scenario=ScenarioConfig(name="random", density=density), **common)
             for name, density in DENSITIES.items()}
    cells["paper:circle-n8"] = EvalSettings(scenario=ScenarioConfig(name="circle", circle_radius_m=CIRCLE_RADIUS_M),
                                            **common)
    cells |= {f"flown:{cell.name}": cell.settings for cell in flown_cells(episodes)}
    return cells


def eval_cell_list(text: str) -> list[str]:
    """``--eval``'s parser: known, distinct evaluation cells (:func:`evaluation_settings`), comma-separated."""
    known = evaluation_settings(1)
    names = [v.strip() for v in text.split(",") if v.strip()]
    unknown = [n for n in names if n not in known]
    if not names or unknown:
        raise argparse.ArgumentTypeError(f"unknown evaluation cell(s) {', '.join(unknown) or repr(text)}; "
                                         f"choose from {', '.join(known)}")
    if len(set(names)) != len(names):
        raise argparse.ArgumentTypeError(f"evaluation cells repeat in {text!r}")
    return names


def build_parser() -> argparse.ArgumentParser:
    parser = ArgumentParser(prog=PROG, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter,
                            usage=f"{PROG} [options] [-- TRAIN FLAGS]")
    parser.add_argument("--seeds", type=_seed_list, default=[0, 1, 2], help="training seeds (default 0,1,2)")
    parser.add_argument("--grid", type=_grid_item, action="append", default=[], metavar="NAME=V1,V2",
                        help="a training setting and its values, e.g. actor-lr=1e-3,3e-4 (repeatable: the runs "
                             "are every combination, times every seed)")
    parser.add_argument("--out", type=output_dir, default=None,
                        help="sweep directory (default runs/sweep-<time>); an existing one is resumed")
    parser.add_argument("--address", default=LOCAL,
                        help="Ray to run on: local (start one on this machine, the default), auto (the one "
                             "`ray start` runs here) or a cluster address such as ray://head:10001")
    parser.add_argument("--num-cpus", type=int_range(1, 4096), default=None,
                        help="cores of a local Ray (default all of this machine's)")
    parser.add_argument("--cpus-per-run", type=int_range(1, 256), default=1,
                        help="CPUs each run's task holds, and its torch threads (default 1)")
    parser.add_argument("--no-ray", dest="ray", action="store_false",
                        help="run the runs one after another in this process instead (no Ray needed)")
    parser.add_argument("--eval", type=eval_cell_list, default=[], metavar="CELLS",
                        help="also fly every run's policy.pt in these swarm_test cells, comma-separated: "
                             "paper:random-small|medium|large, paper:circle-n8, flown:random-small|medium|large, "
                             "flown:circle-n8, flown:obstacles, flown:random-medium-jsbsim (one 1-CPU task each)")
    parser.add_argument("--eval-episodes", type=int_range(1, 100_000), default=DEFAULT_EVAL_EPISODES,
                        help=f"episodes per evaluation cell, held-out test seeds (default {DEFAULT_EVAL_EPISODES})")
    return parser


def plan_runs(seeds: list[int], grid: list[tuple[str, list[str]]], train_argv: list[str]) -> list[SweepRun]:
    """Every grid combination times every seed, each with its run directory name."""
    names = [name for name, _ in grid]
    runs = []
    for values in itertools.product(*[v for _, v in grid]):
        point = dict(zip(names, values))
        label = "-".join(f"{n}={v}" for n, v in point.items())
        for seed in seeds:
            argv = [*train_argv, *itertools.chain.from_iterable((f"--{n}", v) for n, v in point.items()),
                    "--seed", str(seed)]
            name = f"{label}-s{seed}" if label else f"s{seed}"
            runs.append(SweepRun("".join(c if c.isalnum() or c in "-=._" else "_" for c in name), seed, point,
                                 tuple(argv)))
    return runs


def parse_args(argv: list[str] | None = None) -> tuple[argparse.Namespace, list[SweepRun]]:
    """The sweep's options and its runs; every run's training flags are checked here, before anything starts."""
    from sitl.learn.cli import parse_args as parse_train_args

    argv = sys.argv[1:] if argv is None else list(argv)
    if "--" in argv:
        split = argv.index("--")
        own, train_argv = argv[:split], argv[split + 1:]
    else:
        own, train_argv = argv, []
    parser = build_parser()
    args = parser.parse_args(own)
    for flag in train_argv:
        if flag.split("=")[0] in RESERVED_FLAGS:
            parser.error(f"{flag.split('=')[0]} is set by the sweep for each run (seeds: --seeds; "
                         "directory: --out; threads: --cpus-per-run)")
    names = [n for n, _ in args.grid]
    if len(set(names)) != len(names):
        parser.error("a --grid setting is given twice")
    runs = plan_runs(args.seeds, args.grid, train_argv)
    for run in runs:
        try:
            parse_train_args([*run.argv, "--threads", str(args.cpus_per_run)])
        except SystemExit as stop:  # the training parser printed its one-line error
            if stop.code:
                print(f"{PROG}: error: the training flags of run {run.name} are invalid (above)", file=sys.stderr)
            raise SystemExit(2 if stop.code else 0) from None
    return args, runs


# --------------------------------------------------------------------------- one run

def _read_json(path: Path):
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def run_result(run_dir: Path) -> dict | None:
    """A finished run's results: last validation success and final success per evaluation scenario."""
    final = _read_json(run_dir / "final_eval.json")
    if final is None:
        return None
    recipe = _read_json(run_dir / "recipe.json")  # a recipe: its stages are runs of their own under run_dir
    curve_dir = run_dir / recipe["stages"][-1]["run_dir"] if recipe and recipe.get("stages") else run_dir
    curve = _read_json(curve_dir / "learning_curve.json") or {}
    validations = curve.get("eval_success") or []
    finals = {value["scenario"]: value["success_rate"] for key, value in final.items()
              if key.startswith("evaluation") and isinstance(value, dict) and "success_rate" in value}
    result = {"last_validation_success": validations[-1] if validations else None, "final_success": finals,
              "updates": final.get("updates"), "wall_time_s": final.get("wall_time_s"),
              "selected_snapshot": (final.get("selected_snapshot") or {}).get("updates")}
    exported = final.get("recipe")  # a recipe's export: the whole recipe's updates and its end-to-end wall
    if exported:                     # time, as policy.json's provenance records them (the one source)
        result |= {"updates": sum(stage["updates"] for stage in exported["stages"]),
                   "wall_time_s": exported["wall_time_s"]}
    return result


def train_run(run: SweepRun, run_dir: str, token: str, threads: int) -> dict:
    """Train one run (inside a Ray task or in this process); returns its result and, off the shared
    file system, its files."""
    from sitl.learn.cli import main as train_main

    single_thread()
    target = Path(run_dir)
    shared = _read_text(target.parent / TOKEN_FILE) == token
    scratch = None
    if not shared:
        scratch = Path(tempfile.mkdtemp(prefix="swarmnav-sweep-"))
        target = scratch / target.name
    try:
        try:
            code = train_main([*run.argv, "--run-dir", str(target), "--threads", str(threads)])
        except SystemExit as stop:
            code = stop.code if isinstance(stop.code, int) else 2
        result = {"name": run.name, "returncode": code, "shared": shared, "result": run_result(target)}
        if not shared and target.is_dir():
            result["files"] = {str(p.relative_to(target)): p.read_bytes() for p in sorted(target.rglob("*"))
                               if p.is_file() and p.name not in LEFT_ON_NODE}
        return result
    finally:
        if scratch is not None:
            shutil.rmtree(scratch, ignore_errors=True)


def _read_text(path: Path) -> str | None:
    try:
        return path.read_text()
    except OSError:
        return None


# --------------------------------------------------------------------------- evaluation cells

def add_policy_eval_options(parser: argparse.ArgumentParser) -> None:
    """``--eval``, ``--eval-episodes`` and ``--threads`` of the tools that write one policy file and may fly it
    (``sitl.learn.average``, ``sitl.learn.ensemble``): :func:`fly_policy_cells` reads them."""
    parser.add_argument("--eval", type=eval_cell_list, default=[], metavar="CELLS",
                        help="then fly the written policy in these `sitl.sweep --eval` cells, comma-separated "
                             "(results under OUT's folder/eval/cells)")
    parser.add_argument("--eval-episodes", type=positive_int, default=DEFAULT_EVAL_EPISODES,
                        help=f"episodes per evaluation cell (default: {DEFAULT_EVAL_EPISODES})")
    parser.add_argument("--threads", type=int_range(1, MAX_THREADS), default=2, help="torch threads (default: 2)")


def fly_policy_cells(cells: list[tuple[str, "PaperCell"]], out_dir: Path) -> None:
    """Fly each ``(label, cell)`` (results under ``out_dir/eval/cells``, an identical one reused) and print its success."""
    from sitl.eval.paper import run_cell

    for label, cell in cells:
        summary, status = run_cell(cell, out_dir / "eval", progress=False)
        print(f"{label}: success {summary['success_rate']:.3f} on {summary['episodes']} episodes ({status})",
              flush=True)


def _trained_method(policy: Path) -> str | None:
    """The method recorded in a policy file's provenance; None if the file is missing or unreadable."""
    from companion.policy import PolicyFileError, load_policy

    if not policy.is_file():
        return None
    try:
        return load_policy(policy, check_forward=False).metadata.get("provenance", {}).get("method")
    except PolicyFileError:
        return None  # the cell itself reports the unusable file


def eval_cells(run_dir: Path, labels: list[str], settings: dict[str, "EvalSettings"],
               policy: Path | None = None) -> list[tuple[str, "PaperCell"]]:
    """``(label, cell)`` for each ``--eval`` cell of one run: its policy file (``policy``, default
    ``run_dir/policy.pt``), evaluated as the method that trained it.

    The method is the policy file's own record (a recipe's stages may change method, e.g.
    ``flown-distill`` exports a SAC actor after distilled stages), else the run's config.
    """
    from sitl.eval.paper import PaperCell

    path = str(policy if policy is not None else run_dir / "policy.pt")
    method = _trained_method(Path(path)) or \
        (_read_json(run_dir / "config.json") or {}).get("train", {}).get("method", "sac_ae")
    return [(label, PaperCell(label.replace(":", "-"), method, path, settings[label])) for label in labels]


def _log_eval(run: SweepRun, label: str, summary: dict, status: str) -> None:
    log(f"{run.name} in {label}: success {summary['success_rate']:.3f} on {summary['episodes']} episodes ({status})")


# --------------------------------------------------------------------------- the table

def _stats(values: list[float]) -> dict:
    v = np.asarray([x for x in values if x is not None], dtype=float)
    if not len(v):
        return {"n": 0, "mean": None, "std": None, "spread": None}
    return {"n": int(len(v)), "mean": float(v.mean()), "std": float(v.std(ddof=1)) if len(v) > 1 else 0.0,
            "spread": float(v.max() - v.min())}


def summarize_sweep(runs: list[SweepRun], results: dict[str, dict | None]) -> dict:
    """Per grid point, mean / std / spread over seeds of the last validation, the final successes and
    the ``--eval`` cells' successes."""
    points: dict[str, list[SweepRun]] = {}
    for run in runs:
        points.setdefault(json.dumps(run.grid, sort_keys=True), []).append(run)
    groups = []
    for key, members in points.items():
        done = [results.get(r.name) for r in members if results.get(r.name)]
        scenarios = sorted({s for d in done for s in d["final_success"]})
        groups.append({"grid": json.loads(key), "runs": [r.name for r in members],
                       "last_validation_success": _stats([d["last_validation_success"] for d in done]),
                       "final_success": {s: _stats([d["final_success"].get(s) for d in done]) for s in scenarios},
                       "eval_success": {c: _stats([d.get("eval_success", {}).get(c) for d in done])
                                        for c in _eval_labels(done)}})
    return {"groups": groups}


def _eval_labels(results) -> list[str]:
    """The evaluation cells any of ``results`` was flown in, in the order first met."""
    return list(dict.fromkeys(c for r in results if r for c in r.get("eval_success", {})))


def _fmt(value, digits: int = 3) -> str:
    return "-" if value is None or (isinstance(value, float) and math.isnan(value)) else f"{value:.{digits}f}"


def sweep_markdown(runs: list[SweepRun], results: dict[str, dict | None], summary: dict, train_argv: list[str]) -> str:
    scenarios = sorted({s for r in results.values() if r for s in r["final_success"]})
    cells = _eval_labels(results.values())
    lines = ["# Training sweep", "", f"Generated by `{PROG}`; training flags: `{' '.join(train_argv) or '(defaults)'}`.",
             "Validation: the trainer's last validation (validation seeds); final: the exported networks on the "
             "test seeds (`final_eval.json`)" + ("; `paper:`/`flown:` columns: the policy in that `swarm_test` "
                                                 "cell (held-out test seeds, `<run>/eval/cells/`)." if cells else "."), "",
             "| run | seed | " + " | ".join([*(f"final {s}" for s in scenarios), *cells])
             + " | last validation | updates | wall (min) |",
             "| --- | --- | " + " | ".join("---" for _ in [*scenarios, *cells]) + " | --- | --- | --- |"]
    for run in runs:
        r = results.get(run.name)
        if r is None:
            lines.append(f"| {run.name} | {run.seed} | " + " | ".join("failed" for _ in [*scenarios, *cells])
                         + " | - | - | - |")
            continue
        wall = r["wall_time_s"] / 60 if r.get("wall_time_s") is not None else None
        lines.append(f"| {run.name} | {run.seed} | "
                     + " | ".join([*(_fmt(r["final_success"].get(s)) for s in scenarios),
                                   *(_fmt(r.get("eval_success", {}).get(c)) for c in cells)])
                     + f" | {_fmt(r['last_validation_success'])} | {r['updates']} | {_fmt(wall, 1)} |")
    lines += ["", "Over seeds (mean ± std, spread = max - min):", "",
              "| grid point | runs | " + " | ".join([*(f"final {s}" for s in scenarios), *cells]) + " | last validation |",
              "| --- | --- | " + " | ".join("---" for _ in [*scenarios, *cells]) + " | --- |"]
    for group in summary["groups"]:
        label = ", ".join(f"{k}={v}" for k, v in group["grid"].items()) or "(all)"

        def cell(st: dict) -> str:
            return "-" if not st or not st["n"] else \
                f"{st['mean']:.3f} ± {st['std']:.3f} (spread {st['spread']:.3f}, n={st['n']})"
        lines.append(f"| {label} | {len(group['runs'])} | "
                     + " | ".join([*(cell(group["final_success"].get(s)) for s in scenarios),
                                   *(cell(group["eval_success"].get(c)) for c in cells)])
                     + f" | {cell(group['last_validation_success'])} |")
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------- the sweep

def _store_files(run_dir: Path, files: dict[str, bytes]) -> None:
    for rel, data in files.items():
        path = run_dir / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data)


def run_sweep(out: Path, runs: list[SweepRun], train_argv: list[str], use_ray: bool = True, address: str | None = LOCAL,
              num_cpus: int | None = None, cpus_per_run: int = 1, evals: list[str] | None = None,
              eval_episodes: int = DEFAULT_EVAL_EPISODES) -> dict:
    """Train every run not finished yet (as Ray tasks, or here one after another), fly every finished
    run's policy in the ``evals`` cells not stored yet, then write the tables."""
    from sitl.eval.paper import run_cell, stored_cell

    out.mkdir(parents=True, exist_ok=True)
    token = uuid.uuid4().hex
    (out / TOKEN_FILE).write_text(token)
    settings = evaluation_settings(eval_episodes) if evals else {}
    results: dict[str, dict | None] = {}
    evaluations: dict[str, dict[str, dict]] = {run.name: {} for run in runs}  # run -> cell label -> summary
    todo = []
    for run in runs:
        stored = run_result(out / run.name)
        if stored is not None:
            results[run.name] = stored
            log(f"{run.name}: finished before, reused")
            continue
        if (out / run.name).exists():
            shutil.rmtree(out / run.name)  # an interrupted run starts afresh
        todo.append(run)

    def cells_to_fly(run: SweepRun) -> list[tuple[str, "PaperCell"]]:
        """The run's evaluation cells not stored under its directory yet (the stored ones are taken)."""
        left = []
        for label, cell in eval_cells(out / run.name, evals or [], settings):
            summary = stored_cell(cell, out / run.name / "eval")
            if summary is None:
                left.append((label, cell))
            else:
                evaluations[run.name][label] = summary
                _log_eval(run, label, summary, "stored")
        return left

    reused_cells = {run.name: cells_to_fly(run) for run in runs if run not in todo}
    started = time.perf_counter()
    if use_ray and (todo or any(reused_cells.values())):
        from sitl.eval.paper_ray import write_cell_files, evaluate_cell_task

        ray = connect(address, num_cpus)
        log(f"{describe_cluster(ray)}; {len(todo)} run(s) of {cpus_per_run} CPU(s) each"
            + (f", then {len(evals)} evaluation cell(s) of 1 CPU per run" if evals else ""))
        train_task = ray.remote(num_cpus=cpus_per_run, max_retries=0)(train_run)
        eval_task = ray.remote(num_cpus=1, max_retries=1)(evaluate_cell_task)
        pending: dict = {}

        def submit_cells(run: SweepRun, cells: list[tuple[str, "PaperCell"]]) -> None:
            if cells:
                blob = ray.put((out / run.name / "policy.pt").read_bytes())  # nodes need not see this machine's files
                for label, cell in cells:
                    pending[eval_task.remote(cell, "policy.pt", blob)] = (run, label, cell)

        for run in todo:
            pending[train_task.remote(run, str((out / run.name).resolve()), token, cpus_per_run)] = (run, None, None)
        for run in runs:
            submit_cells(run, reused_cells.get(run.name, []))
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1)
            run, label, cell = pending.pop(ready[0])
            try:
                outcome = ray.get(ready[0])
            except Exception as err:  # noqa: BLE001 - a failed task is one failed entry, not a failed sweep
                what = f"evaluation in {label}" if label else "training"
                log(f"{run.name}: {what} failed on Ray: "
                    f"{str(err).strip().splitlines()[-1] if str(err).strip() else err}")
                if label is None:
                    results[run.name] = None
                continue
            if label is None:
                _collect(out, run, outcome, results, started, len(results), len(runs))
                if results[run.name] is not None:
                    submit_cells(run, cells_to_fly(run))
            else:
                write_cell_files(out / run.name / "eval", cell, outcome["files"])
                evaluations[run.name][label] = outcome["summary"]
                _log_eval(run, label, outcome["summary"], "computed")
    else:
        for run in todo:
            outcome = train_run(run, str((out / run.name).resolve()), token, cpus_per_run)
            _collect(out, run, outcome, results, started, len(results), len(runs))
        for run in runs:
            if results.get(run.name) is None:
                continue
            for label, cell in reused_cells[run.name] if run.name in reused_cells else cells_to_fly(run):
                summary, status = run_cell(cell, out / run.name / "eval", progress=False)
                evaluations[run.name][label] = summary
                _log_eval(run, label, summary, status)
    for name, cells in evaluations.items():
        if results.get(name) is not None and cells:
            results[name] = {**results[name], "eval_success": {label: cells[label]["success_rate"]
                                                               for label in (evals or []) if label in cells}}
    summary = summarize_sweep(runs, results)
    write_json(out / "sweep.json", {"train_argv": train_argv, "evaluation": {"cells": evals or [],
                                                                            "episodes": eval_episodes},
                                    "runs": [{"name": r.name, "seed": r.seed, "grid": r.grid, "argv": list(r.argv),
                                              "result": results.get(r.name)} for r in runs], **summary})
    (out / "sweep.md").write_text(sweep_markdown(runs, results, summary, train_argv))
    plot_sweep(out / "sweep.png", runs, results, summary)
    return {"results": results, **summary}


def plot_sweep(path: Path, runs: list[SweepRun], results: dict[str, dict | None], summary: dict) -> None:
    """``sweep.png``: every finished run's final and evaluation-cell successes, by grid point and seed."""
    from sitl.eval.plots import plot_seed_spread

    by_name = {r.name: r for r in runs}
    columns = {}
    for group in summary["groups"]:
        label = ", ".join(f"{k}={v}" for k, v in group["grid"].items()) or "all runs"
        done = [(by_name[n].seed, results[n]) for n in group["runs"] if results.get(n)]
        names = [*(f"final {s}" for s in group["final_success"]), *group["eval_success"]]
        columns[label] = {name: {seed: value for seed, r in done if (value := _column(r, name)) is not None}
                          for name in names}
    if any(columns.values()):
        plot_seed_spread(columns, path, "success over seeds (python -m sitl.sweep)")


def _column(result: dict, name: str) -> float | None:
    if name.startswith("final "):
        return result["final_success"].get(name[len("final "):])
    return result.get("eval_success", {}).get(name)


def _collect(out: Path, run: SweepRun, outcome: dict, results: dict, started: float, done: int, total: int) -> None:
    run_dir = out / run.name
    if outcome.get("files"):
        _store_files(run_dir, outcome["files"])
    results[run.name] = outcome["result"] if outcome["returncode"] == 0 else None
    what = "failed (exit %s)" % outcome["returncode"] if results[run.name] is None else \
        "final success " + ", ".join(f"{s} {v:.3f}" for s, v in outcome["result"]["final_success"].items())
    log(f"[{done + 1}/{total}] {run.name}: {what} ({(time.perf_counter() - started) / 60:.1f} min into the sweep)")


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    args, runs = parse_args(argv)
    train_argv = argv[argv.index("--") + 1:] if "--" in argv else []
    out = args.out or Path("runs") / f"sweep-{time.strftime('%Y%m%d-%H%M%S')}"
    try:
        result = run_sweep(out, runs, train_argv, args.ray, args.address, args.num_cpus, args.cpus_per_run,
                           args.eval, args.eval_episodes)
    except (RayUnavailable, EvaluationError) as err:  # EvaluationError: a run's policy file cannot be flown
        print(f"error: {err}", file=sys.stderr)
        return 2
    except OSError as err:
        print(f"error: cannot write the sweep directory {out}: {err.strerror or err}", file=sys.stderr)
        return 2
    print((out / "sweep.md").read_text())
    failed = [name for name, r in result["results"].items() if r is None]
    print(f"wrote {out / 'sweep.md'}, {out / 'sweep.json'} and {out / 'sweep.png'}"
          + (f"; failed: {', '.join(failed)}" if failed else ""))
    return 1 if failed else 0
