"""Average a training stage's validated snapshots into one policy (weight averaging, no selection).

The recipe's last stage keeps a snapshot at every validation and exports the one with the best
(rescored) validation success. Picking the best of a few noisy validations adds its own noise to
the exported policy; averaging the snapshots' weights (Izmailov et al. 2018, "Averaging weights
leads to wider optima") is the usual alternative. This tool writes that average as a policy file
so it can be flown beside the selected one::

    python -m sitl.learn.average runs/privcritic/s0/stage4-anneal --out runs/privavg/s0/policy.pt \\
        --eval paper:random-medium,flown:random-medium,flown:circle-n8,flown:obstacles

Every floating-point tensor of the agent (encoder, actor, critics, temperature) is the plain mean
over the snapshots; integer buffers are taken from the first. The exported file keeps the stage's
policy.json provenance (camera, training conditions, recipe) without the selected policy's test
evaluation, and records the averaged snapshots under ``provenance.averaged_snapshots``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

from companion.policy import PolicyFileError, load_policy
from sitl.cli_args import ArgumentParser, int_list
from sitl.learn.config import make_sim_config
from sitl.learn.export import export_policy
from sitl.learn.rescore import load_run
from sitl.learn.sweep import add_policy_eval_options, eval_cells, evaluation_settings, fly_policy_cells
from sitl.learn.trainer import load_training_file, make_agent


def average_state_dicts(states: list[dict[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
    """The element-wise mean of floating-point tensors; other tensors from the first state."""
    if not states:
        raise ValueError("nothing to average")
    keys = set(states[0])
    for state in states[1:]:
        if set(state) != keys:
            raise ValueError("the snapshots hold different networks")
    averaged = {}
    for key, first in states[0].items():
        if torch.is_floating_point(first):
            averaged[key] = torch.stack([s[key].to(torch.float64) for s in states]).mean(0).to(first.dtype)
        else:
            averaged[key] = first.clone()
    return averaged


def average_stage(stage_dir: Path, out: Path, updates: list[int] | None = None) -> list[int]:
    """Write the average of ``stage_dir``'s snapshots (all validated ones, or ``updates``) as ``out``.

    Returns the update counts averaged. The stage must have exported its own ``policy.pt`` (its
    metadata is the provenance of the average).
    """
    cfg, agent_cfg, rows = load_run(stage_dir)
    chosen = sorted(r["updates"] for r in rows) if updates is None else sorted(updates)
    missing = [u for u in chosen if not (stage_dir / "snapshots" / f"agent_{u}.pt").is_file()]
    if missing:
        raise ValueError(f"{stage_dir}: no snapshot at {', '.join(map(str, missing))} updates")
    try:
        selected = load_policy(stage_dir / "policy.pt", check_forward=False)
    except PolicyFileError as err:
        raise ValueError(f"{stage_dir}: needs the stage's exported policy.pt for its metadata ({err})") from None
    states = [load_training_file(stage_dir / "snapshots" / f"agent_{u}.pt") for u in chosen]
    agent = make_agent(agent_cfg, make_sim_config(cfg, 1))
    agent.load_state_dict(average_state_dicts(states))
    agent.eval()
    provenance = {k: v for k, v in selected.metadata["provenance"].items()
                  if k != "git_commit" and not k.startswith("evaluation")}
    provenance["averaged_snapshots"] = {"stage": str(stage_dir), "updates": chosen,
                                        "replaces_selected_updates": _selected_updates(stage_dir)}
    out.parent.mkdir(parents=True, exist_ok=True)
    export_policy(agent, out, selected.control_period_s, provenance, selected.task,
                  governor=selected.governor)
    return chosen


def _selected_updates(stage_dir: Path) -> int | None:
    """The snapshot the stage itself exported (its recipe's choice), when recorded."""
    recipe_state = stage_dir.parent / "recipe.json"
    if recipe_state.is_file():
        for stage in json.loads(recipe_state.read_text()).get("stages", []):
            if Path(stage.get("run_dir", "")).name == stage_dir.name:
                return stage.get("selected_updates")
    return None


def build_parser() -> argparse.ArgumentParser:
    parser = ArgumentParser(prog="python -m sitl.learn.average", description=__doc__,
                            formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("stage_dir", type=Path, metavar="STAGE_DIR",
                        help="a training stage's run directory (config.json, snapshots/, policy.pt)")
    parser.add_argument("--out", type=Path, required=True, help="the averaged policy file to write (.pt)")
    parser.add_argument("--updates", type=int_list(1), default=None,
                        help="average only these snapshots, comma-separated update counts (default: every validated one)")
    add_policy_eval_options(parser)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    torch.set_num_threads(args.threads)
    try:
        chosen = average_stage(args.stage_dir, args.out, args.updates)
    except (ValueError, OSError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(f"wrote {args.out}: the mean of {len(chosen)} snapshots ({', '.join(map(str, chosen))} updates)", flush=True)
    if args.eval:
        fly_policy_cells(eval_cells(args.stage_dir, args.eval, evaluation_settings(args.eval_episodes), policy=args.out),
                         args.out.parent)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
