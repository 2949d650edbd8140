"""``python -m sitl.rescore``: re-validate a run's snapshots on more episodes and scenes (the code is :mod:`sitl.learn.rescore`)."""

from sitl.learn.rescore import main

if __name__ == "__main__":
    raise SystemExit(main())
