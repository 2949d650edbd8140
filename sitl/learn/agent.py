"""SAC+AE (paper III.C-D) and the baselines that share its soft actor-critic.

Methods (``AgentConfig.method``):

* ``sac_ae`` — the paper's method: the critic's encoder is trained by the critic loss and by
  a regularised autoencoder (RAE, eq. 8); the actor reuses the critic's convolutions with
  their gradient stopped (Fig. 2).
* ``cnn`` — RL+CNN: the same agent without the decoder; the encoder learns from the critic only.
* ``drq`` — the encoder learns from the critic on randomly shifted images (Kostrikov et al.
  2020): cheaper per update than the decoder, and reported as more sample-efficient.
* ``vae`` — RL+VAE: the encoder is a VAE trained beforehand on depth images and frozen; SAC
  learns on its latent (see :mod:`sitl.learn.vae`).
* ``distill`` — not reinforcement learning: the same actor (encoder and MLP, the same policy
  file) learns by regression on a privileged teacher's actions, DAgger-style (Ross et al. 2011):
  the trainer labels every transition with what obstacle-aware ORCA, which knows every UAV's and
  obstacle's true position, would command (:mod:`sitl.eval.orca`), and the UAVs fly a mixture of
  teacher and student that hands over to the student (``TrainConfig.dagger_beta_updates``).
  :meth:`SacAeAgent.update_imitation`; the critic is built but never trained. A later stage may hand
  the student to SAC (``cnn`` with ``freeze_convs``: its convolutions stay, and ``actor_delay_updates``
  lets the critic learn before the actor moves; the ``flown-distill`` recipe).

The update follows the equations: :meth:`SacAeAgent.update_critic` (eqs. 5-6),
:meth:`SacAeAgent.update_actor_and_alpha` (eq. 7), :meth:`SacAeAgent.update_decoder` (eq. 8).
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from companion.spec import ActionSpec, CameraSpec, MemorySpec
from sitl.learn.networks import Actor, Critic, Decoder, DepthNormalizer, Encoder, StateFeatures, weight_init
from sitl.learn.privileged import PRIVILEGED_DIM

METHODS = ("sac_ae", "cnn", "drq", "vae", "distill")


@dataclass(frozen=True)
class AgentConfig:
    """Hyperparameters of the agent; defaults are the paper's Table I, else the reference's train.py."""

    method: str = field(default="sac_ae", metadata={"help": "learning method (set by --method)"})
    hidden_dim: int = field(default=1024, metadata={"help": "paper: 3-layer MLPs with 1024 units"})
    latent_dim: int = field(default=50, metadata={"help": "paper: 50-d latent"})
    num_filters: int = field(default=32, metadata={"help": "paper: 32 filters per conv layer"})
    discount: float = field(default=0.99, metadata={"help": "Table I"})
    critic_lr: float = field(default=1e-3, metadata={"help": "Table I"})
    critic_beta: float = field(default=0.9, metadata={"help": "reference train.py (Adam beta1)"})
    critic_tau: float = field(default=0.01, metadata={"help": "Table I: tau_Q"})
    encoder_tau: float = field(default=0.05, metadata={"help": "Table I: tau_enc"})
    critic_target_update_freq: int = field(default=2, metadata={"help": "Table I"})
    actor_lr: float = field(default=1e-3, metadata={"help": "Table I"})
    actor_beta: float = field(default=0.9, metadata={"help": "reference train.py"})
    actor_update_freq: int = field(default=2, metadata={"help": "Table I"})
    init_temperature: float = field(default=0.1, metadata={"help": "reference train.py"})
    alpha_lr: float = field(default=1e-4, metadata={"help": "reference train.py"})
    alpha_beta: float = field(default=0.5, metadata={"help": "reference train.py"})
    encoder_lr: float = field(default=1e-3, metadata={"help": "Table I: autoencoder learning rate"})
    decoder_lr: float = field(default=1e-3, metadata={"help": "Table I: autoencoder learning rate"})
    decoder_latent_lambda: float = field(default=1e-6, metadata={"help": "eq. 8: lambda_z"})
    decoder_weight_lambda: float = field(default=1e-7, metadata={"help": "eq. 8: lambda_phi (L2 on decoder weights)"})
    decoder_update_freq: int = field(default=1, metadata={"help": "reference train.py"})
    n_step: int = field(default=1, metadata={"help": "n-step returns (1: the paper's one-step SAC target)"})
    drq_pad: int = field(default=2, metadata={"help": "drq: random shift of up to this many pixels"})
    distill_shift_px: int = field(default=0, metadata={
        "help": "distill only: shift each depth stack in the imitation loss by up to this many pixels (DrQ's "
                "random shift as a regulariser for a student that fits its labels but does not generalise them; "
                "0: off; not in the paper)"})
    privileged_critic: bool = field(default=False, metadata={
        "help": "asymmetric actor-critic (not in the paper): the critic also sees the true positions and velocities "
                "of the 3 nearest UAVs, the nearest obstacle point and the altitude (sitl.learn.privileged); "
                "the actor and the policy file are unchanged"})
    freeze_convs: bool = field(default=False, metadata={
        "help": "cnn method only: the convolutions are not trained (SAC on fixed features, e.g. those of a "
                "distilled student handed over to reinforcement learning; not in the paper)"})
    actor_delay_updates: int = field(default=0, metadata={
        "help": "no actor or temperature update in this agent's first N updates: the critic learns the policy "
                "it was handed before the policy moves (not in the paper)"})

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ValueError(f"unknown method {self.method!r}; choose one of {', '.join(METHODS)}")
        # Ranges written so that NaN fails them too (every comparison with NaN is false).
        for name, low, high in (("hidden_dim", 1, 8192), ("latent_dim", 1, 1024), ("num_filters", 1, 256),
                                ("critic_target_update_freq", 1, 10_000), ("actor_update_freq", 1, 10_000),
                                ("decoder_update_freq", 1, 10_000), ("n_step", 1, 1000), ("drq_pad", 0, 16),
                                ("distill_shift_px", 0, 16),
                                ("actor_delay_updates", 0, 10_000_000)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
                raise ValueError(f"{name} must be an integer in {low}..{high}, got {value!r}")
        if self.freeze_convs and self.method != "cnn":
            raise ValueError(f"freeze_convs is for the cnn method (SAC on fixed convolutions), not {self.method!r}")
        checks = {
            "discount": (lambda v: 0.0 < v <= 1.0, "in (0, 1]"),
            "critic_tau": (lambda v: 0.0 < v <= 1.0, "in (0, 1]"),
            "encoder_tau": (lambda v: 0.0 < v <= 1.0, "in (0, 1]"),
            "critic_beta": (lambda v: 0.0 <= v < 1.0, "in [0, 1)"),
            "actor_beta": (lambda v: 0.0 <= v < 1.0, "in [0, 1)"),
            "alpha_beta": (lambda v: 0.0 <= v < 1.0, "in [0, 1)"),
            "init_temperature": (lambda v: 0.0 < v < math.inf, "a finite number > 0"),
            "decoder_latent_lambda": (lambda v: 0.0 <= v < math.inf, "a finite number >= 0"),
            "decoder_weight_lambda": (lambda v: 0.0 <= v < math.inf, "a finite number >= 0"),
            **{f"{net}_lr": (lambda v: 0.0 < v <= 1.0, "in (0, 1]") for net in ("critic", "actor", "alpha", "encoder",
                                                                               "decoder")},
        }
        for name, (ok, wanted) in checks.items():
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not ok(value):
                raise ValueError(f"{name} must be {wanted}, got {value!r}")


def random_shift(x: torch.Tensor, pad: int) -> torch.Tensor:
    """DrQ augmentation: replicate-pad by ``pad`` and crop back at a random offset per sample."""
    n, c, h, w = x.shape
    padded = F.pad(x, (pad, pad, pad, pad), mode="replicate")
    # Pixel centres of the padded image in grid_sample's [-1, 1] coordinates, per axis: with one eps for
    # both (DrQ's square images) a non-square grid such as the D435's 32x20 would be resampled, not shifted.
    eps_y, eps_x = 1.0 / (h + 2 * pad), 1.0 / (w + 2 * pad)
    arange = torch.linspace(-1.0 + eps_y, 1.0 - eps_y, h + 2 * pad, device=x.device)[:h]
    base_y = arange.unsqueeze(1).repeat(1, w)
    arange_x = torch.linspace(-1.0 + eps_x, 1.0 - eps_x, w + 2 * pad, device=x.device)[:w]
    base_x = arange_x.unsqueeze(0).repeat(h, 1)
    grid = torch.stack([base_x, base_y], dim=-1).unsqueeze(0).repeat(n, 1, 1, 1)
    shift = torch.randint(0, 2 * pad + 1, size=(n, 1, 1, 2), device=x.device, dtype=x.dtype)
    shift *= 2.0 / (torch.tensor([w, h], device=x.device, dtype=x.dtype) + 2 * pad)
    return F.grid_sample(padded, grid + shift, padding_mode="zeros", align_corners=False)


class SacAeAgent(nn.Module):
    """The shared policy of all UAVs, its critics and (for sac_ae) its decoder."""

    def __init__(self, config: AgentConfig, camera: CameraSpec, action_spec: ActionSpec,
                 device: torch.device | str = "cpu", vae_encoder: nn.Module | None = None,
                 memory: MemorySpec | None = None) -> None:
        super().__init__()
        self.config = config
        self.camera = camera
        self.memory = memory  # remembered depth in the state (None: the paper's state)
        self.action_spec = action_spec
        self.device = torch.device(device)
        frames, h, w = camera.frames, camera.height, camera.width
        self.normalize_depth = DepthNormalizer(camera.max_range_m)
        self.state_features = (StateFeatures(memory.num_sectors, memory.range_m) if memory is not None
                               else StateFeatures())
        state_features = self.state_features.num_features
        low = torch.tensor(action_spec.low, dtype=torch.float32)
        high = torch.tensor(action_spec.high, dtype=torch.float32)

        if config.method == "vae":
            if vae_encoder is None:
                raise ValueError("method 'vae' needs a trained VAE encoder")
            critic_encoder, actor_encoder = vae_encoder, vae_encoder
            for p in vae_encoder.parameters():
                p.requires_grad_(False)
        else:
            critic_encoder = Encoder(frames, h, w, config.latent_dim, config.num_filters)
            actor_encoder = Encoder(frames, h, w, config.latent_dim, config.num_filters)
        #: width of the critic's privileged input (0: the paper's critic, which sees what the actor sees)
        self.privileged_dim = PRIVILEGED_DIM if config.privileged_critic else 0
        self.critic = Critic(critic_encoder, state_features + self.privileged_dim, len(action_spec.low),
                             config.hidden_dim)
        self.actor = Actor(actor_encoder, state_features, low, high, config.hidden_dim)
        for net in (self.critic, self.actor):
            for name, child in net.named_children():
                if name != "encoder" or config.method != "vae":
                    child.apply(weight_init)
        if config.method != "vae":
            self.actor.encoder.tie_convs_to(self.critic.encoder)  # actor convs = critic convs (Fig. 2)
        if config.freeze_convs:
            for p in self.critic.encoder.convs.parameters():
                p.requires_grad_(False)
        self.critic_target = copy.deepcopy(self.critic)
        self.decoder = None
        if config.method == "sac_ae":
            self.decoder = Decoder(frames, h, w, critic_encoder.feature_shape, config.latent_dim)
            self.decoder.apply(weight_init)
        self.log_alpha = nn.Parameter(torch.tensor(np.log(config.init_temperature), dtype=torch.float32))
        self.target_entropy = -float(len(action_spec.low))
        self.to(self.device)

        trainable_encoder = config.method != "vae"
        # The actor's convolutions are the critic's and learn from the critic (and decoder) only; a
        # distilled student has no critic to learn them from, so its actor loss trains them.
        actor_params = [p for n, p in self.actor.named_parameters()
                        if config.method == "distill" or not n.startswith("encoder.convs")]
        self.actor_optimizer = torch.optim.Adam([p for p in actor_params if p.requires_grad],
                                                lr=config.actor_lr, betas=(config.actor_beta, 0.999))
        self.critic_optimizer = torch.optim.Adam([p for p in self.critic.parameters() if p.requires_grad],
                                                 lr=config.critic_lr, betas=(config.critic_beta, 0.999))
        self.alpha_optimizer = torch.optim.Adam([self.log_alpha], lr=config.alpha_lr, betas=(config.alpha_beta, 0.999))
        if self.decoder is not None and trainable_encoder:
            self.encoder_optimizer = torch.optim.Adam(self.critic.encoder.parameters(), lr=config.encoder_lr)
            self.decoder_optimizer = torch.optim.Adam(self.decoder.parameters(), lr=config.decoder_lr,
                                                      weight_decay=config.decoder_weight_lambda)
        self.updates = 0

    # ------------------------------------------------------------------ inputs
    def _inputs(self, depth_m: torch.Tensor, state: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.normalize_depth(depth_m), self.state_features(state)

    @property
    def alpha(self) -> torch.Tensor:
        return self.log_alpha.exp()

    @torch.no_grad()
    def act(self, depth_m: np.ndarray, state: np.ndarray, explore: bool) -> np.ndarray:
        """Physical actions [B, 3] for a batch of observations (sampled when exploring)."""
        pixels, st = self._inputs(torch.as_tensor(depth_m, device=self.device, dtype=torch.float32),
                                  torch.as_tensor(state, device=self.device, dtype=torch.float32))
        if explore:
            unit, _, _ = self.actor.sample(pixels, st)
        else:
            unit = self.actor.deterministic(pixels, st)
        return self.actor.to_physical(unit).cpu().numpy()

    def to_unit_action(self, action: np.ndarray) -> np.ndarray:
        mid = self.actor.action_mid.cpu().numpy()
        half = self.actor.action_half.cpu().numpy()
        return np.clip((action - mid) / half, -1.0, 1.0)

    # ------------------------------------------------------------------ updates
    def critic_state(self, state: torch.Tensor, privileged: torch.Tensor | None) -> torch.Tensor:
        """The critic's state input: the actor's state features, then the privileged ones where the
        critic has them (``privileged_critic``)."""
        if not self.privileged_dim:
            return state
        if privileged is None:
            raise ValueError("this agent's critic is privileged: the batch must carry 'privileged' and "
                             "'next_privileged' (sitl.learn.privileged)")
        return torch.cat([state, privileged], dim=1)

    def update_critic(self, pixels, state, action, reward, next_pixels, next_state, discount,
                      privileged=None, next_privileged=None) -> dict:
        """Eqs. 5-6: regress both Q-functions on the soft Bellman target of the target critic.

        ``discount`` is gamma (gamma^n for n-step returns), 0 after a terminal step.
        ``privileged``/``next_privileged``: the critic's extra inputs (asymmetric critic only).
        """
        with torch.no_grad():
            next_action, next_log_prob, _ = self.actor.sample(next_pixels, next_state)
            target_q1, target_q2 = self.critic_target(next_pixels, self.critic_state(next_state, next_privileged),
                                                      next_action)
            target_v = torch.min(target_q1, target_q2) - self.alpha.detach() * next_log_prob
            target_q = reward + discount * target_v
        q1, q2 = self.critic(pixels, self.critic_state(state, privileged), action)
        loss = F.mse_loss(q1, target_q) + F.mse_loss(q2, target_q)
        self.critic_optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.critic_optimizer.step()
        return {"losses/critic": loss.item(), "values/q": q1.mean().item()}

    def update_actor_and_alpha(self, pixels, state, teacher_action=None, teacher_valid=None,
                               bc_weight: float = 0.0, privileged=None) -> dict:
        """Eq. 7 with the convolutions detached; then the temperature towards the target entropy.

        ``bc_weight`` > 0 adds a behaviour-cloning term (teacher-guided SAC+AE, not in the paper):
        the squared distance of the actor's mean action ``tanh(mu)`` from the teacher's unit
        action where ``teacher_valid``, scaled by ``bc_weight`` times the batch's mean |Q| (at least 1)
        so that its pull keeps its proportion to eq. 7's as the values grow (as in TD3+BC, Fujimoto &
        Gu 2021) and still pulls while the critic knows nothing yet. ``privileged``: the critic's
        extra input (asymmetric critic only; the actor never sees it).
        """
        critic_state = self.critic_state(state, privileged)
        if self.config.method == "vae":
            latent = self.actor.encoder(pixels)
            action, log_prob, log_std = self.actor.sample_from_latent(latent, state)
            q1, q2 = self.critic(pixels, critic_state, action, detach_encoder=True)
        else:
            # The actor's convolutions are the critic's: compute them once, without gradient.
            with torch.no_grad():
                features = self.critic.encoder.conv_features(pixels)
            latent = self.actor.encoder.head(features)
            action, log_prob, log_std = self.actor.sample_from_latent(latent, state)
            q1, q2 = self.critic.q_from_latent(self.critic.encoder.head(features).detach(), critic_state, action)
        q = torch.min(q1, q2)
        actor_loss = (self.alpha.detach() * log_prob - q).mean()
        info = {}
        if bc_weight > 0.0 and teacher_action is not None and teacher_valid.sum() > 0:
            mean_action = torch.tanh(self.actor.distribution_from_latent(latent, state)[0])
            per_sample = (mean_action - teacher_action).pow(2).sum(-1, keepdim=True)
            bc_loss = (per_sample * teacher_valid).sum() / teacher_valid.sum()
            actor_loss = actor_loss + bc_weight * q.abs().mean().detach().clamp(min=1.0) * bc_loss
            info = {"losses/teacher_bc": bc_loss.item(), "values/teacher_bc_weight": bc_weight}
        self.actor_optimizer.zero_grad(set_to_none=True)
        actor_loss.backward()
        self.actor_optimizer.step()
        alpha_loss = (self.alpha * (-log_prob - self.target_entropy).detach()).mean()
        self.alpha_optimizer.zero_grad(set_to_none=True)
        alpha_loss.backward()
        self.alpha_optimizer.step()
        return info | {"losses/actor": actor_loss.item(), "losses/alpha": alpha_loss.item(),
                       "values/alpha": self.alpha.item(), "values/entropy": -log_prob.mean().item()}

    def update_imitation(self, pixels, state, teacher_action, teacher_valid) -> dict:
        """``distill``: regress the actor's mean action ``tanh(mu)`` (what the exported policy flies) on
        the teacher's unit action where ``teacher_valid``; the encoder learns from this loss alone."""
        mean_action = torch.tanh(self.actor.distribution(pixels, state)[0])
        per_sample = (mean_action - teacher_action).pow(2).sum(-1, keepdim=True)
        loss = (per_sample * teacher_valid).sum() / teacher_valid.sum().clamp(min=1.0)
        self.actor_optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.actor_optimizer.step()
        return {"losses/imitation": loss.item()}

    def update_decoder(self, pixels) -> dict:
        """Eq. 8 (RAE): reconstruction + lambda_z |z|^2; lambda_phi |phi|^2 is the decoder's weight decay."""
        latent = self.critic.encoder(pixels)
        recon = self.decoder(latent)
        rec_loss = F.mse_loss(recon, pixels)
        latent_loss = (0.5 * latent.pow(2).sum(1)).mean()
        loss = rec_loss + self.config.decoder_latent_lambda * latent_loss
        self.encoder_optimizer.zero_grad(set_to_none=True)
        self.decoder_optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.encoder_optimizer.step()
        self.decoder_optimizer.step()
        return {"losses/reconstruction": rec_loss.item()}

    def copy_critic_to_target(self) -> None:
        """Make the target critic the critic itself: where a run starts from networks whose critic was
        never trained (a distilled student's), the old target would only pull towards stale weights."""
        self.critic_target.load_state_dict(self.critic.state_dict())

    def soft_update_targets(self) -> None:
        """EMA of the critic (tau_Q) and of its encoder (tau_enc), Table I."""
        cfg = self.config
        with torch.no_grad():
            for name in ("q1", "q2"):
                for p, tp in zip(getattr(self.critic, name).parameters(), getattr(self.critic_target, name).parameters()):
                    tp.lerp_(p, cfg.critic_tau)
            if cfg.method != "vae":
                for p, tp in zip(self.critic.encoder.parameters(), self.critic_target.encoder.parameters()):
                    tp.lerp_(p, cfg.encoder_tau)

    def update(self, batch: dict[str, torch.Tensor], bc_weight: float = 0.0) -> dict:
        """One gradient step of every part due at this update count (``bc_weight``: see
        :meth:`update_actor_and_alpha`; the batch then carries ``teacher_action``/``teacher_valid``)."""
        cfg = self.config
        pixels, state = self._inputs(batch["depth"], batch["state"])
        if cfg.method == "distill":
            self.updates += 1
            if cfg.distill_shift_px:
                pixels = random_shift(pixels, cfg.distill_shift_px)
            return self.update_imitation(pixels, state, batch["teacher_action"], batch["teacher_valid"])
        next_pixels, next_state = self._inputs(batch["next_depth"], batch["next_state"])
        if cfg.method == "drq":
            pixels, next_pixels = random_shift(pixels, cfg.drq_pad), random_shift(next_pixels, cfg.drq_pad)
        info = self.update_critic(pixels, state, batch["action"], batch["reward"], next_pixels, next_state,
                                  batch["discount"], batch.get("privileged"), batch.get("next_privileged"))
        if self.updates >= cfg.actor_delay_updates and self.updates % cfg.actor_update_freq == 0:
            info |= self.update_actor_and_alpha(pixels, state, batch.get("teacher_action"), batch.get("teacher_valid"),
                                                bc_weight, batch.get("privileged"))
        if self.updates % cfg.critic_target_update_freq == 0:
            self.soft_update_targets()
        if self.decoder is not None and self.updates % cfg.decoder_update_freq == 0:
            info |= self.update_decoder(pixels)
        self.updates += 1
        return info

    # ------------------------------------------------------------------ checkpoints
    def optimizers(self) -> dict[str, torch.optim.Optimizer]:
        names = ["actor_optimizer", "critic_optimizer", "alpha_optimizer", "encoder_optimizer", "decoder_optimizer"]
        return {n: getattr(self, n) for n in names if hasattr(self, n)}

    def checkpoint(self) -> dict:
        return {"model": self.state_dict(), "updates": self.updates, "method": self.config.method,
                "optimizers": {n: o.state_dict() for n, o in self.optimizers().items()}}

    def restore(self, checkpoint: dict) -> None:
        self.load_state_dict(checkpoint["model"])
        self.updates = checkpoint["updates"]
        for name, opt in self.optimizers().items():
            opt.load_state_dict(checkpoint["optimizers"][name])

    def apply_learning_rates(self) -> None:
        """Set every optimiser's learning rate from this agent's config.

        A restored optimiser state carries the learning rate it was saved with; a later
        curriculum stage (``--init-from``) may ask for another one.
        """
        for name, opt in self.optimizers().items():
            lr = getattr(self.config, name.replace("_optimizer", "_lr"))
            for group in opt.param_groups:
                group["lr"] = lr
