"""Networks of SAC+AE (paper III.C, Fig. 2; Yarats et al. 2019): encoder, decoder, actor, critic.

Inputs are normalised here, so every module takes the observation in physical units:
depth in metres ([B, frames, H, W]) and the state vector of :data:`companion.spec.STATE_NAMES`.
"""

from __future__ import annotations

import math

import torch
from torch import nn

#: Divisors that bring the velocity part of the state to order one: forward and down
#: speed (m/s), yaw rate (rad/s).
VELOCITY_SCALE = (2.0, 0.5, 0.5)
GOAL_DISTANCE_SCALE_M = 10.0
STATE_FEATURES = 7  # goal direction (3), goal distance (1), velocity (3)
LOG_STD_MIN, LOG_STD_MAX = -10.0, 2.0  # Table I: actor log-std bounds


def weight_init(module: nn.Module) -> None:
    """Orthogonal init (reference implementation): delta-orthogonal for convolutions."""
    if isinstance(module, nn.Linear):
        nn.init.orthogonal_(module.weight.data)
        module.bias.data.fill_(0.0)
    elif isinstance(module, (nn.Conv2d, nn.ConvTranspose2d)):
        gain = nn.init.calculate_gain("relu")
        module.weight.data.fill_(0.0)
        module.bias.data.fill_(0.0)
        mid = module.weight.size(2) // 2
        nn.init.orthogonal_(module.weight.data[:, :, mid, mid], gain)


def conv_output_side(image_side: int, layers: int = 4) -> int:
    """Side of the encoder's last feature map: first conv stride 2, the rest stride 1, no padding."""
    side = (image_side - 3) // 2 + 1
    return side - 2 * (layers - 1)


class DepthNormalizer(nn.Module):
    """Depth in metres -> [-0.5, 0.5] (the reference's ``obs / 255 - 0.5`` for pixels)."""

    def __init__(self, max_range_m: float) -> None:
        super().__init__()
        self.max_range_m = max_range_m

    def forward(self, depth_m: torch.Tensor) -> torch.Tensor:
        return torch.clamp(depth_m, 0.0, self.max_range_m) / self.max_range_m - 0.5


class StateFeatures(nn.Module):
    """The state vector in physical units -> the features the MLPs see.

    The goal becomes a unit direction and a distance: the bearing stays as clear at 0.5 m
    from the goal as at 20 m, which a plain goal / scale loses near arrival. Distances
    above 2 x ``GOAL_DISTANCE_SCALE_M`` saturate. Remembered sector ranges (``memory_range_m``
    > 0, :class:`companion.spec.MemorySpec`) become closeness in [0, 1]: 0 nothing within the
    range, 1 touching.
    """

    def __init__(self, memory_sectors: int = 0, memory_range_m: float = 1.0) -> None:
        super().__init__()
        self.register_buffer("velocity_scale", torch.tensor(VELOCITY_SCALE, dtype=torch.float32))
        self.goal_distance_scale_m = GOAL_DISTANCE_SCALE_M
        self.memory_sectors = memory_sectors
        self.memory_range_m = memory_range_m
        self.num_features = STATE_FEATURES + memory_sectors

    def forward(self, state: torch.Tensor) -> torch.Tensor:
        goal = state[:, 0:3]
        distance = torch.linalg.vector_norm(goal, dim=1, keepdim=True)
        direction = goal / torch.clamp(distance, min=1e-6)
        scaled = torch.clamp(distance / self.goal_distance_scale_m, max=2.0)
        features = torch.cat([direction, scaled, state[:, 3:6] / self.velocity_scale], dim=1)
        if self.memory_sectors == 0:
            return features
        closeness = 1.0 - torch.clamp(state[:, 6:] / self.memory_range_m, 0.0, 1.0)
        return torch.cat([features, closeness], dim=1)


class Encoder(nn.Module):
    """4 conv layers of 32 3x3 filters (first stride 2), FC to a latent, LayerNorm, tanh."""

    def __init__(self, frames: int, height: int, width: int, latent_dim: int = 50, filters: int = 32) -> None:
        super().__init__()
        self.convs = nn.ModuleList([nn.Conv2d(frames, filters, 3, stride=2)] +
                                   [nn.Conv2d(filters, filters, 3, stride=1) for _ in range(3)])
        self.feature_shape = (filters, conv_output_side(height), conv_output_side(width))
        self.fc = nn.Linear(math.prod(self.feature_shape), latent_dim)
        self.ln = nn.LayerNorm(latent_dim)
        self.latent_dim = latent_dim

    def conv_features(self, x: torch.Tensor) -> torch.Tensor:
        for conv in self.convs:
            x = torch.relu(conv(x))
        return x.flatten(1)

    def head(self, features: torch.Tensor) -> torch.Tensor:
        return torch.tanh(self.ln(self.fc(features)))

    def forward(self, x: torch.Tensor, detach_convs: bool = False) -> torch.Tensor:
        features = self.conv_features(x)
        if detach_convs:
            features = features.detach()
        return self.head(features)

    def tie_convs_to(self, other: "Encoder") -> None:
        """Share conv weights with ``other`` (the actor's convs are the critic's)."""
        for mine, theirs in zip(self.convs, other.convs):
            mine.weight = theirs.weight
            mine.bias = theirs.bias


class Decoder(nn.Module):
    """Mirror of the encoder: FC, 3 stride-1 deconvolutions and a stride-2 one (RAE, eq. 8)."""

    def __init__(self, frames: int, height: int, width: int, feature_shape: tuple[int, int, int],
                 latent_dim: int = 50) -> None:
        super().__init__()
        filters = feature_shape[0]
        self.feature_shape = feature_shape
        self.out_hw = (height, width)
        self.fc = nn.Linear(latent_dim, math.prod(feature_shape))
        self.deconvs = nn.ModuleList([nn.ConvTranspose2d(filters, filters, 3, stride=1) for _ in range(3)] +
                                     [nn.ConvTranspose2d(filters, frames, 3, stride=2, output_padding=1)])

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        x = torch.relu(self.fc(z)).view(-1, *self.feature_shape)
        for deconv in self.deconvs[:-1]:
            x = torch.relu(deconv(x))
        x = self.deconvs[-1](x)
        return x[..., : self.out_hw[0], : self.out_hw[1]]


def mlp(inputs: int, hidden: int, outputs: int) -> nn.Sequential:
    """The paper's 3-layer MLP."""
    return nn.Sequential(nn.Linear(inputs, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(),
                         nn.Linear(hidden, outputs))


class Actor(nn.Module):
    """Squashed Gaussian policy on [latent, state]; actions in physical units within the bounds."""

    def __init__(self, encoder: Encoder, state_dim: int, action_low: torch.Tensor, action_high: torch.Tensor,
                 hidden: int = 1024) -> None:
        super().__init__()
        self.encoder = encoder
        self.trunk = mlp(encoder.latent_dim + state_dim, hidden, 2 * action_low.numel())
        self.register_buffer("action_mid", (action_high + action_low) / 2)
        self.register_buffer("action_half", (action_high - action_low) / 2)

    def distribution(self, pixels: torch.Tensor, state: torch.Tensor, detach_convs: bool = False):
        """Mean and log-std of the pre-tanh Gaussian."""
        return self.distribution_from_latent(self.encoder(pixels, detach_convs=detach_convs), state)

    def distribution_from_latent(self, latent: torch.Tensor, state: torch.Tensor):
        mu, log_std = self.trunk(torch.cat([latent, state], dim=1)).chunk(2, dim=-1)
        log_std = LOG_STD_MIN + 0.5 * (LOG_STD_MAX - LOG_STD_MIN) * (torch.tanh(log_std) + 1)
        return mu, log_std

    def sample(self, pixels: torch.Tensor, state: torch.Tensor, detach_convs: bool = False):
        """(action in [-1, 1], log-prob, log-std) with the reparameterisation trick and tanh correction."""
        return self.sample_from_latent(self.encoder(pixels, detach_convs=detach_convs), state)

    def sample_from_latent(self, latent: torch.Tensor, state: torch.Tensor):
        mu, log_std = self.distribution_from_latent(latent, state)
        std = log_std.exp()
        noise = torch.randn_like(mu)
        pre_tanh = mu + noise * std
        action = torch.tanh(pre_tanh)
        log_prob = (-0.5 * noise.pow(2) - log_std - 0.5 * math.log(2 * math.pi)).sum(-1, keepdim=True)
        log_prob = log_prob - torch.log(torch.relu(1 - action.pow(2)) + 1e-6).sum(-1, keepdim=True)
        return action, log_prob, log_std

    def deterministic(self, pixels: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
        mu, _ = self.distribution(pixels, state)
        return torch.tanh(mu)

    def to_physical(self, unit_action: torch.Tensor) -> torch.Tensor:
        return self.action_mid + self.action_half * unit_action


class Critic(nn.Module):
    """Twin Q-functions on [latent, state, action] sharing one encoder."""

    def __init__(self, encoder: Encoder, state_dim: int, action_dim: int, hidden: int = 1024) -> None:
        super().__init__()
        self.encoder = encoder
        self.q1 = mlp(encoder.latent_dim + state_dim + action_dim, hidden, 1)
        self.q2 = mlp(encoder.latent_dim + state_dim + action_dim, hidden, 1)

    def forward(self, pixels: torch.Tensor, state: torch.Tensor, action: torch.Tensor, detach_encoder: bool = False):
        latent = self.encoder(pixels, detach_convs=detach_encoder)
        if detach_encoder:
            latent = latent.detach()
        return self.q_from_latent(latent, state, action)

    def q_from_latent(self, latent: torch.Tensor, state: torch.Tensor, action: torch.Tensor):
        x = torch.cat([latent, state, action], dim=1)
        return self.q1(x), self.q2(x)
