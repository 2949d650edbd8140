"""``python -m sitl.train``: train the shared collision-avoidance policy (paper Alg. 1).

All UAVs of all simulated worlds act with one policy and feed one replay buffer
(centralised training, decentralised execution). The loop alternates environment steps
and gradient updates; the agent and its equations are in :mod:`sitl.learn.agent`; the loop in :mod:`sitl.learn.trainer`.

Presets (``--preset``):

* ``fast`` (default) — trains on a 2-core laptop in under 2 hours: 32x32 depth, four
  worlds of 8 UAVs stepped together, one update per environment step (32 transitions), a
  fixed budget of updates, initial temperature 0.01 and 5-step returns
  (see ``sitl.learn.config.PRESETS`` for why). Every other hyperparameter is the paper's Table I.
* ``paper`` — Table I literally: one world of 8 UAVs, 200 episodes, 400 updates after
  each episode, replay capacity 20,000, 64x64 depth.
* ``flown`` — a recipe (3 stages in one command): the task as drones fly it, RealSense D435
  camera with noise, 1.5-15 m, obstacles, randomized dynamics, at the paper's 1024 units (~79 min;
  the bundled policy's recipe until 2026-11-25).
* ``flown-fast`` — the same task with 512-unit MLPs, the decoder every second update, a
  UAV-UAV collision at -50 from the third stage on and a fourth stage at learning rates 1e-4
  with half of its episodes circles: 38-40 min on 2 cores, run whole; the bundled policy is its
  seed 0 (docs/training.md, models/README.md).
* ``flown-distill`` — flown-fast's four stages, the first two as the ``distill`` method (a DAgger
  student of privileged ORCA, four times the data per update), the last two as SAC on the student's
  frozen convolutions, still pulled towards the teacher and validated at 40 s; circle worlds are
  taught by camera-limited ORCA that keeps right (``--circle-teacher-right``): 33-36 min on 2 cores until session 67, five
  seeds' paper medium 0.906 within 1.4 points, every circle of 8 at 1.000 (a method beside SAC+AE, issue 17;
  docs/training.md "A circle teacher the camera can explain"). Its final choice leaves out snapshots that
  lose the paper's circle of 14 on validation seeds (a gate, session 43) and flies the others again on 500
  validation episodes of random medium and obstacles (session 67: ~8.5 more minutes, 41 min in all).
* ``bundle-paper`` — a recipe: the paper-camera policy's four-stage curriculum.

Everything is a command-line flag (``--help``); a run directory holds ``config.json``,
TensorBoard logs (``tb/``), ``learning_curve.png``, ``checkpoint.pt`` (``--resume RUN_DIR``
continues from it) and the exported ``policy.pt``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import sys
import time
from dataclasses import fields, replace
from pathlib import Path

from sitl.cli_args import ArgumentParser, finite_float, integer, positive_float, positive_floats
from sitl.learn.agent import AgentConfig
from sitl.learn.config import PRESETS, WHERE_SETTINGS, DeviceUnavailable, TrainConfig, resolve_configs
from sitl.learn.recipe import RECIPE_FILE, Recipe, scaled_stages
from sitl.learn.trainer import make_trainer

PROG = "python -m sitl.train"


def _add_dataclass_flags(parser: argparse.ArgumentParser, cls, title: str, defaults: dict) -> None:
    """One flag per field of ``cls``; ``--help`` shows ``defaults`` (the values a run would use)."""
    group = parser.add_argument_group(title)
    for f in fields(cls):
        if any(a.dest == f.name for a in parser._actions):
            continue  # e.g. method: one flag sets both configs
        flag = "--" + f.name.replace("_", "-")
        kind = {float: finite_float, int: integer}.get(type(f.default), type(f.default))
        help_text = f.metadata.get("help", "") + f" (default: {defaults[f.name]})"
        if type(f.default) is bool:
            group.add_argument(flag, dest=f.name, action=argparse.BooleanOptionalAction, default=argparse.SUPPRESS,
                               help=help_text)
        else:
            group.add_argument(flag, dest=f.name, type=kind, default=argparse.SUPPRESS, help=help_text)


def _preset_of(argv: list[str] | None) -> str:
    """The ``--preset`` of ``argv`` (the default one if absent or unknown: the full parser then reports it)."""
    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--preset", default=TrainConfig.preset)
    known, _ = pre.parse_known_args(argv)
    return known.preset if known.preset in PRESETS else TrainConfig.preset


def build_parser(preset: str = TrainConfig.preset) -> argparse.ArgumentParser:
    """The parser, its help showing ``preset``'s resolved defaults (as CleanRL's dataclass CLIs do)."""
    train_defaults, agent_defaults = resolve_configs({"preset": preset}, {})
    parser = ArgumentParser(prog=PROG, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--resume", metavar="RUN_DIR", default=None,
                        help="continue the run (or recipe) in RUN_DIR from its checkpoint, with the settings "
                             "it was started with; --device and --threads may be given to continue it on "
                             "another machine (e.g. trained on cuda, continued on a CPU)")
    stages = PRESETS[preset].get("stages")
    if stages:
        lines = [f"  stage {i + 1} '{st.name}': {st.description}; "
                 + ", ".join(f"{k}={v}" for k, v in {**st.train, **st.agent}.items()) for i, st in enumerate(stages)]
        lines += [f"  final choice: only snapshots with {g.name} (a {g.num_uavs}-UAV {g.scenario} scene, {g.geometry} "
                  f"geometry, camera noise {'on' if g.camera_noise else 'off'}, validation seeds) >= {g.min_success:g}"
                  for g in stages[-1].gates]
        recipe = PRESETS[preset].get("recipe", {})
        if recipe.get("rescore_top", 0) > 0 and recipe.get("rescore_episodes", 0) > 0:
            lines.append(f"  final choice: the last stage's {recipe['rescore_top']} best snapshots flown again on "
                         f"{recipe['rescore_episodes']} validation episodes each of "
                         f"{', '.join(s[0] for s in stages[-1].rescore_scenes)}; the best mean over the kinds of scene")
        parser.epilog = f"preset {preset} is a recipe of {len(stages)} stages (sitl.learn.recipe):\n" + "\n".join(lines)
    parser.add_argument("--recipe-scale", type=positive_float, default=None, metavar="F",
                        help="recipe presets: multiply every stage's updates and validation interval by F "
                             "(e.g. 0.01 for a quick trial of the whole recipe; default 1)")
    parser.add_argument("--stage-scale", type=positive_floats, default=None, metavar="F1,F2,...",
                        help="recipe presets: one factor per stage on its updates and validation interval, on top "
                             "of --recipe-scale (e.g. 1.5,1.5,1,1: the first two stages half as long again; "
                             "default all 1)")
    _add_dataclass_flags(parser, TrainConfig, f"training (defaults: preset {preset})",
                         dataclasses.asdict(train_defaults))
    _add_dataclass_flags(parser, AgentConfig,
                         f"agent (paper Table I; reference train.py where the paper is silent; defaults: preset {preset})",
                         dataclasses.asdict(agent_defaults))
    return parser


def parse_args(argv: list[str] | None = None) -> tuple[TrainConfig, AgentConfig, str | None, dict]:
    """The two configs (defaults, then the preset, then explicit flags), ``--resume``, and for recipes
    ``{"scale": --recipe-scale or None, "stage_scales": --stage-scale or None, "explicit": the config fields
    given on the command line}``."""
    parser = build_parser(_preset_of(argv))
    args = vars(parser.parse_args(argv))
    resume = args.pop("resume")
    scale = args.pop("recipe_scale")
    stage_scales = args.pop("stage_scale")
    train_names = {f.name for f in fields(TrainConfig)}
    train_args = {k: v for k, v in args.items() if k in train_names}
    agent_args = {k: v for k, v in args.items() if k not in train_names}
    try:
        train_cfg, agent_cfg = resolve_configs(train_args, agent_args)
    except ValueError as err:
        parser.error(str(err))
    if stage_scales is not None:  # checked before a run directory is made
        stages = PRESETS[train_cfg.preset].get("stages")
        if not stages:
            parser.error(f"--stage-scale: preset {train_cfg.preset} is not a recipe (it has no stages)")
        try:
            scaled_stages(stages, 1.0, stage_scales)
        except ValueError as err:
            parser.error(f"--stage-scale: {err} (preset {train_cfg.preset})")
    return train_cfg, agent_cfg, resume, {"scale": scale, "stage_scales": stage_scales,
                                          "explicit": frozenset(train_args) | frozenset(agent_args)}


def default_run_dir(cfg: TrainConfig) -> Path:
    stamp = time.strftime("%Y%m%d-%H%M%S")
    return Path("runs") / f"{cfg.method}-{cfg.scenario}-{cfg.density}-s{cfg.seed}-{stamp}"


def move_run(run_dir: Path, where: dict) -> None:
    """Rewrite the :data:`WHERE_SETTINGS` in ``where`` into the run's config.json and, for a recipe, each
    stage's, so that this resume and every later one computes there."""
    if not where:
        return
    for path in [run_dir / "config.json", *sorted(run_dir.glob("stage*/config.json"))]:
        saved = json.loads(path.read_text())
        saved["train"].update(where)
        path.write_text(json.dumps(saved, indent=2))


def _resume_error(err: Exception) -> str:
    """Why a run's config.json could not be taken up again."""
    if isinstance(err, DeviceUnavailable):  # e.g. trained on cuda, resumed on a laptop
        return f"{err} (give --device cpu to continue it here)"
    return f"its config.json is missing or invalid ({err})"


def _run_recipe(cfg: TrainConfig, agent_cfg: AgentConfig, run_dir: Path, scale: float | None,
                explicit: frozenset[str], stage_scales: list[float] | None = None) -> int:
    """Run (or resume: ``scale`` None) the recipe of ``cfg.preset`` in ``run_dir``."""
    preset = PRESETS[cfg.preset]
    state_path = run_dir / RECIPE_FILE
    if scale is None:  # resuming: as the recipe was started
        state = json.loads(state_path.read_text()) if state_path.is_file() else {}
        scale, explicit = state.get("scale", 1.0), frozenset(state.get("explicit", ()))
        stage_scales = state.get("stage_scales")
    try:  # a recipe.json whose stage scales no longer fit the preset's stages is a one-line error too
        Recipe(cfg, agent_cfg, preset["stages"], run_dir, explicit=explicit, scale=scale,
               stage_scales=stage_scales, **preset.get("recipe", {})).run()
    except (FileNotFoundError, ValueError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    return 0


def main(argv: list[str] | None = None) -> int:
    cfg, agent_cfg, resume, recipe_args = parse_args(argv)
    if resume:
        run_dir = Path(resume)
        others = sorted(recipe_args["explicit"] - set(WHERE_SETTINGS))
        if others:
            print(f"error: --resume continues {run_dir} with the settings in its config.json; only "
                  f"{' and '.join('--' + n for n in WHERE_SETTINGS)} may be given with it, not "
                  f"{', '.join('--' + n.replace('_', '-') for n in others)}", file=sys.stderr)
            return 2
        try:
            move_run(run_dir, {name: getattr(cfg, name) for name in WHERE_SETTINGS if name in recipe_args["explicit"]})
            saved = json.loads((run_dir / "config.json").read_text())
            cfg, agent_cfg = TrainConfig(**saved["train"]), AgentConfig(**saved["agent"])
        except (OSError, ValueError, KeyError, TypeError) as err:
            print(f"error: cannot resume {run_dir}: {_resume_error(err)}", file=sys.stderr)
            return 2
        if "stages" in PRESETS[cfg.preset]:
            return _run_recipe(cfg, agent_cfg, run_dir, None, frozenset())  # each stage resumes from its checkpoint
        if not (run_dir / "checkpoint.pt").is_file():
            print(f"error: {run_dir} has no checkpoint.pt to resume from", file=sys.stderr)
            return 2
    else:
        run_dir = Path(cfg.run_dir) if cfg.run_dir else default_run_dir(cfg)
        if run_dir.exists() and (not run_dir.is_dir() or any(run_dir.iterdir())):
            print(f"error: run directory {run_dir} already exists and is not empty; "
                  f"use --resume {run_dir} to continue it or choose another --run-dir", file=sys.stderr)
            return 2
        try:
            run_dir.mkdir(parents=True, exist_ok=True)
            cfg = replace(cfg, run_dir=str(run_dir))
            (run_dir / "config.json").write_text(json.dumps(
                {"train": dataclasses.asdict(cfg), "agent": dataclasses.asdict(agent_cfg)}, indent=2))
        except OSError as err:
            print(f"error: cannot create the run directory {run_dir}: {err.strerror}", file=sys.stderr)
            return 2
    if "stages" in PRESETS[cfg.preset]:
        return _run_recipe(cfg, agent_cfg, run_dir, recipe_args["scale"] or 1.0, recipe_args["explicit"],
                           recipe_args["stage_scales"])
    try:
        trainer = make_trainer(cfg, agent_cfg, run_dir, resume=bool(resume))
    except (FileNotFoundError, ValueError) as err:
        if not resume:
            shutil.rmtree(run_dir, ignore_errors=True)  # nothing was trained: leave no half-made run behind
        print(f"error: {err}", file=sys.stderr)
        return 2
    trainer.log(f"run directory {run_dir}; replay buffer {trainer.buffer.nbytes / 2**20:.0f} MiB")
    trainer.run()
    return 0
