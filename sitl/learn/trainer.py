"""``python -m sitl.train``: train the shared collision-avoidance policy (paper Alg. 1).

All UAVs of all simulated worlds act with one policy and feed one replay buffer
(centralised training, decentralised execution). The loop alternates environment steps
and gradient updates; the agent and its equations are in :mod:`sitl.learn.agent`.

Presets (``--preset``):

* ``fast`` (default) — trains on a 2-core laptop in under 2 hours: 32x32 depth, four
  worlds of 8 UAVs stepped together, one update per environment step (32 transitions), a
  fixed budget of updates, initial temperature 0.01 and 5-step returns
  (see ``PRESETS`` for why). Every other hyperparameter is the paper's Table I.
* ``paper`` — Table I literally: one world of 8 UAVs, 200 episodes, 400 updates after
  each episode, replay capacity 20,000, 64x64 depth.

Everything is a command-line flag (``--help``); a run directory holds ``config.json``,
TensorBoard logs (``tb/``), ``learning_curve.png``, ``checkpoint.pt`` (``--resume RUN_DIR``
continues from it) and the exported ``policy.pt``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import pickle
import shutil
import sys
import time
import warnings
from dataclasses import dataclass, field, fields, replace
from pathlib import Path

import numpy as np
import torch

from companion.spec import DEFAULT_ACTION_SPEC, CameraSpec
from sitl.cli_args import MAX_THREADS, ArgumentParser, finite_float, integer
from sitl.sim.config import TRAINING_SCENARIOS, RewardConfig, ScenarioConfig, SimConfig, density_from_name
from sitl.sim.env import SwarmEnv
from sitl.sim.metrics import summarize
from sitl.learn.agent import METHODS, AgentConfig, SacAeAgent
from sitl.learn.buffer import FrameReplayBuffer
from sitl.learn.export import export_policy

EVAL_SEED_OFFSET = 1_000_000  # test seeds (final evaluation, swarm_test) are >= this; training seeds are below it
#: Periodic evaluations during training (and snapshot selection) use their own seeds, so
#: choosing a snapshot never looks at the test episodes.
VALIDATION_SEED_OFFSET = 500_000


def _param(default, help: str):
    return field(default=default, metadata={"help": help})


@dataclass(frozen=True)
class TrainConfig:
    """Everything a training run depends on besides the agent's hyperparameters."""

    preset: str = _param("fast", "fast (CPU, < 2 h) or paper (Table I literally); explicit flags override it")
    method: str = _param("sac_ae", f"learning method: {', '.join(METHODS)}")
    scenario: str = _param("random", "training scenario: random, circle or mixed (each episode one of the two)")
    circle_fraction: float = _param(0.5, "mixed scenario: probability that an episode is a circle episode")
    density: str = _param("medium", "random scenario density: small, medium, large or UAV/m^3")
    circle_radius_m: float = _param(12.0, "circle scenario radius in m")
    yaw_jitter_deg: float = _param(45.0, "random scenario: initial heading error from the goal bearing, up to +-deg")
    arrival_radius_m: float = _param(0.5, "distance to the goal that counts as arrival (paper: 0.5 m)")
    num_uavs: int = _param(8, "UAVs per world")
    num_worlds: int = _param(4, "worlds stepped together (vectorised rollouts)")
    image_size: int = _param(32, "depth image side in pixels (square, 90 deg FOV)")
    max_episode_steps: int = _param(200, "episode time limit in 0.1 s steps")
    batch_size: int = _param(128, "Table I: batch size")
    replay_capacity: int = _param(50_000, "transitions kept (Table I: 20000)")
    max_episodes: int = _param(0, "stop after this many world episodes (0: no limit; Table I: 200)")
    total_updates: int = _param(25_000, "stop after this many gradient updates (0: no limit)")
    updates_per_episode: int = _param(0, "updates owed per finished world episode (Table I: 400)")
    updates_per_env_step: float = _param(1.0, "updates owed per vectorised environment step")
    init_steps: int = _param(2_000, "transitions of uniform random actions before learning starts")
    eval_every_updates: int = _param(2_500, "validate the deterministic policy every so many updates (0: never)")
    eval_episodes: int = _param(20, "episodes per periodic validation (validation seeds, disjoint from training and test)")
    select_best: bool = _param(False, "keep the networks of every validation and export the best one (highest mean "
                                      "validation success over the evaluation scenarios; later wins ties)")
    final_eval_episodes: int = _param(500, "episodes of the final evaluation recorded in policy.json (the random scene's success needs ~500 for +-1 point)")
    checkpoint_every_s: float = _param(300.0, "seconds between checkpoints")
    seed: int = _param(0, "seed of the environment, the buffer and torch")
    device: str = _param("cpu", "torch device: cpu or cuda")
    threads: int = _param(2, "torch intra-op threads")
    run_dir: str = _param("", "run directory (default runs/<method>-<scenario>-<density>-s<seed>-<time>)")
    vae_policy: str = _param("", "vae method: policy.pt that flies while depth images are collected")
    vae_images: int = _param(20_000, "vae method: stacked depth images to collect")
    vae_epochs: int = _param(20, "vae method: training epochs of the VAE")
    init_from: str = _param("", "start from the networks of another run (a curriculum stage): its directory or "
                                "checkpoint.pt (optimiser states carried over) or a validated snapshot "
                                "snapshots/agent_<updates>.pt; its updates and wall time count in this run's provenance")

    def __post_init__(self) -> None:
        if self.preset not in PRESETS:
            raise ValueError(f"unknown preset {self.preset!r}; choose one of {', '.join(PRESETS)}")
        if self.method not in METHODS:
            raise ValueError(f"unknown method {self.method!r}; choose one of {', '.join(METHODS)}")
        if self.scenario not in TRAINING_SCENARIOS:
            raise ValueError(f"unknown scenario {self.scenario!r}; choose one of {', '.join(TRAINING_SCENARIOS)}")
        if not 0.0 <= self.circle_fraction <= 1.0:
            raise ValueError(f"circle_fraction must be in [0, 1], got {self.circle_fraction}")
        if not math.isfinite(density_from_name(self.density)):
            raise ValueError(f"density must be a finite number of UAV/m^3, got {self.density!r}")
        # Integer ranges: the upper ends keep a typo from allocating (or promising) the impossible.
        for name, low, high in TRAIN_INT_RANGES:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
                raise ValueError(f"{name} must be an integer in {low}..{high}, got {value!r}")
        # Float ranges written so that NaN fails them too.
        if not 0.0 < self.arrival_radius_m <= 100.0:
            raise ValueError(f"arrival_radius_m must be in (0, 100], got {self.arrival_radius_m}")
        if not 0.0 < self.circle_radius_m <= 10_000.0:
            raise ValueError(f"circle_radius_m must be in (0, 10000], got {self.circle_radius_m}")
        if not 0.0 <= self.yaw_jitter_deg <= 180.0:
            raise ValueError(f"yaw_jitter_deg must be in [0, 180], got {self.yaw_jitter_deg}")
        if not 0.0 <= self.updates_per_env_step <= 10_000.0:
            raise ValueError(f"updates_per_env_step must be in [0, 10000], got {self.updates_per_env_step}")
        if not 0.0 < self.checkpoint_every_s < math.inf:
            raise ValueError(f"checkpoint_every_s must be a finite number > 0, got {self.checkpoint_every_s}")
        try:
            torch.device(self.device)
        except RuntimeError:
            raise ValueError(f"unknown torch device {self.device!r}; use cpu or cuda") from None
        if self.image_size < 16:
            raise ValueError(f"image_size must be >= 16 (the encoder shrinks it by 14 pixels), got {self.image_size}")
        if self.max_episodes <= 0 and self.total_updates <= 0:
            raise ValueError("set max_episodes or total_updates: the run needs an end")
        if self.updates_per_episode <= 0 and self.updates_per_env_step <= 0:
            raise ValueError("set updates_per_episode or updates_per_env_step: the run needs updates")
        if self.device.startswith("cuda") and not torch.cuda.is_available():
            raise ValueError("--device cuda asked for, but torch sees no CUDA device")


#: (field, lowest, highest) of TrainConfig's integers.
TRAIN_INT_RANGES = (
    ("num_uavs", 1, 1000), ("num_worlds", 1, 1000), ("image_size", 1, 256), ("max_episode_steps", 1, 100_000),
    ("batch_size", 1, 100_000), ("replay_capacity", 1, 10_000_000), ("max_episodes", 0, 10**9),
    ("total_updates", 0, 10**9), ("updates_per_episode", 0, 1_000_000), ("init_steps", 0, 10**9),
    ("eval_every_updates", 0, 10**9), ("eval_episodes", 1, 1_000_000), ("final_eval_episodes", 0, 1_000_000),
    ("seed", 0, 2**32 - 1), ("threads", 1, MAX_THREADS), ("vae_images", 1, 10_000_000), ("vae_epochs", 1, 100_000),
)

#: Each preset sets training and agent fields; explicit flags override it. The dataclass
#: defaults are the fast preset's training values and the paper's agent values.
PRESETS: dict[str, dict[str, dict]] = {
    # Measured choices for a 2-core CPU (docs/training.md): 32x32 images (the paper's 1024
    # hidden units stay: at 32x32 they cost only ~4 % more than 256), a lower initial temperature
    # (the reference's 0.1 is tuned for DMC rewards of ~1 per step; here progress pays
    # <= 0.6 per step and the entropy bonus drowned it) and 5-step returns (one-step targets
    # with tau 0.01 propagated the arrival reward over the ~40-step episodes too slowly).
    "fast": {"train": {}, "agent": {"init_temperature": 0.01, "n_step": 5}},
    "paper": {"train": {"num_worlds": 1, "image_size": 64, "replay_capacity": 20_000, "max_episodes": 200,
                        "total_updates": 0, "updates_per_episode": 400, "updates_per_env_step": 0.0,
                        "init_steps": 1_000},
              "agent": {}},
}


# --------------------------------------------------------------------------- command line

def _add_dataclass_flags(parser: argparse.ArgumentParser, cls, title: str) -> None:
    group = parser.add_argument_group(title)
    for f in fields(cls):
        if any(a.dest == f.name for a in parser._actions):
            continue  # e.g. method: one flag sets both configs
        flag = "--" + f.name.replace("_", "-")
        kind = {float: finite_float, int: integer}.get(type(f.default), type(f.default))
        help_text = f.metadata.get("help", "") + f" (default: {f.default})"
        if type(f.default) is bool:
            group.add_argument(flag, dest=f.name, action=argparse.BooleanOptionalAction, default=argparse.SUPPRESS,
                               help=help_text)
        else:
            group.add_argument(flag, dest=f.name, type=kind, default=argparse.SUPPRESS, help=help_text)


def parse_args(argv: list[str] | None = None) -> tuple[TrainConfig, AgentConfig, str | None]:
    """Build the two configs: defaults, then the preset, then explicit flags."""
    parser = ArgumentParser(prog="python -m sitl.train", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--resume", metavar="RUN_DIR", default=None, help="continue the run in RUN_DIR from its checkpoint")
    _add_dataclass_flags(parser, TrainConfig, "training")
    _add_dataclass_flags(parser, AgentConfig, "agent (paper Table I; reference train.py where the paper is silent)")
    args = vars(parser.parse_args(argv))
    resume = args.pop("resume")
    train_names = {f.name for f in fields(TrainConfig)}
    train_args = {k: v for k, v in args.items() if k in train_names}
    agent_args = {k: v for k, v in args.items() if k not in train_names}
    try:
        preset = train_args.get("preset", "fast")
        if preset not in PRESETS:
            raise ValueError(f"unknown preset {preset!r}; choose one of {', '.join(PRESETS)}")
        train_cfg = TrainConfig(**{**PRESETS[preset]["train"], **train_args})
        agent_cfg = AgentConfig(**{**PRESETS[preset]["agent"], "method": train_cfg.method, **agent_args})
    except ValueError as err:
        parser.error(str(err))
    return train_cfg, agent_cfg, resume


# --------------------------------------------------------------------------- pieces

def make_sim_config(cfg: TrainConfig, num_worlds: int, record_paths: bool = False,
                    scenario_name: str | None = None) -> SimConfig:
    """The worlds of ``cfg`` (``scenario_name`` overrides its scenario, e.g. for evaluation)."""
    scenario = ScenarioConfig(name=scenario_name or cfg.scenario, density=density_from_name(cfg.density),
                              circle_radius_m=cfg.circle_radius_m, yaw_jitter_rad=math.radians(cfg.yaw_jitter_deg),
                              circle_fraction=cfg.circle_fraction)
    camera = CameraSpec(width=cfg.image_size, height=cfg.image_size)
    return SimConfig(num_uavs=cfg.num_uavs, num_worlds=num_worlds, scenario=scenario, camera=camera,
                     max_episode_steps=cfg.max_episode_steps, record_paths=record_paths,
                     reward=RewardConfig(arrival_radius_m=cfg.arrival_radius_m))


#: Evaluation episodes flown at once as parallel worlds (as ``swarm_test --batch``).
EVAL_BATCH_WORLDS = 100


def evaluate(act, sim_config: SimConfig, seed: int, episodes: int) -> dict:
    """Fly ``episodes`` episodes of ``act(depth, state) -> actions``, ``sim_config.num_worlds`` at a time.

    The episodes are those of ``swarm_test`` with the same seed (``SwarmEnv.fly_episodes``).
    """
    env = SwarmEnv(sim_config, seed=seed)
    return summarize(env.fly_episodes(env.reset(), lambda obs: act(obs.depth, obs.state), episodes))


def evaluation_scenarios(cfg: TrainConfig) -> tuple[str, ...]:
    """The scenarios a run is evaluated on: its own, or both halves of a mixed one."""
    return ("random", "circle") if cfg.scenario == "mixed" else (cfg.scenario,)


def default_run_dir(cfg: TrainConfig) -> Path:
    stamp = time.strftime("%Y%m%d-%H%M%S")
    return Path("runs") / f"{cfg.method}-{cfg.scenario}-{cfg.density}-s{cfg.seed}-{stamp}"


def plot_learning_curve(history: dict, path: Path, title: str) -> None:
    """Paper Fig. 4 style: average episode reward (and success rate) against episodes."""
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
    ax_s.set_xlabel("episode")
    ax_r.set_title(title)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


STAGE_COUNTERS = ("updates", "env_steps", "transitions", "episodes", "wall_s")


def add_counters(counters: dict, earlier: dict) -> dict:
    """A run's counters plus those of the stages it started from (provenance of curricula)."""
    return {n: counters[n] + earlier.get(n, 0) for n in STAGE_COUNTERS}


def snapshot_counters(snapshot: Path) -> dict:
    """Training that went into a validated snapshot ``RUN/snapshots/agent_<updates>.pt``.

    Updates and wall time come from the snapshot's row in ``validation.json``; so do
    environment steps, transitions and episodes where the row records them (rows written
    before it did get them scaled from the run's totals by the update count).
    """
    run_dir = snapshot.parent.parent
    try:
        rows = json.loads((snapshot.parent / "validation.json").read_text())
        ckpt = torch.load(run_dir / "checkpoint.pt", weights_only=False)
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


def select_snapshot(rows: list[dict]) -> dict:
    """The best row of ``validation.json``; rescored rows (``sitl.rescore``) compete only among themselves."""
    rescored = [row for row in rows if "rescored" in row]
    return max(rescored or rows, key=lambda row: (snapshot_score(row), row["updates"]))


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
    return SacAeAgent(agent_cfg, cam, DEFAULT_ACTION_SPEC, device, vae_encoder)


def evaluate_scenario(act, cfg: TrainConfig, scenario_name: str, episodes: int, seed: int) -> dict:
    """``evaluate`` in ``cfg``'s worlds of one scenario, up to ``EVAL_BATCH_WORLDS`` at a time."""
    sim_config = make_sim_config(cfg, min(episodes, EVAL_BATCH_WORLDS), scenario_name=scenario_name)
    return evaluate(act, sim_config, seed=seed, episodes=episodes)


def build_vae_encoder(cfg: TrainConfig, sim_config: SimConfig, log) -> torch.nn.Module:
    """RL+VAE's protocol: collect depth images with a trained policy, train a VAE, freeze it."""
    from companion.policy import load_policy
    from sitl.eval.baselines import straight_to_goal
    from sitl.learn.vae import train_vae

    if cfg.vae_policy:
        policy = load_policy(cfg.vae_policy)
        act = policy.act
        log(f"collecting {cfg.vae_images} depth images with {cfg.vae_policy}")
    else:
        act = lambda depth, state: straight_to_goal(state)  # noqa: E731
        log(f"no --vae-policy given: collecting {cfg.vae_images} depth images with the straight-to-goal reference")
    env = SwarmEnv(sim_config, seed=cfg.seed + 7)
    obs = env.reset()
    images = []
    count = 0
    while count < cfg.vae_images:
        rows = np.flatnonzero(env.acting)
        images.append(obs.depth[rows].astype(np.float16))
        count += len(rows)
        obs, *_ = env.step(act(obs.depth, obs.state))
        if env.world_done.any():
            obs = env.reset_worlds(env.world_done)
    data = np.concatenate(images)[: cfg.vae_images].astype(np.float32)
    encoder, losses = train_vae(data, sim_config.camera.max_range_m, epochs=cfg.vae_epochs, seed=cfg.seed,
                                progress=lambda e, loss: log(f"VAE epoch {e}/{cfg.vae_epochs}: loss {loss:.2f}"))
    return encoder


# --------------------------------------------------------------------------- the loop

class Trainer:
    """One training run: environment, agent, buffer, logs and checkpoints."""

    def __init__(self, cfg: TrainConfig, agent_cfg: AgentConfig, run_dir: Path, resume: bool = False) -> None:
        self.cfg, self.agent_cfg, self.run_dir = cfg, agent_cfg, run_dir
        torch.set_num_threads(cfg.threads)
        torch.manual_seed(cfg.seed)
        self.sim_config = make_sim_config(cfg, cfg.num_worlds)
        self.env = SwarmEnv(self.sim_config, seed=cfg.seed)
        trained_vae = build_vae_encoder(cfg, self.sim_config, self.log) \
            if agent_cfg.method == "vae" and not resume else None
        self.agent = make_agent(agent_cfg, self.sim_config, cfg.device, trained_vae)
        cam = self.sim_config.camera
        self.buffer = FrameReplayBuffer(cfg.replay_capacity, self.env.num_agents, cam.frames, cam.height, cam.width,
                                        6, 3, seed=cfg.seed)
        self.counters = {"env_steps": 0, "transitions": 0, "episodes": 0, "updates": 0, "wall_s": 0.0,
                         "update_credit": 0.0}
        self.history: dict[str, list] = {"episode": [], "return": [], "success": [], "eval_episode": [],
                                         "eval_success": [], "eval_spl": []}
        from torch.utils.tensorboard import SummaryWriter

        self.writer = SummaryWriter(str(run_dir / "tb"))
        #: counters of the run this one started from (``init_from``), for the provenance
        self.initial_stage: dict = {}
        if resume:
            try:
                ckpt = torch.load(run_dir / "checkpoint.pt", weights_only=False)
            except (OSError, RuntimeError, EOFError, pickle.UnpicklingError) as err:
                raise ValueError(f"cannot resume: {run_dir / 'checkpoint.pt'} is not a readable checkpoint "
                                 f"({str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__})") from None
            self._restore(ckpt)
        elif cfg.init_from:
            self._init_from(Path(cfg.init_from))

    def log(self, message: str) -> None:
        print(message, file=sys.stderr, flush=True)

    # -------------------------------------------------------------- checkpoints
    def save_checkpoint(self) -> None:
        _atomic_save({
            "agent": self.agent.checkpoint(), "buffer": self.buffer.state_dict(), "counters": dict(self.counters),
            "history": self.history, "env_rng": self.env.rng.bit_generator.state,
            "torch_rng": torch.get_rng_state(), "initial_stage": self.initial_stage,
        }, self.run_dir / "checkpoint.pt")
        plot_learning_curve(self.history, self.run_dir / "learning_curve.png", self._title())

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
                ckpt = torch.load(path, weights_only=False)
        except Exception as err:  # noqa: BLE001 - any unreadable file gets the same clear refusal
            raise ValueError(f"--init-from {path}: not a readable training checkpoint ({err})") from None
        if not isinstance(ckpt, dict):
            raise ValueError(f"--init-from {path}: not a training checkpoint or snapshot but a "
                             f"{type(ckpt).__name__} (an exported policy.pt cannot be trained further; "
                             "pass the run directory it came from)")
        is_snapshot = "agent" not in ckpt
        try:
            if is_snapshot:
                self.agent.load_state_dict(ckpt)
            else:
                self.agent.restore(ckpt["agent"])
        except (RuntimeError, KeyError, ValueError, TypeError) as err:
            raise ValueError(f"--init-from {path}: its networks do not match this run's agent settings "
                             f"(method, hidden_dim, image_size, ...): {str(err)[:300]}") from None
        self.agent.apply_learning_rates()
        self.initial_stage = snapshot_counters(path) if is_snapshot else \
            add_counters(ckpt["counters"], ckpt.get("initial_stage", {}))  # that run may itself be a later stage
        self.log(f"initialised from {path}: {self.initial_stage['updates']} updates, "
                 f"{self.initial_stage['wall_s'] / 60:.1f} min of training")

    def _title(self) -> str:
        c = self.cfg
        return f"{c.method}, {c.scenario} {c.density}, N={c.num_uavs}"

    # -------------------------------------------------------------- helpers
    def finished(self) -> bool:
        c, k = self.cfg, self.counters
        return (c.total_updates > 0 and k["updates"] >= c.total_updates) or \
               (c.max_episodes > 0 and k["episodes"] >= c.max_episodes)

    def evaluate(self, episodes: int, seed_offset: int = EVAL_SEED_OFFSET) -> dict[str, dict]:
        """Deterministic evaluation on unseen seeds (test seeds by default), one summary per evaluation scenario."""
        act = lambda d, s: self.agent.act(d, s, explore=False)  # noqa: E731
        return {name: evaluate_scenario(act, self.cfg, name, episodes, seed_offset + self.cfg.seed)
                for name in evaluation_scenarios(self.cfg)}

    def validate(self, write=print) -> None:
        """Evaluate on the validation seeds, log it, and keep a snapshot when selecting the best."""
        cfg, k = self.cfg, self.counters
        summaries = self.evaluate(cfg.eval_episodes, VALIDATION_SEED_OFFSET)
        if cfg.select_best:
            self._keep_snapshot(summaries)
        self.history["eval_episode"].append(k["episodes"])
        # The curve shows the mean over the evaluation scenarios; TensorBoard each one.
        self.history["eval_success"].append(float(np.mean([s["success_rate"] for s in summaries.values()])))
        self.history["eval_spl"].append(float(np.mean([s["spl"] for s in summaries.values()])))
        for name, summary in summaries.items():
            suffix = "" if len(summaries) == 1 else f"_{name}"
            self.writer.add_scalar(f"eval/success_rate{suffix}", summary["success_rate"], k["updates"])
            self.writer.add_scalar(f"eval/spl{suffix}", summary["spl"], k["updates"])
            write(f"validation @ {k['updates']} updates ({k['episodes']} training episodes), {name} "
                  f"({cfg.eval_episodes} episodes): success {summary['success_rate']:.3f}, SPL {summary['spl']:.3f}")

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
                      "counters": counters,
                      **{name: {"success_rate": s["success_rate"], "spl": s["spl"]} for name, s in summaries.items()}})
        index_path.write_text(json.dumps(index, indent=1))

    def _restore_best_snapshot(self) -> dict | None:
        """Load the best validated networks into the agent; returns that snapshot's row."""
        index_path = self.run_dir / "snapshots" / "validation.json"
        if not index_path.exists():
            return None
        best = select_snapshot(json.loads(index_path.read_text()))
        self.agent.load_state_dict(torch.load(self.run_dir / "snapshots" / f"agent_{best['updates']}.pt"))
        how = "rescored" if "rescored" in best else "validation success"
        self.log(f"selected the snapshot at {best['updates']} updates ({how} {snapshot_score(best):.3f})")
        return best

    # -------------------------------------------------------------- main loop
    def run(self) -> Path:
        from tqdm import tqdm

        cfg, env, agent, buffer, k = self.cfg, self.env, self.agent, self.buffer, self.counters
        obs = env.reset()
        everyone = np.arange(env.num_agents)
        buffer.start_episodes(everyone, obs.depth[:, -1])
        returns = np.zeros(env.num_agents)
        low, high = env.action_spec.low_array(), env.action_spec.high_array()
        rng = np.random.default_rng(cfg.seed + k["env_steps"])
        total = cfg.total_updates if cfg.total_updates > 0 else cfg.max_episodes
        unit = "update" if cfg.total_updates > 0 else "episode"
        bar = tqdm(total=total, initial=k["updates"] if unit == "update" else k["episodes"], unit=unit,
                   desc=self._title(), file=sys.stderr, dynamic_ncols=True, mininterval=2.0)
        started = self._started = time.perf_counter() - k["wall_s"]
        last_ckpt = time.perf_counter()
        next_eval = (k["updates"] // cfg.eval_every_updates + 1) * cfg.eval_every_updates if cfg.eval_every_updates else math.inf
        window_t, window_steps, window_updates = time.perf_counter(), 0, 0
        latest_losses: dict[str, float] = {}

        while not self.finished():
            acting = env.acting.copy()
            rows = np.flatnonzero(acting)
            if k["transitions"] < cfg.init_steps and not cfg.init_from:
                action = rng.uniform(low, high, size=(env.num_agents, 3)).astype(np.float32)
            else:
                action = agent.act(obs.depth, obs.state, explore=True)
            state = obs.state
            obs, reward, terminated, truncated, info = env.step(action)
            buffer.add(rows, state[rows], agent.to_unit_action(action[rows]), reward[rows], obs.depth[rows, -1],
                       obs.state[rows], terminated[rows])
            returns += reward
            k["env_steps"] += 1
            k["transitions"] += len(rows)
            k["update_credit"] += cfg.updates_per_env_step
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
                    self.history["episode"].append(k["episodes"])
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
                for _ in range(todo):
                    latest_losses |= agent.update(buffer.sample(cfg.batch_size, agent.device, agent.config.n_step,
                                                                agent.config.discount))
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
                bar.set_postfix(ep=k["episodes"], succ=f"{np.mean(self.history['success'][-20:] or [0]):.2f}",
                                sps=f"{env_rate:.0f}", ups=f"{upd_rate:.2f}")
                window_t, window_steps, window_updates = now, 0, 0
            if k["updates"] >= next_eval:
                self.validate(write=bar.write)
                next_eval += cfg.eval_every_updates
            if now - last_ckpt > cfg.checkpoint_every_s:
                k["wall_s"] = time.perf_counter() - started
                self.save_checkpoint()
                last_ckpt = time.perf_counter()

        bar.close()
        k["wall_s"] = time.perf_counter() - started
        self.save_checkpoint()
        return self.finish()

    def finish(self) -> Path:
        """Final evaluation on unseen seeds, then export policy.pt with its provenance."""
        cfg, k = self.cfg, self.counters
        if cfg.select_best and cfg.eval_every_updates and k["updates"] not in self._validated_updates():
            # The last networks are candidates too, also when the run does not end on a validation.
            self.validate(write=self.log)
            self.save_checkpoint()  # its history (and learning curve) now include that validation
        selected = self._restore_best_snapshot() if cfg.select_best else None
        self.log(f"final evaluation: {cfg.final_eval_episodes} episodes, seeds >= {EVAL_SEED_OFFSET}")
        summaries = self.evaluate(cfg.final_eval_episodes) if cfg.final_eval_episodes else {}
        before = self.initial_stage
        provenance = {
            "method": cfg.method, "scenario": cfg.scenario, "density": cfg.density, "num_uavs": cfg.num_uavs,
            "preset": cfg.preset, "updates": k["updates"] + before.get("updates", 0),
            "env_steps": k["env_steps"] + before.get("env_steps", 0),
            "transitions": k["transitions"] + before.get("transitions", 0),
            "episodes": k["episodes"] + before.get("episodes", 0),
            "wall_time_s": round(k["wall_s"] + before.get("wall_s", 0.0), 1),
            "seed": cfg.seed, "device": cfg.device, "threads": cfg.threads,
        }
        if selected is not None:
            provenance["selected_snapshot"] = selected  # trained for wall_time_s; these networks are from here
        if cfg.init_from:
            provenance["stages"] = [{"init_from": cfg.init_from, **before},
                                    {"scenario": cfg.scenario, **{n: k[n] for n in ("updates", "env_steps",
                                     "transitions", "episodes")}, "wall_s": round(k["wall_s"], 1)}]
        for i, (name, summary) in enumerate(summaries.items()):
            # The first evaluation scenario is "evaluation" (what evaluators read); others get a suffix.
            key = "evaluation" if i == 0 else f"evaluation_{name}"
            provenance[key] = {"episodes": cfg.final_eval_episodes, "seed": EVAL_SEED_OFFSET + cfg.seed,
                               "scenario": name, "density": cfg.density, **summary}
        path = self.run_dir / "policy.pt"
        export_policy(self.agent, path, self.sim_config.control_period_s, provenance)
        (self.run_dir / "final_eval.json").write_text(json.dumps(provenance, indent=2))
        self.writer.close()
        for name, summary in summaries.items():
            self.log(f"{name}: success {summary['success_rate']:.3f}, SPL {summary['spl']:.3f}")
        self.log(f"wrote {path}")
        return path


def main(argv: list[str] | None = None) -> int:
    cfg, agent_cfg, resume = parse_args(argv)
    if resume:
        run_dir = Path(resume)
        if not (run_dir / "checkpoint.pt").is_file():
            print(f"error: {run_dir} has no checkpoint.pt to resume from", file=sys.stderr)
            return 2
        try:
            saved = json.loads((run_dir / "config.json").read_text())
            cfg, agent_cfg = TrainConfig(**saved["train"]), AgentConfig(**saved["agent"])
        except (OSError, ValueError, KeyError, TypeError) as err:
            print(f"error: cannot resume {run_dir}: its config.json is missing or invalid ({err})", file=sys.stderr)
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
    try:
        trainer = Trainer(cfg, agent_cfg, run_dir, resume=bool(resume))
    except (FileNotFoundError, ValueError) as err:
        if not resume:
            shutil.rmtree(run_dir, ignore_errors=True)  # nothing was trained: leave no half-made run behind
        print(f"error: {err}", file=sys.stderr)
        return 2
    trainer.log(f"run directory {run_dir}; replay buffer {trainer.buffer.nbytes / 2**20:.0f} MiB")
    trainer.run()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
