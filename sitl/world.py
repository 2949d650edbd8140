"""``python -m sitl.world``: depth cameras for external autopilots (see :mod:`sitl.realtime.depth_bridge`)."""

from sitl.realtime.depth_bridge import main

if __name__ == "__main__":
    raise SystemExit(main())
