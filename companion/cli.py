"""``companion``: the onboard process's command line.

This release ships the observation and action contract shared with the simulator;
``companion --describe`` prints it as JSON. The MAVLink flight loop
(``companion --connect udp:14540 --model policy.pt``) is not part of this release yet:
asking for it fails with a clear message instead of pretending to fly.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict

from companion.spec import DEFAULT_ACTION_SPEC, DEFAULT_CAMERA_SPEC, STATE_NAMES


def describe() -> dict:
    """The observation/action contract as a JSON-ready dict."""
    return {
        "frames": "world: local NED; body: heading frame FRD (x forward, y right, z down), yaw positive right",
        "depth": {**DEFAULT_CAMERA_SPEC.to_dict(), "units": "metres, planar", "order": "oldest frame first"},
        "state": list(STATE_NAMES),
        "action": asdict(DEFAULT_ACTION_SPEC),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="companion", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--describe", action="store_true", help="print the observation/action contract as JSON")
    parser.add_argument("--connect", help="MAVLink connection (flight loop not in this release)")
    parser.add_argument("--model", help="policy file (flight loop not in this release)")
    args = parser.parse_args(argv)
    if args.describe:
        print(json.dumps(describe(), indent=2))
        return 0
    print("companion: the MAVLink flight loop is not part of this release yet; "
          "`companion --describe` prints the observation/action contract", file=sys.stderr)
    return 2


if __name__ == "__main__":
    raise SystemExit(main())
