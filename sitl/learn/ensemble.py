"""Several trained policies flown as one: the mean of their actions (an ensemble of seeds).

Independent training runs (seeds) of one recipe make different mistakes; averaging their
commands is the usual way to ask whether those mistakes cancel. This tool writes the ensemble
as an ordinary policy file (same inputs, output and ``policy.json`` contract as its members),
so every evaluation and the companion fly it unchanged::

    python -m sitl.learn.ensemble runs/ff/s0/policy.pt runs/ff/s1/policy.pt runs/ff/s2/policy.pt \\
        --out runs/ensemble/policy.pt --eval flown:random-medium,flown:circle-n8

The members must share the camera, control period, state layout, action bounds and task
(``policy.json``); the file keeps the first member's metadata without its test evaluation and
records the members (path and SHA-256 prefix) under ``provenance.ensemble``. Inference costs
one forward pass per member. Averaging is per action component after each member's own
``tanh`` squashing, so the result stays inside the bounds; where members disagree on a side
(one climbs, one descends) the mean can be neither.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch
from torch import nn

from companion.checked_policy import unwrap_checked
from companion.policy import PolicyFileError, load_policy, save_policy
from sitl.cli_args import ArgumentParser
from sitl.eval.methods import file_digest
from sitl.learn.sweep import add_policy_eval_options, evaluation_settings, fly_policy_cells

#: policy.json fields the members must agree on (the contract the ensemble's file declares).
SHARED_FIELDS = ("depth", "control_period_s", "state_names", "action", "body_frame", "task")


class MeanActionEnsemble(nn.Module):
    """``policy(depth, state)``: the mean of the members' actions [B, action_dim]."""

    def __init__(self, members: list[nn.Module]) -> None:
        super().__init__()
        self.members = nn.ModuleList(members)
        self.count = float(len(members))

    def forward(self, depth: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
        actions: list[torch.Tensor] = []
        for member in self.members:
            actions.append(member(depth, state))
        total = actions[0]
        for action in actions[1:]:
            total = total + action
        return total / self.count


def build_ensemble(paths: list[Path], out: Path) -> dict:
    """Write the mean-action ensemble of the policy files ``paths`` to ``out``; returns its metadata."""
    if len(paths) < 2:
        raise ValueError("an ensemble needs at least two policy files")
    loaded = []
    for path in paths:
        if path.suffix == ".onnx":
            raise ValueError(f"{path}: members must be TorchScript policy files (.pt)")
        try:
            loaded.append(load_policy(path))
        except PolicyFileError as err:
            raise ValueError(str(err)) from None
    first = loaded[0].metadata
    for path, policy in zip(paths[1:], loaded[1:]):
        for key in SHARED_FIELDS:
            if policy.metadata.get(key) != first.get(key):
                raise ValueError(f"{path}: its policy.json {key!r} differs from {paths[0]}'s; "
                                 "members must share camera, control period, state, actions and task")
    metadata = dict(first)
    provenance = {k: v for k, v in first["provenance"].items()
                  if k != "git_commit" and not k.startswith("evaluation")}
    provenance["ensemble"] = {"rule": "mean action",
                              "members": [{"path": str(p), "sha256": file_digest(p)} for p in paths]}
    metadata["provenance"] = provenance
    save_policy(MeanActionEnsemble([unwrap_checked(p.module) for p in loaded]), metadata, out)  # scripts it
    return metadata


def build_parser() -> argparse.ArgumentParser:
    parser = ArgumentParser(prog="python -m sitl.learn.ensemble", description=__doc__,
                            formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("policies", type=Path, nargs="+", metavar="POLICY",
                        help="two or more policy files (.pt) with the same policy.json contract")
    parser.add_argument("--out", type=Path, required=True, help="the ensemble policy file to write (.pt)")
    add_policy_eval_options(parser)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    torch.set_num_threads(args.threads)
    try:
        metadata = build_ensemble(args.policies, args.out)
    except (ValueError, OSError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(f"wrote {args.out}: the mean action of {len(args.policies)} policies", flush=True)
    if args.eval:
        from sitl.eval.paper import PaperCell  # noqa: PLC0415 - only when evaluating

        settings = evaluation_settings(args.eval_episodes)
        method = metadata["provenance"].get("method", "sac_ae")  # the members' training method labels the cells
        fly_policy_cells([(label, PaperCell(label.replace(":", "-"), method, str(args.out), settings[label]))
                          for label in args.eval], args.out.parent)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
