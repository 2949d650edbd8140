"""``python -m sitl.train``: train the shared collision-avoidance policy (the command line is :mod:`sitl.learn.cli`)."""

from sitl.learn.cli import main

if __name__ == "__main__":
    raise SystemExit(main())
