"""The training loop (paper Alg. 1) and the factories that build its parts (``make_*``).

All UAVs of all simulated worlds act with one policy and feed one replay buffer
(centralised training, decentralised execution). :func:`make_trainer` builds the
environment, the VAE (method ``vae``: trained here, before the trainer exists), the agent
and the buffer; :class:`Trainer` runs the loop, validates, checkpoints and exports.
The agent and its equations are in :mod:`sitl.learn.agent`; the command line is
``python -m sitl.train`` (:mod:`sitl.learn.cli`).
"""

from __future__ import annotations

import json
import math
import os
import pickle
import sys
import time
import warnings
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
import torch

from companion.governor import GOVERNOR_PRESETS, GovernorSpec
from companion.spec import DEFAULT_ACTION_SPEC, TaskSpec, state_dim_for
from sitl.learn.agent import AgentConfig, SacAeAgent
from sitl.learn.buffer import FrameReplayBuffer
from sitl.learn.config import TrainConfig, evaluation_scenarios, make_sim_config
from sitl.learn.export import export_policy
from sitl.learn.privileged import PRIVILEGED_NEIGHBOURS, env_privileged_features
from sitl.learn.progress import Progress
from sitl.sim.config import RewardConfig, SimConfig
from sitl.sim.env import SwarmEnv
from sitl.sim.episodes import ActorFactory, SwarmGovernor, depth_state_actor, governed_actor, run_episodes
from sitl.sim.metrics import summarize
from sitl.sim.scenarios import EVAL_SEED_OFFSET, VALIDATION_SEED_OFFSET

#: Evaluation episodes flown at once as parallel worlds (as ``swarm_test --batch``).
EVAL_BATCH_WORLDS = 100


def evaluate_scenario(make_actor: ActorFactory, cfg: TrainConfig, scenario_name: str, episodes: int,
                      seed: int) -> dict:
    """Summary of ``episodes`` episodes of ``cfg``'s worlds in one scenario, up to ``EVAL_BATCH_WORLDS`` at a time.

    The episodes are ``swarm_test``'s starts and goals for the same seed and scenario
    (:func:`sitl.sim.episodes.run_episodes`), flown with ``cfg.max_episode_steps`` as the time
    limit (the trainer's, 200 steps by default; ``swarm_test`` flies 400).
    """
    sim_config = make_sim_config(cfg, min(episodes, EVAL_BATCH_WORLDS), scenario_name=scenario_name)
    return summarize(run_episodes(make_actor, sim_config, seed, episodes))


def agent_actor(agent: SacAeAgent, governor: GovernorSpec | None = None) -> ActorFactory:
    """The factory of a training agent's deterministic actor (with the speed ``governor`` after it, if given)."""
    plain = depth_state_actor(lambda depth, state: agent.act(depth, state, explore=False))
    if governor is None:
        return plain
    return lambda env: governed_actor(plain(env), governor, env)


def train_governor(cfg: TrainConfig) -> GovernorSpec | None:
    """The speed governor a run trains with (``--governor``, ``--governor-setting``), or none."""
    return GOVERNOR_PRESETS[cfg.governor_setting] if cfg.governor else None


def flight_governor(cfg: TrainConfig) -> GovernorSpec | None:
    """The speed governor a run's policy flies with, or none: ``--flight-governor-setting`` if given, else the
    training one. Validation, the selection gates, the final evaluation and the exported file use it; only the
    training rollouts fly :func:`train_governor`'s."""
    if not cfg.governor:
        return None
    return GOVERNOR_PRESETS[cfg.flight_governor_setting or cfg.governor_setting]


def plot_learning_curve(history: dict, path: Path, title: str) -> None:
    """Paper Fig. 4 style: average episode reward (and success rate) against episodes.

    Where the history holds several stages (``history["stages"]``: runs started with
    ``--init-from``), a dashed line marks where each began, with its name.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    episodes = np.asarray(history["episode"])
    fig, (ax_r, ax_s) = plt.subplots(2, 1, figsize=(7, 6), sharex=True)
    for key, ax, label in (("return", ax_r, "average reward per UAV"), ("success", ax_s, "success rate")):
        values = np.asarray(history[key], dtype=float)
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        if len(values) == 0:
            ax.text(0.5, 0.5, "no finished episode yet", ha="center", transform=ax.transAxes)
            continue
        window = max(1, min(50, len(values) // 10))
        smooth = np.convolve(values, np.ones(window) / window, mode="valid")
        ax.plot(episodes, values, color="tab:green", alpha=0.25, lw=0.8)
        ax.plot(episodes[window - 1:], smooth, color="tab:green", lw=2)
    if history.get("eval_episode"):
        ax_s.plot(history["eval_episode"], history["eval_success"], "o-", color="tab:blue", label="evaluation")
        ax_s.legend()
    stages = history.get("stages") or []
    for stage in stages[1:] if len(stages) > 1 else []:
        for ax in (ax_r, ax_s):
            ax.axvline(stage["episode"], color="grey", ls="--", lw=1)
    if len(stages) > 1:
        for stage in stages:
            ax_r.annotate(stage["name"], (stage["episode"], 1.0), xycoords=("data", "axes fraction"),
                          xytext=(3, -3), textcoords="offset points", va="top", fontsize=8, color="dimgrey")
    ax_s.set_xlabel("episode" + (" (all stages)" if len(stages) > 1 else ""))
    ax_r.set_title(title)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


STAGE_COUNTERS = ("updates", "env_steps", "transitions", "episodes", "wall_s")


def add_counters(counters: dict, earlier: dict) -> dict:
    """A run's counters plus those of the stages it started from (provenance of curricula)."""
    return {n: counters[n] + earlier.get(n, 0) for n in STAGE_COUNTERS}


def load_training_file(path: Path, weights_only: bool = True):
    """A checkpoint or snapshot of training, its tensors on the CPU whatever device wrote it, so that a run
    started with ``--device cuda`` goes on, is rescored and averaged on a CPU machine (``load_state_dict``
    then moves the tensors to the agent's device)."""
    return torch.load(path, weights_only=weights_only, map_location="cpu")


def _run_method(run_dir: Path) -> str | None:
    """The learning method a run directory was trained with (its config.json), None if it has none."""
    try:
        return json.loads((run_dir / "config.json").read_text())["agent"]["method"]
    except (OSError, ValueError, KeyError, TypeError):
        return None


def snapshot_counters(snapshot: Path) -> dict:
    """Training that went into a validated snapshot ``RUN/snapshots/agent_<updates>.pt``.

    Updates and wall time come from the snapshot's row in ``validation.json``; so do
    environment steps, transitions and episodes where the row records them (rows written
    before it did get them scaled from the run's totals by the update count).
    """
    run_dir = snapshot.parent.parent
    try:
        rows = json.loads((snapshot.parent / "validation.json").read_text())
        ckpt = load_training_file(run_dir / "checkpoint.pt", weights_only=False)
        row = next(r for r in rows if snapshot.name == f"agent_{r['updates']}.pt")
    except (OSError, ValueError, StopIteration) as err:
        raise ValueError(f"--init-from {snapshot}: not a snapshot of a run directory with its "
                         f"validation.json and checkpoint.pt ({err})") from None
    total = ckpt["counters"]
    share = row["updates"] / max(total["updates"], 1)
    counters = {"updates": row["updates"], "wall_s": row["wall_s"],
                **{n: row.get("counters", {}).get(n, round(total[n] * share))
                   for n in ("env_steps", "transitions", "episodes")}}
    return add_counters(counters, ckpt.get("initial_stage", {}))


def snapshot_score(row: dict) -> float:
    """A validated snapshot's score: the ``sitl.rescore`` one where present, else the training-time one."""
    return row["rescored"]["score"] if "rescored" in row else row["score"]


def gate_cleared(rows: list[dict]) -> list[dict]:
    """The rows of ``validation.json`` that cleared the recipe's gates (``"gate"``,
    :class:`sitl.learn.config.SelectionGate`; a row never gated counts as cleared), or all of them if none did."""
    return [row for row in rows if row.get("gate", {}).get("passed", True)] or rows


def select_snapshot(rows: list[dict]) -> dict:
    """The best row of ``validation.json``; rescored rows (``sitl.rescore``) compete only among themselves, and
    of those, only the ones that cleared the recipe's gates unless none did (:func:`gate_cleared`)."""
    rescored = [row for row in rows if "rescored" in row]
    return max(gate_cleared(rescored or rows), key=lambda row: (snapshot_score(row), row["updates"]))


def earlier_history(path: Path, episodes: int) -> dict:
    """The learning curve of the run a stage starts from (``--init-from``), up to its first ``episodes``.

    Empty when that run has no readable checkpoint history (then the curve starts with this stage).
    """
    run_dir = path.parent if path.name == "checkpoint.pt" else path.parent.parent
    try:
        history = load_training_file(run_dir / "checkpoint.pt", weights_only=False)["history"]
    except Exception:  # noqa: BLE001 - the curve is a convenience; training goes on without it
        return {}
    keep = sum(1 for e in history.get("episode", []) if e <= episodes)
    keep_eval = sum(1 for e in history.get("eval_episode", []) if e <= episodes)
    out = {k: list(history.get(k, []))[:keep] for k in ("episode", "return", "success")}
    out |= {k: list(history.get(k, []))[:keep_eval] for k in ("eval_episode", "eval_success", "eval_spl")}
    out["stages"] = [s for s in history.get("stages", []) if s["episode"] <= episodes]
    return out


def _atomic_save(obj, path: Path) -> None:
    tmp = path.with_suffix(".tmp")
    torch.save(obj, tmp)
    os.replace(tmp, path)  # a run killed mid-save keeps its previous checkpoint


def make_agent(agent_cfg: AgentConfig, sim_config: SimConfig, device: str = "cpu",
               vae_encoder: torch.nn.Module | None = None) -> SacAeAgent:
    """The agent of ``agent_cfg`` for ``sim_config``'s camera.

    Method ``vae`` without a trained ``vae_encoder`` gets a blank one, whose weights a
    checkpoint or snapshot then loads.
    """
    cam = sim_config.camera
    if agent_cfg.method == "vae" and vae_encoder is None:
        from sitl.learn.vae import VAEEncoder

        vae_encoder = VAEEncoder(cam.frames, cam.height, cam.width, agent_cfg.latent_dim)
    return SacAeAgent(agent_cfg, cam, DEFAULT_ACTION_SPEC, device, vae_encoder, memory=sim_config.memory)


# --------------------------------------------------------------------------- the loop

def make_env(cfg: TrainConfig) -> SwarmEnv:
    """The training worlds of ``cfg`` (``cfg.num_worlds`` of them, seeded with ``cfg.seed``)."""
    return SwarmEnv(make_sim_config(cfg, cfg.num_worlds), seed=cfg.seed)


def data_scale(cfg: TrainConfig) -> float:
    """How many times the labelled transitions per update (and the buffer) this run collects: ``distill_data_scale``
    for the ``distill`` method, 1 for the others."""
    return cfg.distill_data_scale if cfg.method == "distill" else 1.0


def make_buffer(cfg: TrainConfig, env: SwarmEnv, privileged_dim: int = 0) -> FrameReplayBuffer:
    """The replay buffer for ``env``'s UAVs and camera (``privileged_dim``: an asymmetric critic's extra input)."""
    cam = env.config.camera
    return FrameReplayBuffer(round(cfg.replay_capacity * data_scale(cfg)), env.num_agents, cam.frames, cam.height, cam.width,
                             state_dim_for(env.config.memory), DEFAULT_ACTION_SPEC.dim, seed=cfg.seed,
                             privileged_dim=privileged_dim,
                             frame_ages=cam.stack_ages, precollision_steps=cfg.precollision_steps)


def make_trainer(cfg: TrainConfig, agent_cfg: AgentConfig, run_dir: Path, resume: bool = False) -> "Trainer":
    """Build a run's parts in order — environment, VAE (method ``vae``, trained now unless resuming:
    the checkpoint holds it), agent, buffer — then the :class:`Trainer` that runs them."""
    torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.seed)  # before any network is built: the same seed gives the same run
    env = make_env(cfg)
    vae_encoder = None
    if agent_cfg.method == "vae" and not resume:
        from sitl.learn.vae_data import make_vae_encoder

        vae_encoder = make_vae_encoder(env.config, cfg.seed, cfg.vae_images, cfg.vae_epochs, cfg.vae_policy,
                                       log=Trainer.log)
    agent = make_agent(agent_cfg, env.config, cfg.device, vae_encoder)
    return Trainer(cfg, agent_cfg, run_dir, env, agent, make_buffer(cfg, env, agent.privileged_dim), resume=resume)


class Trainer:
    """One training run's loop: acting, learning, validation, logs, checkpoints and export.

    Its parts are built beforehand (:func:`make_trainer`); constructing it only restores a
    checkpoint (``resume``) or another run's networks (``cfg.init_from``).
    """

    def __init__(self, cfg: TrainConfig, agent_cfg: AgentConfig, run_dir: Path, env: SwarmEnv, agent: SacAeAgent,
                 buffer: FrameReplayBuffer, resume: bool = False) -> None:
        self.cfg, self.agent_cfg, self.run_dir = cfg, agent_cfg, run_dir
        self.env, self.agent, self.buffer = env, agent, buffer
        self.sim_config = env.config
        self.counters = {"env_steps": 0, "transitions": 0, "episodes": 0, "updates": 0, "wall_s": 0.0,
                         "update_credit": 0.0}
        #: The learning curve; its episode axis counts the episodes of earlier stages too, and
        #: ``stages`` lists where each stage began (``name``, ``episode``, ``updates``).
        self.history: dict[str, list] = {"episode": [], "return": [], "success": [], "eval_episode": [],
                                         "eval_success": [], "eval_spl": [], "stages": []}
        from torch.utils.tensorboard import SummaryWriter

        self.writer = SummaryWriter(str(run_dir / "tb"))
        #: privileged ORCA (it sees every UAV and the obstacles) labels the actions: teacher-guided SAC+AE
        #: (``teacher_bc_weight`` > 0) or the ``distill`` method
        self.teacher = None
        #: ``circle_teacher_right``: the circle worlds' teacher (camera-limited ORCA keeping right)
        self.circle_teacher = None
        self.distill = agent_cfg.method == "distill"
        if cfg.teacher_bc_weight > 0 or self.distill:
            from sitl.eval.orca import OrcaController, OrcaParams

            params = OrcaParams(time_horizon_s=cfg.teacher_time_horizon_s, radius_margin_m=cfg.teacher_radius_margin_m)
            try:
                self.teacher = OrcaController.for_env(env, params, camera_limited=cfg.teacher_camera_limited,
                                                      see_obstacles=True)
                if cfg.circle_teacher_right:
                    right = OrcaParams(right_hand_deg=cfg.circle_teacher_right_deg)
                    self.circle_teacher = OrcaController.for_env(env, right, camera_limited=True)
            except ImportError as err:  # the binding has wheels for Linux x86_64 only
                flag = "--method distill" if self.distill else "--teacher-bc-weight"
                raise ValueError(f"{flag}: {err}") from None
        #: counters of the run this one started from (``init_from``), for the provenance
        self.initial_stage: dict = {}
        if resume:
            try:
                ckpt = load_training_file(run_dir / "checkpoint.pt", weights_only=False)
            except (OSError, RuntimeError, EOFError, pickle.UnpicklingError) as err:
                raise ValueError(f"cannot resume: {run_dir / 'checkpoint.pt'} is not a readable checkpoint "
                                 f"({str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__})") from None
            self._restore(ckpt)
        elif cfg.init_from:
            self._init_from(Path(cfg.init_from))
        if not resume:
            self.history.setdefault("stages", []).append(
                {"name": self._stage_name(), "episode": self.initial_stage.get("episodes", 0),
                 "updates": self.initial_stage.get("updates", 0)})

    @staticmethod
    def log(message: str) -> None:
        print(message, file=sys.stderr, flush=True)

    # -------------------------------------------------------------- checkpoints
    def save_checkpoint(self) -> None:
        _atomic_save({
            "agent": self.agent.checkpoint(), "buffer": self.buffer.state_dict(), "counters": dict(self.counters),
            "history": self.history, "env_rng": self.env.rng.bit_generator.state,
            "torch_rng": torch.get_rng_state(), "initial_stage": self.initial_stage,
        }, self.run_dir / "checkpoint.pt")
        plot_learning_curve(self.history, self.run_dir / "learning_curve.png", self._title())
        # The curve's numbers beside its picture (python -m sitl.sweep reads the last validation from it).
        (self.run_dir / "learning_curve.json").write_text(json.dumps(self.history))

    def _restore(self, ckpt: dict) -> None:
        self.agent.restore(ckpt["agent"])
        self.buffer.load_state_dict(ckpt["buffer"])
        self.counters = ckpt["counters"]
        self.history = ckpt["history"]
        self.env.rng.bit_generator.state = ckpt["env_rng"]
        torch.set_rng_state(ckpt["torch_rng"])
        self.initial_stage = ckpt.get("initial_stage", {})
        self.log(f"resumed from {self.run_dir / 'checkpoint.pt'}: {self.counters['updates']} updates, "
                 f"{self.counters['episodes']} episodes")

    def _init_from(self, path: Path) -> None:
        """Start from another run's networks; buffer and counters start afresh.

        ``path`` is a run directory or its ``checkpoint.pt`` (networks, optimiser states and
        temperature at the end of that run) or one of its validated snapshots
        ``snapshots/agent_<updates>.pt`` (networks and temperature; optimisers start afresh).
        Either way this run's learning rates apply.
        """
        if path.is_dir():
            path = path / "checkpoint.pt"
        if not path.is_file():
            raise FileNotFoundError(f"--init-from {path}: no such checkpoint")
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # torch.load's note on TorchScript archives: refused below
                ckpt = load_training_file(path, weights_only=False)
        except Exception as err:  # noqa: BLE001 - any unreadable file gets the same clear refusal
            raise ValueError(f"--init-from {path}: not a readable training checkpoint ({err})") from None
        if not isinstance(ckpt, dict):
            raise ValueError(f"--init-from {path}: not a training checkpoint or snapshot but a "
                             f"{type(ckpt).__name__} (an exported policy.pt cannot be trained further; "
                             "pass the run directory it came from)")
        is_snapshot = "agent" not in ckpt
        source = _run_method(path.parent.parent) if is_snapshot else ckpt["agent"].get("method", _run_method(path.parent))
        handover = self.agent_cfg.method != "distill" and source == "distill"
        try:
            if is_snapshot:
                self.agent.load_state_dict(ckpt)
            elif handover:  # another method's optimisers (the student's trained its convolutions): networks only
                self.agent.load_state_dict(ckpt["agent"]["model"])
            else:
                self.agent.restore(ckpt["agent"])
        except (RuntimeError, KeyError, ValueError, TypeError) as err:
            raise ValueError(f"--init-from {path}: its networks do not match this run's agent settings "
                             f"(method, hidden_dim, image_size, privileged_critic, ...): {str(err)[:300]}") from None
        self.agent.apply_learning_rates()
        if handover:
            # A distilled student hands over to reinforcement learning: its critic was never trained,
            # and its target critic still holds the initial weights (the convolutions included).
            self.agent.copy_critic_to_target()
            self.log(f"{path}: a distilled student, handed over to {self.agent_cfg.method}; its target critic "
                     "starts as its critic")
        self.initial_stage = snapshot_counters(path) if is_snapshot else \
            add_counters(ckpt["counters"], ckpt.get("initial_stage", {}))  # that run may itself be a later stage
        # The curve goes on from the earlier stages' (theirs up to the networks taken from them).
        earlier = earlier_history(path, self.initial_stage["episodes"])
        if not earlier.get("stages"):  # that run kept no stage marks: it was one stage
            earlier["stages"] = [{"name": f"stage 1: {path.parent.name if path.name == 'checkpoint.pt' else path.name}",
                                  "episode": 0, "updates": 0}]
        self.history |= earlier
        self.log(f"initialised from {path}: {self.initial_stage['updates']} updates, "
                 f"{self.initial_stage['wall_s'] / 60:.1f} min of training")

    def _title(self) -> str:
        c = self.cfg
        return f"{c.method}, {c.scenario} {c.density}, N={c.num_uavs}"

    def _stage_name(self) -> str:
        """``stage 2: mixed medium`` (a run with earlier stages) or ``random medium``."""
        c = self.cfg
        number = len(self.history.get("stages", [])) + 1
        what = f"{c.scenario} {c.density}" + (f", lr {self.agent_cfg.actor_lr:g}" if number > 1 else "")
        return f"stage {number}: {what}" if number > 1 else what

    def name_stage(self, name: str) -> None:
        """Call this run's stage ``name`` on the curve and in the progress display (e.g. a recipe's
        ``stage 2/3 'circles'``) instead of the name made from its scenario."""
        if self.history.get("stages"):
            self.history["stages"][-1]["name"] = name

    def stage_label(self) -> str:
        """What the progress display calls this run: its directory and stage (``s0 | stage 2: ...``)."""
        stages = self.history.get("stages") or [{"name": self._title()}]
        return f"{self.run_dir.name} | {stages[-1]['name']}"

    # -------------------------------------------------------------- helpers
    def _recipe_updates(self) -> int:
        """Updates so far, counted from a recipe's first stage (earlier stages included)."""
        return self.counters["updates"] + self.initial_stage.get("updates", 0)

    def teacher_weight(self) -> float:
        """The behaviour-cloning weight at this update: ``teacher_bc_weight`` falling linearly to 0 over
        ``teacher_bc_updates`` updates counted from the recipe's first stage (earlier stages included);
        1 throughout for the ``distill`` method, whose every update is the teacher's."""
        cfg = self.cfg
        if self.distill:
            return 1.0
        if cfg.teacher_bc_weight <= 0 or not cfg.teacher_bc_updates:
            return cfg.teacher_bc_weight
        return cfg.teacher_bc_weight * max(0.0, 1.0 - self._recipe_updates() / cfg.teacher_bc_updates)

    def dagger_beta(self) -> float:
        """``distill``: the share of UAVs that fly the teacher's command this step, 1 falling linearly to 0
        over ``dagger_beta_updates`` updates of the recipe (DAgger's beta; 0 for the other methods)."""
        if not self.distill or not self.cfg.dagger_beta_updates:
            return 0.0
        return max(0.0, 1.0 - self._recipe_updates() / self.cfg.dagger_beta_updates)

    def teacher_commands(self) -> np.ndarray | None:
        """The teacher's physical commands [M, 3] for every UAV now; None once the teacher's weight is 0."""
        if self.teacher is None or self.teacher_weight() <= 0:
            return None
        env = self.env
        if self.circle_teacher is None:
            return self.teacher.act_env(env)
        # Each world solved by one teacher only: privileged ORCA outside circle worlds, the circle teacher in them.
        circle = np.repeat(env.world_is_circle, env.uavs_per_world) & env.acting
        commands = self.teacher.act_env(env, acting=env.acting & ~circle)
        if circle.any():
            commands[circle] = self.circle_teacher.act_env(env, acting=circle)[circle]
        return commands

    def teacher_labels(self, rows: np.ndarray, commands: np.ndarray | None) -> tuple[np.ndarray | None, np.ndarray | None]:
        """The teacher's unit actions for the acting ``rows`` and where they hold: everywhere for
        ``distill`` or with the circle teacher, else outside circle worlds (teacher-guided SAC: privileged ORCA's
        circle manoeuvre depends on UAVs the camera does not see, and the student imitating it failed the
        circle, docs/training.md)."""
        if commands is None:
            return None, None
        env = self.env
        action = self.agent.to_unit_action(commands[rows])
        if self.distill or self.circle_teacher is not None:
            return action, np.ones(len(rows), dtype=bool)
        return action, ~np.repeat(env.world_is_circle, env.uavs_per_world)[rows]

    def finished(self) -> bool:
        c, k = self.cfg, self.counters
        return (c.total_updates > 0 and k["updates"] >= c.total_updates) or \
               (c.max_episodes > 0 and k["episodes"] >= c.max_episodes)

    def evaluate(self, episodes: int, seed_offset: int = EVAL_SEED_OFFSET,
                 max_episode_steps: int | None = None) -> dict[str, dict]:
        """Deterministic evaluation on unseen seeds (test seeds by default), one summary per evaluation scenario,
        with the training episodes' time limit unless ``max_episode_steps`` is given."""
        cfg = replace(self.cfg, max_episode_steps=self.cfg.time_limit(max_episode_steps))
        make_actor = agent_actor(self.agent, flight_governor(cfg))
        return {name: evaluate_scenario(make_actor, cfg, name, episodes, seed_offset + cfg.seed)
                for name in evaluation_scenarios(cfg)}

    def validate(self, write=print) -> None:
        """Evaluate on the validation seeds, log it, and keep a snapshot when selecting the best."""
        cfg, k = self.cfg, self.counters
        summaries = self.evaluate(cfg.eval_episodes, VALIDATION_SEED_OFFSET, max_episode_steps=cfg.validation_time_limit())
        if cfg.select_best:
            self._keep_snapshot(summaries)
        self.history["eval_episode"].append(self._episode_offset() + k["episodes"])
        # The curve shows the mean over the evaluation scenarios; TensorBoard each one.
        self.history["eval_success"].append(float(np.mean([s["success_rate"] for s in summaries.values()])))
        self.history["eval_spl"].append(float(np.mean([s["spl"] for s in summaries.values()])))
        for name, summary in summaries.items():
            suffix = "" if len(summaries) == 1 else f"_{name}"
            self.writer.add_scalar(f"eval/success_rate{suffix}", summary["success_rate"], k["updates"])
            self.writer.add_scalar(f"eval/spl{suffix}", summary["spl"], k["updates"])
            write(f"validation @ {k['updates']} updates ({k['episodes']} training episodes), {name} "
                  f"({cfg.eval_episodes} episodes): success {summary['success_rate']:.3f}, SPL {summary['spl']:.3f}")

    def _episode_offset(self) -> int:
        """Episodes of the earlier stages: the curve's episode axis runs on across stages."""
        return self.initial_stage.get("episodes", 0)

    def _validated_updates(self) -> set[int]:
        index_path = self.run_dir / "snapshots" / "validation.json"
        return {row["updates"] for row in json.loads(index_path.read_text())} if index_path.exists() else set()

    def _keep_snapshot(self, summaries: dict[str, dict]) -> None:
        """Save the networks with their validation result (``select_best``)."""
        folder = self.run_dir / "snapshots"
        folder.mkdir(exist_ok=True)
        updates = self.counters["updates"]
        score = float(np.mean([s["success_rate"] for s in summaries.values()]))
        torch.save(self.agent.state_dict(), folder / f"agent_{updates}.pt")
        index_path = folder / "validation.json"
        index = json.loads(index_path.read_text()) if index_path.exists() else []
        index = [row for row in index if row["updates"] != updates]
        counters = {n: self.counters[n] for n in ("env_steps", "transitions", "episodes")}
        index.append({"updates": updates, "wall_s": round(time.perf_counter() - self._started, 1), "score": score,
                      "counters": counters, "max_episode_steps": self.cfg.validation_time_limit(),
                      **{name: {"success_rate": s["success_rate"], "spl": s["spl"]} for name, s in summaries.items()}})
        index_path.write_text(json.dumps(index, indent=1))

    def _restore_best_snapshot(self) -> dict | None:
        """Load the best validated networks into the agent; returns that snapshot's row."""
        index_path = self.run_dir / "snapshots" / "validation.json"
        if not index_path.exists():
            return None
        best = select_snapshot(json.loads(index_path.read_text()))
        self.agent.load_state_dict(load_training_file(self.run_dir / "snapshots" / f"agent_{best['updates']}.pt"))
        how = "rescored" if "rescored" in best else "validation success"
        self.log(f"selected the snapshot at {best['updates']} updates ({how} {snapshot_score(best):.3f})")
        return best

    # -------------------------------------------------------------- main loop
    def run(self) -> Path:
        cfg, env, agent, buffer, k = self.cfg, self.env, self.agent, self.buffer, self.counters
        obs = env.reset()
        everyone = np.arange(env.num_agents)
        buffer.start_episodes(everyone, obs.depth[:, -1])
        returns = np.zeros(env.num_agents)
        low, high = env.action_spec.low_array(), env.action_spec.high_array()
        rng = np.random.default_rng(cfg.seed + k["env_steps"])
        spec = train_governor(cfg)
        govern = SwarmGovernor(env, spec) if spec is not None else None
        total = cfg.total_updates if cfg.total_updates > 0 else cfg.max_episodes
        unit = "update" if cfg.total_updates > 0 else "episode"
        # A bar on a terminal, a plain line a minute elsewhere (CI logs, Ray workers): see sitl.learn.progress.
        bar = Progress(total, k["updates"] if unit == "update" else k["episodes"], unit, self.stage_label())
        if self.history["eval_success"]:
            bar.set_fields(val=f"{self.history['eval_success'][-1]:.2f}")
        started = self._started = time.perf_counter() - k["wall_s"]
        last_ckpt = time.perf_counter()
        next_eval = (k["updates"] // cfg.eval_every_updates + 1) * cfg.eval_every_updates if cfg.eval_every_updates else math.inf
        window_t, window_steps, window_updates = time.perf_counter(), 0, 0
        latest_losses: dict[str, float] = {}
        credit_per_step = cfg.updates_per_env_step / data_scale(cfg)  # updates earned by one environment step

        while not self.finished():
            acting = env.acting.copy()
            rows = np.flatnonzero(acting)
            commands = self.teacher_commands()  # for the observation acted on
            if self.distill:
                # DAgger: the student flies its own (deterministic) command, except a beta share of the UAVs
                # that fly the teacher's; either way the replay keeps the teacher's label for the observation.
                action = agent.act(obs.depth, obs.state, explore=False)
                teach = rng.random(env.num_agents) < self.dagger_beta()
                action[teach] = commands[teach]
            elif k["transitions"] < cfg.init_steps and not cfg.init_from:
                action = rng.uniform(low, high, size=(env.num_agents, env.action_spec.dim)).astype(np.float32)
            else:
                action = agent.act(obs.depth, obs.state, explore=True)
            state = obs.state
            # The governor is part of the environment here: the UAVs fly the governed commands and the
            # replay keeps the policy's own (its critic learns what a command is worth with the governor after it).
            executed = govern(obs, action) if govern is not None else action
            teacher_action, teacher_valid = self.teacher_labels(rows, commands)
            privileged = env_privileged_features(env)[rows] if agent.privileged_dim else None
            obs, reward, terminated, truncated, info = env.step(executed)
            next_privileged = env_privileged_features(env)[rows] if agent.privileged_dim else None
            buffer.add(rows, state[rows], agent.to_unit_action(action[rows]), reward[rows], obs.depth[rows, -1],
                       obs.state[rows], terminated[rows], teacher_action, teacher_valid, privileged, next_privileged,
                       collided=info["collided"][rows])
            returns += reward
            k["env_steps"] += 1
            k["transitions"] += len(rows)
            k["update_credit"] += credit_per_step
            window_steps += len(rows)

            done_worlds = env.world_done
            if done_worlds.any():
                episode_ids = env.world_episode.copy()
                obs = env.reset_worlds(done_worlds)
                for b in np.flatnonzero(done_worlds):
                    world_rows = slice(b * env.uavs_per_world, (b + 1) * env.uavs_per_world)
                    records = [r for r in env.completed if r.episode == episode_ids[b]]
                    success = float(np.mean([r.success for r in records])) if records else 0.0
                    k["episodes"] += 1
                    self.history["episode"].append(self._episode_offset() + k["episodes"])
                    self.history["return"].append(float(returns[world_rows].mean()))
                    self.history["success"].append(success)
                    self.writer.add_scalar("charts/episode_reward", returns[world_rows].mean(), k["episodes"])
                    self.writer.add_scalar("charts/success_rate", success, k["episodes"])
                    returns[world_rows] = 0.0
                    k["update_credit"] += cfg.updates_per_episode
                    if unit == "episode":
                        bar.update(1)
                env.completed.clear()
                reset_rows = np.flatnonzero(np.repeat(done_worlds, env.uavs_per_world))
                buffer.start_episodes(reset_rows, obs.depth[reset_rows, -1])

            if k["transitions"] >= cfg.init_steps and buffer.size >= cfg.batch_size:
                todo = int(k["update_credit"])
                if cfg.total_updates > 0:
                    todo = min(todo, cfg.total_updates - k["updates"])
                bc_weight = self.teacher_weight()  # changes by a few parts in 10^4 over one step's updates
                for _ in range(todo):
                    latest_losses |= agent.update(buffer.sample(cfg.batch_size, agent.device, agent.config.n_step,
                                                                agent.config.discount, with_teacher=bc_weight > 0,
                                                                precollision_fraction=cfg.precollision_fraction),
                                                  bc_weight)
                    k["updates"] += 1
                    window_updates += 1
                    if unit == "update":
                        bar.update(1)
                    if k["updates"] % 100 == 0:
                        for name, value in latest_losses.items():
                            self.writer.add_scalar(name, value, k["updates"])
                k["update_credit"] -= todo
            else:
                k["update_credit"] = 0.0  # no debt piles up while the buffer fills

            now = time.perf_counter()
            if now - window_t > 10:
                env_rate, upd_rate = window_steps / (now - window_t), window_updates / (now - window_t)
                self.writer.add_scalar("charts/transitions_per_s", env_rate, k["updates"])
                self.writer.add_scalar("charts/updates_per_s", upd_rate, k["updates"])
                bar.set_fields(ep=k["episodes"], succ=f"{np.mean(self.history['success'][-20:] or [0]):.2f}",
                               sps=f"{env_rate:.0f}", ups=f"{upd_rate:.2f}")
                window_t, window_steps, window_updates = now, 0, 0
            if k["updates"] >= next_eval:
                self.validate(write=bar.write)
                bar.set_fields(val=f"{self.history['eval_success'][-1]:.2f}")
                next_eval += cfg.eval_every_updates
            bar.tick()
            if now - last_ckpt > cfg.checkpoint_every_s:
                k["wall_s"] = time.perf_counter() - started
                self.save_checkpoint()
                last_ckpt = time.perf_counter()

        bar.close()
        k["wall_s"] = time.perf_counter() - started
        self.save_checkpoint()
        return self.finish()

    def finish(self, recipe: dict | None = None, evaluation_steps: int | None = None) -> Path:
        """Final evaluation on unseen seeds, then export policy.pt with its provenance.

        ``recipe``: the stages of the recipe this run ends (:mod:`sitl.learn.recipe`), recorded in
        the provenance with the recipe's wall time from its first update to this export.
        ``evaluation_steps``: the final evaluation's time limit (default: the training episodes').
        """
        cfg, k = self.cfg, self.counters
        finish_started = time.perf_counter()
        if cfg.select_best and cfg.eval_every_updates and k["updates"] not in self._validated_updates():
            # The last networks are candidates too, also when the run does not end on a validation.
            self.validate(write=self.log)
            self.save_checkpoint()  # its history (and learning curve) now include that validation
        selected = self._restore_best_snapshot() if cfg.select_best else None
        eval_steps = cfg.time_limit(evaluation_steps)
        self.log(f"final evaluation: {cfg.final_eval_episodes} episodes of at most {eval_steps} steps, "
                 f"seeds >= {EVAL_SEED_OFFSET}")
        summaries = self.evaluate(cfg.final_eval_episodes, max_episode_steps=eval_steps) if cfg.final_eval_episodes else {}
        before = self.initial_stage
        provenance = {
            "method": cfg.method, "scenario": cfg.scenario, "density": cfg.density, "num_uavs": cfg.num_uavs,
            "preset": cfg.preset, "updates": k["updates"] + before.get("updates", 0),
            "env_steps": k["env_steps"] + before.get("env_steps", 0),
            "transitions": k["transitions"] + before.get("transitions", 0),
            "episodes": k["episodes"] + before.get("episodes", 0),
            "wall_time_s": round(k["wall_s"] + before.get("wall_s", 0.0), 1),
            "seed": cfg.seed, "device": cfg.device, "threads": cfg.threads,
            # The camera conditions it was trained in (policy.json's depth has the geometry).
            "camera": cfg.camera, "camera_noise": cfg.camera_noise,
            "mount_pitch_jitter_deg": cfg.mount_pitch_jitter_deg, "avoid_counts_ground": cfg.avoid_counts_ground,
            "collision_reward": cfg.collision_reward, "uav_collision_extra_reward": cfg.uav_collision_extra_reward,
        }
        if self.env.config.camera_noise is not None:  # the training worlds' noise, edge model included
            provenance["camera_noise_model"] = asdict(self.env.config.camera_noise)
        if self.env.config.dynamics_randomization is not None:  # each UAV's response drawn per episode from these
            provenance["dynamics_randomization"] = asdict(self.env.config.dynamics_randomization)
        if cfg.blind_motion_reward:  # not in the paper's reward
            provenance["blind_motion_reward"] = cfg.blind_motion_reward
        if cfg.corridor_speed_reward:  # not in the paper's reward either
            provenance["corridor_speed_reward"] = cfg.corridor_speed_reward
        if cfg.avoid_weight != RewardConfig.w_avoid:  # not the paper's eq. 4 weight
            provenance["avoid_weight"] = cfg.avoid_weight
        if cfg.obstacle_density:  # the training mix's obstacles episodes at their own density
            provenance["obstacle_density"] = cfg.obstacle_density
        if cfg.density_range:  # random training episodes at a density drawn per episode, not --density alone
            provenance["density_range"] = cfg.density_range
        if cfg.governor:  # policy.json's "governor" is the flight one; the rollouts may have flown another
            provenance["governor_setting"] = {"training": cfg.governor_setting,
                                              "flight": cfg.flight_governor_setting or cfg.governor_setting}
        if self.agent_cfg.privileged_critic:  # asymmetric actor-critic: not the paper's critic
            provenance["privileged_critic"] = {"neighbours": PRIVILEGED_NEIGHBOURS, "obstacle_point": True,
                                               "altitude": True, "module": "sitl.learn.privileged"}
        knows = "knows the UAVs in view" if cfg.teacher_camera_limited else "privileged"
        if cfg.teacher_bc_weight > 0:  # teacher-guided SAC+AE: not the paper's method alone
            outside = "circle worlds: see circle_worlds" if self.circle_teacher is not None else "circle worlds unlabelled"
            provenance["teacher"] = {"kind": f"orca ({knows}, sees obstacles; {outside})",
                                     "bc_weight": cfg.teacher_bc_weight, "bc_updates": cfg.teacher_bc_updates}
        if self.distill:  # not reinforcement learning: a student of privileged ORCA
            provenance["teacher"] = {"kind": f"orca ({knows}, sees obstacles)", "dagger_beta_updates":
                                     cfg.dagger_beta_updates, "module": "sitl.eval.orca"}
        from sitl.eval.orca import ORCA_REFERENCES, OrcaParams

        if self.teacher is not None and self.teacher.params != OrcaParams():  # not the ORCA references' settings
            provenance["teacher"]["orca"] = asdict(self.teacher.params)
        if self.circle_teacher is not None:  # circle worlds: the view-limited right-of-way ORCA
            params = self.circle_teacher.params
            name = next((n for n, ref in ORCA_REFERENCES.items() if ref == (params, True, False)), "orca-fov-right")
            provenance["teacher"]["circle_worlds"] = {
                "kind": f"{name} (knows the UAVs in view, keeps right by {params.right_hand_deg:g} deg)",
                "orca": asdict(params)}
        if selected is not None:
            provenance["selected_snapshot"] = selected  # trained for wall_time_s; these networks are from here
        if cfg.init_from:
            provenance["stages"] = [{"init_from": cfg.init_from, **before},
                                    {"scenario": cfg.scenario, **{n: k[n] for n in ("updates", "env_steps",
                                     "transitions", "episodes")}, "wall_s": round(k["wall_s"], 1)}]
        for i, (name, summary) in enumerate(summaries.items()):
            # The first evaluation scenario is "evaluation" (what evaluators read); others get a suffix.
            key = "evaluation" if i == 0 else f"evaluation_{name}"
            provenance[key] = {"episodes": cfg.final_eval_episodes, "max_episode_steps": eval_steps,
                               "seed": EVAL_SEED_OFFSET + cfg.seed,
                               "scenario": name, "density": cfg.density, **summary}
        if recipe is not None:
            recipe = dict(recipe)
            before_eval = recipe.pop("wall_time_s_before_final_evaluation")
            recipe["wall_time_s"] = round(before_eval + time.perf_counter() - finish_started, 1)
            provenance["recipe"] = recipe
        path = self.run_dir / "policy.pt"
        task = TaskSpec(collision_radius_m=self.sim_config.collision_radius_m,
                        arrival_radius_m=self.sim_config.reward.arrival_radius_m,
                        max_episode_steps=self.sim_config.max_episode_steps)
        export_policy(self.agent, path, self.sim_config.control_period_s, provenance, task,
                      governor=flight_governor(cfg))
        (self.run_dir / "final_eval.json").write_text(json.dumps(provenance, indent=2))
        self.writer.close()
        for name, summary in summaries.items():
            self.log(f"{name}: success {summary['success_rate']:.3f}, SPL {summary['spl']:.3f}")
        self.log(f"wrote {path}")
        return path


