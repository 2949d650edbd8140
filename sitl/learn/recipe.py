"""A training recipe: curriculum stages, selection and export in one resumable command.

A preset with ``"stages"`` (:data:`sitl.learn.config.PRESETS`) is a recipe: ``python -m
sitl.train --preset NAME`` runs its stages one after the other in one run directory, each
stage a complete training run of its own (``RUN/stage<i>-<name>/``, with its config,
TensorBoard logs, validated snapshots and checkpoint) that starts from the networks the
previous stage selected (``init_from``). After the last stage the best validated snapshots
of that stage that clear its gates (:class:`sitl.learn.config.SelectionGate`; all of them if none does) are flown
again on more validation episodes (:func:`sitl.learn.rescore.rescore_snapshot`),
the winner gets the test-seed evaluation and is exported to ``RUN/policy.pt`` with the whole
recipe in its provenance, including the wall time from the first update to the export.

Nothing is hand-edited between stages: the choices a person used to make (which snapshot
to continue from, rescoring, the final evaluation) are rules written here. ``RUN/recipe.json``
records each finished stage; ``python -m sitl.train --resume RUN`` continues an interrupted
recipe from the stage it was in (that stage from its last checkpoint).
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from sitl.learn.agent import AgentConfig
from sitl.learn.config import RecipeStage, TrainConfig
from sitl.learn.rescore import gate_snapshot, rescore_snapshot, snapshot_actor
from sitl.learn.trainer import gate_cleared, make_trainer, select_snapshot

RECIPE_FILE = "recipe.json"


def scaled_stages(stages: tuple[RecipeStage, ...], scale: float,
                  stage_scales: tuple[float, ...] | None = None,
                  default_eval_episodes: int | None = None) -> tuple[RecipeStage, ...]:
    """The stages with their updates, validation intervals and validation episodes times ``scale`` (>= 1 each).

    A stage that sets no ``eval_episodes`` validates with the run's (``default_eval_episodes``); at a
    ``scale`` other than 1 that number is scaled into the stage too, so that a quick trial validates
    in proportion (``benchmarks/train_time.py`` extrapolates from it).

    ``stage_scales`` (one factor per stage) lengthens or shortens single stages on top of that: their
    updates and validation interval, not their validation episodes (a stage keeps its number of
    validations and what each one costs)."""
    factors = tuple(stage_scales) if stage_scales is not None else (1.0,) * len(stages)
    if len(factors) != len(stages):
        raise ValueError(f"{len(factors)} stage scale(s) for a recipe of {len(stages)} stages")
    if scale == 1.0 and all(f == 1.0 for f in factors):
        return tuple(stages)
    out = []
    for st, factor in zip(stages, factors):
        values = {k: scaled(st.train[k], scale * factor) for k in ("total_updates", "eval_every_updates")
                  if k in st.train}
        if "eval_episodes" in st.train:
            values["eval_episodes"] = scaled(st.train["eval_episodes"], scale)
        elif scale != 1.0 and default_eval_episodes is not None:
            values["eval_episodes"] = scaled(default_eval_episodes, scale)
        out.append(replace(st, train={**st.train, **values}))
    return tuple(out)


def scaled(count: int, scale: float) -> int:
    """``count * scale`` rounded, at least 1 (a quick trial still runs every step once)."""
    return max(1, round(count * scale))


def stage_dir(run_dir: Path, index: int, stage: RecipeStage) -> Path:
    """Where stage ``index`` (0-based) of a recipe trains."""
    return run_dir / f"stage{index + 1}-{stage.name}"


def stage_configs(cfg: TrainConfig, agent_cfg: AgentConfig, stage: RecipeStage, run_dir: Path,
                  init_from: str, explicit: frozenset[str] = frozenset()) -> tuple[TrainConfig, AgentConfig]:
    """The configs of one stage: the recipe's, the stage's overrides, then the rules every stage follows.

    Fields named in ``explicit`` (given on the command line) keep the recipe's value: an explicit
    flag wins over the preset, stages included. Every stage validates and keeps its best
    snapshot (``select_best``); none runs a test-seed evaluation of its own (the recipe runs one
    at the very end).
    """
    train = {k: v for k, v in stage.train.items() if k not in explicit}
    agent = {k: v for k, v in stage.agent.items() if k not in explicit}
    return (replace(cfg, **train, run_dir=str(run_dir), init_from=init_from, select_best=True, final_eval_episodes=0),
            replace(agent_cfg, **agent))


def _write_config(run_dir: Path, cfg: TrainConfig, agent_cfg: AgentConfig) -> None:
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "config.json").write_text(json.dumps(
        {"train": dataclasses.asdict(cfg), "agent": dataclasses.asdict(agent_cfg)}, indent=2))


def _load_state(run_dir: Path) -> dict:
    path = run_dir / RECIPE_FILE
    return json.loads(path.read_text()) if path.is_file() else {"stages": [], "wall_s": 0.0}


def _save_state(run_dir: Path, state: dict) -> None:
    tmp = run_dir / (RECIPE_FILE + ".tmp")
    tmp.write_text(json.dumps(state, indent=2))
    tmp.replace(run_dir / RECIPE_FILE)


def _validation_rows(sdir: Path) -> list[dict]:
    return json.loads((sdir / "snapshots" / "validation.json").read_text())


def _fmt_minutes(seconds: float) -> str:
    return f"{seconds / 60:.1f} min"


class Recipe:
    """Runs (or resumes) the stages of ``cfg.preset`` in ``run_dir``; :meth:`run` returns the exported policy."""

    def __init__(self, cfg: TrainConfig, agent_cfg: AgentConfig, stages: tuple[RecipeStage, ...], run_dir: Path,
                 rescore_top: int, rescore_episodes: int, explicit: frozenset[str] = frozenset(),
                 scale: float = 1.0, log=None, evaluation_steps: int | None = None,
                 stage_scales: tuple[float, ...] | None = None, gate_episodes: int = 100) -> None:
        """``cfg``/``agent_cfg``: the recipe's configs (preset and explicit flags, ``explicit`` naming the
        flags given); ``scale``: multiplies the stages' updates, validation intervals and every
        evaluation's episodes (a quick trial of the whole recipe); ``stage_scales``: one more factor per
        stage on its updates and validation interval (:func:`scaled_stages`); ``final_eval_episodes`` comes from ``cfg``;
        ``evaluation_steps``: the time limit of the rescoring, the gates and the final evaluation (default: the
        training episodes' own); ``gate_episodes``: validation episodes per gate of the last stage."""
        self.cfg, self.agent_cfg, self.run_dir = cfg, agent_cfg, run_dir
        self.stages = scaled_stages(stages, scale, stage_scales, default_eval_episodes=cfg.eval_episodes)
        self.explicit, self.scale = frozenset(explicit), scale
        self.stage_scales = list(stage_scales) if stage_scales is not None else None
        self.rescore_top, self.rescore_episodes = rescore_top, scaled(rescore_episodes, scale)
        self.gate_episodes = scaled(gate_episodes, scale)
        self.evaluation_steps = evaluation_steps
        self.final_eval_episodes = scaled(cfg.final_eval_episodes, scale) if cfg.final_eval_episodes else 0
        self.log = log or (lambda message: print(message, file=sys.stderr, flush=True))
        self.state = _load_state(run_dir)
        self.state.update(scale=scale, explicit=sorted(self.explicit))
        if self.stage_scales is not None:
            self.state["stage_scales"] = self.stage_scales

    # ------------------------------------------------------------------ helpers
    def _elapsed(self) -> float:
        return self.state["wall_s"] + (time.perf_counter() - self._t0)

    def _checkpoint_state(self) -> None:
        self.state["wall_s"] = self._elapsed()
        self._t0 = time.perf_counter()
        _save_state(self.run_dir, self.state)

    def _eta(self, index: int) -> str:
        """Time left, extrapolated from the updates per second of the stages done so far."""
        done = self.state["stages"]
        if not done:
            return "time left: unknown until the first stage ends"
        rate = sum(s["updates"] for s in done) / max(sum(s["wall_s"] for s in done), 1e-9)
        todo = sum(self.stages[i].train.get("total_updates", self.cfg.total_updates)
                   for i in range(index, len(self.stages)))
        return f"time left: ~{_fmt_minutes(todo / max(rate, 1e-9))} at {rate:.2f} updates/s so far"

    # ------------------------------------------------------------------ stages
    def _run_stage(self, index: int, init_from: str) -> dict:
        stage = self.stages[index]
        sdir = stage_dir(self.run_dir, index, stage)
        cfg, agent_cfg = stage_configs(self.cfg, self.agent_cfg, stage, sdir, init_from, self.explicit)
        resume = (sdir / "checkpoint.pt").is_file()
        if resume:  # the stage's own saved config wins: it is what its checkpoint was trained with
            saved = json.loads((sdir / "config.json").read_text())
            cfg, agent_cfg = TrainConfig(**saved["train"]), AgentConfig(**saved["agent"])
        else:
            if sdir.exists():
                shutil.rmtree(sdir)  # started but never checkpointed: nothing worth keeping
            _write_config(sdir, cfg, agent_cfg)
        # The description is the preset's words; say where a flag changed what the stage would set.
        overridden = [f"{k} {getattr(c, k)}" for fields, c in ((stage.train, cfg), (stage.agent, agent_cfg))
                      for k in fields if k in self.explicit]
        flags = f"; from the command line instead: {', '.join(overridden)}" if overridden else ""
        self.log(f"=== stage {index + 1}/{len(self.stages)} '{stage.name}': {stage.description} "
                 f"({cfg.total_updates} updates{', resumed' if resume else ''}{flags}; {self._eta(index)})")
        started = time.perf_counter()
        trainer = make_trainer(cfg, agent_cfg, sdir, resume=resume)
        trainer.name_stage(f"stage {index + 1}/{len(self.stages)} '{stage.name}'")
        trainer.run()
        best = select_snapshot(_validation_rows(sdir))
        record = {"name": stage.name, "description": stage.description, "run_dir": sdir.name,
                  "init_from": init_from, "overrides": {"train": stage.train, "agent": stage.agent},
                  "updates": trainer.counters["updates"], "wall_s": round(time.perf_counter() - started, 1),
                  "selected_updates": best["updates"], "selected_score": best["score"],
                  "snapshot": str(sdir / "snapshots" / f"agent_{best['updates']}.pt")}
        self.log(f"stage {index + 1} done in {_fmt_minutes(record['wall_s'])}: selected the snapshot at "
                 f"{best['updates']} updates (validation success {best['score']:.3f})")
        return record

    def _rescore_last(self) -> None:
        """Fly the last stage's best snapshots again on ``rescore_episodes`` validation episodes per scene."""
        index = len(self.stages) - 1
        sdir = stage_dir(self.run_dir, index, self.stages[index])
        saved = json.loads((sdir / "config.json").read_text())
        cfg, agent_cfg = TrainConfig(**saved["train"]), AgentConfig(**saved["agent"])
        rows = _validation_rows(sdir)
        scenes = self.stages[index].rescore_scenes
        steps = cfg.time_limit(self.evaluation_steps)
        for row in rows:  # a rescoring under other settings (an earlier version of the recipe) is redone
            done = row.get("rescored")
            if done and (done.get("episodes"), done.get("max_episode_steps"), sorted(done["scenes"])) != \
                    (self.rescore_episodes, steps, sorted(s[0] for s in scenes)):
                del row["rescored"]
        # Gates are flown first: a snapshot that fails them cannot be chosen, so it is not flown again.
        ranked = sorted(gate_cleared(rows), key=lambda r: (r["score"], r["updates"]), reverse=True)
        candidates = ranked[:self.rescore_top]
        for row in candidates:
            if "rescored" in row:
                continue  # done before an interruption
            act = snapshot_actor(cfg, agent_cfg, sdir / "snapshots" / f"agent_{row['updates']}.pt")
            row["rescored"] = rescore_snapshot(cfg, act, list(scenes), self.rescore_episodes, self.evaluation_steps)
            cells = ", ".join(f"{name} {r['success_rate']:.3f}" for name, r in row["rescored"]["scenes"].items())
            self.log(f"rescored {row['updates']} updates on {self.rescore_episodes} episodes per scene "
                     f"({row['rescored']['max_episode_steps']} steps): {cells} "
                     f"-> score {row['rescored']['score']:.3f} (training-time {row['score']:.3f})")
            (sdir / "snapshots" / "validation.json").write_text(json.dumps(rows, indent=1))

    def _gate_last(self) -> None:
        """Fly every snapshot of the last stage in its gates' scenes; the final choice skips those that fail."""
        index = len(self.stages) - 1
        gates = self.stages[index].gates if self.gate_episodes > 0 else ()
        sdir = stage_dir(self.run_dir, index, self.stages[index])
        rows = _validation_rows(sdir)
        if not gates:  # a recipe without gates (now): results of earlier gates must not steer its choice
            if any("gate" in row for row in rows):
                for row in rows:
                    row.pop("gate", None)
                (sdir / "snapshots" / "validation.json").write_text(json.dumps(rows, indent=1))
            return
        saved = json.loads((sdir / "config.json").read_text())
        cfg, agent_cfg = TrainConfig(**saved["train"]), AgentConfig(**saved["agent"])
        steps = cfg.time_limit(self.evaluation_steps)
        wanted = (self.gate_episodes, steps, [dataclasses.asdict(g) for g in gates])
        for row in sorted(rows, key=lambda r: r["updates"]):
            done = row.get("gate")
            if done and (done["episodes"], done["max_episode_steps"], done.get("gates")) == wanted:
                continue  # done before an interruption, under these very gates (scene and bar)
            started = time.perf_counter()
            act = snapshot_actor(cfg, agent_cfg, sdir / "snapshots" / f"agent_{row['updates']}.pt")
            row["gate"] = gate_snapshot(cfg, act, list(gates), self.gate_episodes, self.evaluation_steps)
            cells = ", ".join(f"{name} {r['success_rate']:.3f} (bar {r['min_success']:g})"
                              for name, r in row["gate"]["scenes"].items())
            self.log(f"gate: {row['updates']} updates on {self.gate_episodes} validation episodes: {cells} -> "
                     f"{'competes' if row['gate']['passed'] else 'left out of the final choice'} "
                     f"({time.perf_counter() - started:.0f} s)")
            (sdir / "snapshots" / "validation.json").write_text(json.dumps(rows, indent=1))
        if not any(row["gate"]["passed"] for row in rows):
            self.log("gate: no snapshot clears the gates; all of them compete in the final choice")

    def _export(self) -> Path:
        """Test-seed evaluation of the selected snapshot and export, with the recipe in the provenance."""
        index = len(self.stages) - 1
        sdir = stage_dir(self.run_dir, index, self.stages[index])
        saved = json.loads((sdir / "config.json").read_text())
        cfg = replace(TrainConfig(**saved["train"]), final_eval_episodes=self.final_eval_episodes)
        trainer = make_trainer(cfg, AgentConfig(**saved["agent"]), sdir, resume=True)
        self._checkpoint_state()  # the time so far (the rescoring included); the export's evaluation is added below
        recipe = {"preset": self.cfg.preset, "scale": self.scale, "stage_scales": self.stage_scales,
                  "stages": self.state["stages"],
                  "rescore": {"top": self.rescore_top, "episodes": self.rescore_episodes,
                              "scenes": [s[0] for s in self.stages[index].rescore_scenes],
                              "max_episode_steps": cfg.time_limit(self.evaluation_steps)},
                  "gates": {"episodes": self.gate_episodes,
                            "gates": [dataclasses.asdict(g) for g in self.stages[index].gates]},
                  # unrounded: policy.json's wall_time_s is rounded once, from this plus the final evaluation
                  "wall_time_s_before_final_evaluation": self.state["wall_s"]}
        path = trainer.finish(recipe=recipe, evaluation_steps=self.evaluation_steps)
        for name in ("policy.pt", "final_eval.json"):  # the recipe draws its own learning curve
            if (sdir / name).is_file():
                shutil.copyfile(sdir / name, self.run_dir / name)
        return self.run_dir / path.name

    def run(self) -> Path:
        """Every stage not yet done, the rescoring, the final evaluation and the export."""
        self._t0 = time.perf_counter()
        self.state.setdefault("preset", self.cfg.preset)
        final_choice = {"rescore_top": self.rescore_top, "rescore_episodes": self.rescore_episodes,
                        "evaluation_steps": self.evaluation_steps, "final_eval_episodes": self.final_eval_episodes,
                        "rescore_scenes": [s[0] for s in self.stages[-1].rescore_scenes]}
        if self.stages[-1].gates:  # (absent without gates: runs finished before gates existed stay finished)
            final_choice["gates"] = [dataclasses.asdict(g) for g in self.stages[-1].gates]
            final_choice["gate_episodes"] = self.gate_episodes
        if self.state.get("done") and (len(self.state["stages"]) < len(self.stages)
                                       or self.state.get("final_choice") != final_choice):
            # The recipe changed since this run finished (more stages, or another final choice):
            # its rescoring and export are superseded, so the wall time is that of its stages,
            # and what runs now adds to it.
            self.state["wall_s"] = sum(s["wall_s"] for s in self.state["stages"])
            del self.state["done"]
            self.log(f"{self.run_dir}: finished under an earlier version of recipe '{self.cfg.preset}': continuing "
                     f"with its {len(self.stages) - len(self.state['stages'])} new stage(s) and its final choice "
                     f"(earlier export superseded)")
        self.state["final_choice"] = final_choice
        _save_state(self.run_dir, self.state)  # a resume before the first stage ends knows the scale too
        self.log(f"recipe '{self.cfg.preset}': {len(self.stages)} stages, "
                 f"{sum(s.train.get('total_updates', self.cfg.total_updates) for s in self.stages)} updates in all; "
                 f"run directory {self.run_dir}")
        init_from = self.cfg.init_from
        for index in range(len(self.stages)):
            if index < len(self.state["stages"]):
                init_from = self.state["stages"][index]["snapshot"]
                continue
            record = self._run_stage(index, init_from)
            self.state["stages"].append(record)
            self._checkpoint_state()
            init_from = record["snapshot"]
        self._gate_last()
        if self.rescore_top > 0 and self.rescore_episodes > 0:
            self._rescore_last()
        path = self._export()
        # Rounded as policy.json's wall_time_s is, from a later instant: never below it.
        self.state["wall_s"] = round(self._elapsed(), 1)
        self.state["done"] = True
        _save_state(self.run_dir, self.state)
        plot_recipe_curve(self.run_dir, self.stages, self.run_dir / "learning_curve.png")
        self.log(f"recipe done in {_fmt_minutes(self.state['wall_s'])}; wrote {path}")
        return path


def plot_recipe_curve(run_dir: Path, stages: tuple[RecipeStage, ...], path: Path) -> None:
    """The learning curve of all stages end to end against updates, stage boundaries marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 4))
    offset = 0
    for index, stage in enumerate(stages):
        sdir = stage_dir(run_dir, index, stage)
        index_path = sdir / "snapshots" / "validation.json"
        if not index_path.is_file():
            break
        rows = sorted(json.loads(index_path.read_text()), key=lambda r: r["updates"])
        x = offset + np.array([r["updates"] for r in rows])
        ax.plot(x, [r["score"] for r in rows], "o-", color=f"C{index % 10}", label=f"{index + 1}: {stage.name}")
        rescored = [(offset + r["updates"], r["rescored"]["score"]) for r in rows if "rescored" in r]
        if rescored:
            ax.plot(*zip(*rescored), "k*", ms=10, label="rescored")
        if index:
            ax.axvline(offset, color="grey", ls="--", lw=1)
        offset = int(x.max()) if len(x) else offset
    ax.set_xlabel("gradient updates (all stages)")
    ax.set_ylabel("validation success")
    ax.set_ylim(0, 1.02)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="lower right")
    ax.set_title(f"recipe {run_dir.name}: validation success per stage")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
