"""The RL+VAE baseline's image model: a VAE trained on depth images, then frozen.

The paper's protocol: collect depth images by flying a trained policy in the swarm, train a
VAE on them, freeze it and learn SAC on its latent mean. The encoder has the same conv stack
as SAC+AE's, so the comparison isolates how the representation is learned.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from sitl.learn.networks import Decoder, DepthNormalizer, Encoder, weight_init


class VAEEncoder(Encoder):
    """SAC+AE's conv stack -> (mean, log-variance) of a diagonal Gaussian; ``forward`` gives the mean.

    ``fc`` of the base class is the mean head; its LayerNorm and tanh are not used.
    """

    def __init__(self, frames: int, height: int, width: int, latent_dim: int = 50, filters: int = 32) -> None:
        super().__init__(frames, height, width, latent_dim, filters)
        self.fc_logvar = nn.Linear(self.fc.in_features, latent_dim)

    def moments(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        f = self.conv_features(x)
        return self.fc(f), self.fc_logvar(f)

    def forward(self, x: torch.Tensor, detach_convs: bool = False) -> torch.Tensor:
        return self.fc(self.conv_features(x))


def train_vae(images_m: np.ndarray, max_range_m: float, latent_dim: int = 50, epochs: int = 20, batch_size: int = 128,
              lr: float = 1e-3, beta: float = 1.0, seed: int = 0, progress=None) -> tuple[VAEEncoder, list[float]]:
    """Train a VAE on stacked depth images [K, frames, H, W] (metres); return the frozen encoder and losses."""
    torch.manual_seed(seed)
    frames, height, width = images_m.shape[1:]
    encoder = VAEEncoder(frames, height, width, latent_dim)
    decoder = Decoder(frames, height, width, encoder.feature_shape, latent_dim)
    encoder.apply(weight_init)
    decoder.apply(weight_init)
    normalize = DepthNormalizer(max_range_m)
    data = normalize(torch.as_tensor(images_m, dtype=torch.float32))
    optimizer = torch.optim.Adam([*encoder.parameters(), *decoder.parameters()], lr=lr)
    losses = []
    for _ in range(epochs):
        order = torch.randperm(len(data))
        total = 0.0
        for start in range(0, len(data), batch_size):
            x = data[order[start:start + batch_size]]
            mu, logvar = encoder.moments(x)
            z = mu + torch.randn_like(mu) * (0.5 * logvar).exp()
            recon = decoder(z)
            rec = F.mse_loss(recon, x, reduction="sum") / len(x)
            kl = -0.5 * torch.sum(1 + logvar - mu.pow(2) - logvar.exp()) / len(x)
            loss = rec + beta * kl
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            total += loss.item() * len(x)
        losses.append(total / len(data))
        if progress is not None:
            progress(len(losses), losses[-1])
    encoder.eval()
    for p in encoder.parameters():
        p.requires_grad_(False)
    return encoder, losses
