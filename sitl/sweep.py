"""``python -m sitl.sweep``: training runs over seeds and a grid as Ray tasks (the command line is :mod:`sitl.learn.sweep`)."""

from sitl.learn.sweep import main

if __name__ == "__main__":
    raise SystemExit(main())
