"""Export a trained actor as a ``policy.pt`` that follows :mod:`companion.policy`'s contract."""

from __future__ import annotations

import copy
import subprocess
from pathlib import Path

import torch
from torch import nn

from companion.policy import build_metadata, save_policy
from companion.spec import DEFAULT_TASK_SPEC, TaskSpec
from sitl.learn.agent import SacAeAgent


class ExportedPolicy(nn.Module):
    """Deterministic actor: raw depth (m) and state in, physical actions within the bounds out."""

    def __init__(self, agent: SacAeAgent) -> None:
        super().__init__()
        self.encoder = copy.deepcopy(agent.actor.encoder).cpu()  # own copy of the tied convolutions
        self.trunk = copy.deepcopy(agent.actor.trunk).cpu()
        self.max_range_m = float(agent.camera.max_range_m)
        self.state_features = copy.deepcopy(agent.state_features).cpu()
        self.register_buffer("action_mid", agent.actor.action_mid.detach().cpu().clone())
        self.register_buffer("action_half", agent.actor.action_half.detach().cpu().clone())
        self.action_dim = int(self.action_mid.numel())

    def forward(self, depth: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
        pixels = torch.clamp(depth, 0.0, self.max_range_m) / self.max_range_m - 0.5
        latent = self.encoder(pixels)
        mu = self.trunk(torch.cat([latent, self.state_features(state)], dim=1))[:, : self.action_dim]
        return self.action_mid + self.action_half * torch.tanh(mu)


def git_commit() -> str:
    """The current commit of the repository, or 'unknown' outside a git checkout."""
    try:
        out = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, timeout=5,
                             cwd=Path(__file__).resolve().parent)
        return out.stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def export_policy(agent: SacAeAgent, path: str | Path, control_period_s: float, provenance: dict,
                  task: TaskSpec = DEFAULT_TASK_SPEC) -> None:
    """Write ``path`` as a TorchScript policy with ``policy.json`` metadata (``task``: what it was trained for)."""
    module = ExportedPolicy(agent).eval()
    metadata = build_metadata(agent.camera, agent.action_spec, control_period_s,
                              {"git_commit": git_commit(), **provenance}, task)
    save_policy(module, metadata, path)

