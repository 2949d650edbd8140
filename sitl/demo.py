"""``python -m sitl.demo``: a small no-policy demo of the simulator (the code is :mod:`sitl.eval.demo`)."""

from sitl.eval.demo import main

if __name__ == "__main__":
    raise SystemExit(main())
