"""The input check inside every saved policy file.

A policy file is also run without this package: ``torch.jit.load("policy.pt")`` in someone's
own evaluator. Fed a depth image of the wrong size, the bare network fails deep inside with
torch's "mat1 and mat2 shapes cannot be multiplied", which names neither the input nor the size
it wanted. :func:`companion.policy.save_policy` therefore wraps the network in
:class:`ShapeCheckedPolicy`, which compares the inputs with ``policy.json``'s camera first and
raises a ``ValueError`` that says what it expected. The ONNX export leaves the check out: an
ONNX graph declares its input shapes, and onnxruntime checks them itself.

Imported only where torch is (saving a policy file), like the rest of the TorchScript side.
"""

from __future__ import annotations

import torch
from torch import nn

#: The wrapper's class name as TorchScript records it (``ScriptModule.original_name``).
CHECKED_POLICY_NAME = "ShapeCheckedPolicy"


class ShapeCheckedPolicy(nn.Module):
    """``policy(depth, state)`` after checking depth is [B, frames, height, width] and state [B, state_dim]."""

    def __init__(self, policy: nn.Module, frames: int, height: int, width: int, state_dim: int) -> None:
        super().__init__()
        self.policy = policy
        self.frames = int(frames)
        self.height = int(height)
        self.width = int(width)
        self.state_dim = int(state_dim)

    def forward(self, depth: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
        if (depth.dim() != 4 or depth.shape[1] != self.frames or depth.shape[2] != self.height
                or depth.shape[3] != self.width):
            raise ValueError("depth must be [batch, {}, {}, {}] (frames, height, width of policy.json's camera), "
                             "got {}".format(self.frames, self.height, self.width, depth.shape))
        if state.dim() != 2 or state.shape[1] != self.state_dim or state.shape[0] != depth.shape[0]:
            raise ValueError("state must be [batch, {}] with depth's batch {}, got {}".format(
                self.state_dim, depth.shape[0], state.shape))
        return self.policy(depth, state)


def is_shape_checked(module: nn.Module) -> bool:
    """Whether ``module`` (a Python or TorchScript module) is already a :class:`ShapeCheckedPolicy`."""
    return getattr(module, "original_name", type(module).__name__) == CHECKED_POLICY_NAME


def unwrap_checked(module: nn.Module) -> nn.Module:
    """The network inside a :class:`ShapeCheckedPolicy` (Python or TorchScript); any other module as it is."""
    return module.policy if is_shape_checked(module) else module
