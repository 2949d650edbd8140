"""``python -m sitl.collision_anatomy``: who could see whom before each UAV-UAV collision (the code is :mod:`sitl.eval.collision_anatomy`)."""

from sitl.eval.collision_anatomy import main

if __name__ == "__main__":
    raise SystemExit(main())
