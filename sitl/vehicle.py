"""``python -m sitl.vehicle``: simulated PX4/ArduCopter vehicles (see :mod:`sitl.realtime.vehicle`)."""

from sitl.realtime.vehicle import main

if __name__ == "__main__":
    raise SystemExit(main())
