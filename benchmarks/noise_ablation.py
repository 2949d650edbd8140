"""What each part of the camera noise costs a policy: one flown-protocol cell, each part switched off in turn.

Flies one cell of ``python -m sitl.swarm_test flown`` (default ``random-medium``: its scenes, start jitter,
time limit and held-out test seeds) with the policy's camera

* ``off``: perfect depth;
* ``full``: :class:`sitl.sim.camera.StereoNoise` as the protocol flies it (holes at depth edges only in the
  stereo occlusion shadow, ``edge_holes="shadow"``);
* ``training``: the noise the recipes train with (``TRAINING_STEREO_NOISE``: holes on both sides of every
  depth edge, the protocol's model until session 35);
* ``no_<part>``: ``full`` without one part (Gaussian error, far holes, edge holes, dropouts, the blob);

and prints success, UAV-UAV collisions, timeouts and average speed per variant, then one JSON object as
the last line. The noise draws share the episodes' generator, so beyond the first batch of worlds the
variants fly different episodes: differences within a cell's ~±1.2 points (500 episodes) are the draw.

Usage: ``python benchmarks/noise_ablation.py [--policy models/policy.pt] [--cell random-medium]
[--episodes 500] [--variants off,full,...] [--smoke]`` (``--smoke``: 2 episodes of ``off`` and ``full``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from sitl.learn.config import TRAINING_STEREO_NOISE  # noqa: E402
from sitl.sim.camera import StereoNoise  # noqa: E402

#: The variants by name: None is perfect depth.
VARIANTS: dict[str, StereoNoise | None] = {
    "off": None,
    "full": StereoNoise(),
    "training": TRAINING_STEREO_NOISE,
    "no_gauss": StereoNoise(subpixel_px=0.0),
    "no_far_holes": StereoNoise(far_hole_prob=0.0),
    "no_edge_holes": StereoNoise(edge_hole_prob=0.0),
    "no_dropout": StereoNoise(dropout_prob=0.0),
    "no_blob": StereoNoise(blob_prob=0.0),
}


def _variant_list(text: str) -> list[str]:
    names = [v.strip() for v in text.split(",") if v.strip()]
    unknown = [n for n in names if n not in VARIANTS]
    if not names or unknown:
        raise argparse.ArgumentTypeError(f"unknown variant(s) {', '.join(unknown) or repr(text)}; "
                                         f"choose from {', '.join(VARIANTS)}")
    return names


def main() -> int:
    from sitl.eval.evaluate import evaluate_method
    from sitl.eval.flown import FLOWN_CELL_NAMES, flown_cells
    from sitl.eval.methods import EvaluationError, resolve_method

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--policy", default="models/policy.pt", help="policy file (default models/policy.pt)")
    parser.add_argument("--cell", default="random-medium", choices=FLOWN_CELL_NAMES,
                        help="the flown protocol's cell (default random-medium)")
    parser.add_argument("--episodes", type=int, default=500, help="episodes per variant (default 500)")
    parser.add_argument("--seed", type=int, default=0, help="evaluation seed, as swarm_test's (default 0)")
    parser.add_argument("--variants", type=_variant_list, default=list(VARIANTS),
                        help=f"comma-separated, from {', '.join(VARIANTS)} (default all)")
    parser.add_argument("--smoke", action="store_true", help="CI check: 2 episodes of off and full")
    args = parser.parse_args()
    if args.smoke:
        args.episodes, args.variants = 2, ["off", "full"]
    if args.episodes < 1:
        parser.error(f"--episodes must be >= 1, got {args.episodes}")
    try:
        method = resolve_method(args.policy)
    except (EvaluationError, OSError, ValueError) as exc:
        print(f"noise_ablation: {exc}", file=sys.stderr)
        return 2
    (cell,) = [c for c in flown_cells(args.episodes, args.seed, jsbsim=True) if c.name == args.cell]
    rows = {}
    print(f"{args.policy}, flown {args.cell}, {args.episodes} episodes, seed {args.seed}")
    print(f"{'variant':>14} {'success':>8} {'UAV-UAV':>8} {'timeout':>8} {'speed m/s':>10}")
    for name in args.variants:
        noise = VARIANTS[name]
        settings = dataclasses.replace(cell.settings, camera_noise=noise is not None,
                                       noise_model=noise or StereoNoise())
        s = evaluate_method(method, settings, progress=False).summary
        rows[name] = {"success": round(s["success_rate"], 4), "ci95": round(s["success_ci95_half_width"], 4),
                      "collision_uav": round(s["collision_uav_rate"], 4), "timeout": round(s["timeout_rate"], 4),
                      "average_speed_m_s": round(s["average_speed_m_s"]["mean"], 3)}
        r = rows[name]
        print(f"{name:>14} {r['success']:8.3f} {r['collision_uav']:8.3f} {r['timeout']:8.3f} {r['average_speed_m_s']:10.2f}",
              flush=True)
    print(json.dumps({"benchmark": "noise_ablation", "policy": args.policy, "cell": args.cell,
                      "episodes": args.episodes, "seed": args.seed, "variants": rows}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
