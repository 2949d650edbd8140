"""``python -m sitl.train``: train the shared collision-avoidance policy (the code is :mod:`sitl.learn.trainer`)."""

from sitl.learn.trainer import main

if __name__ == "__main__":
    raise SystemExit(main())
