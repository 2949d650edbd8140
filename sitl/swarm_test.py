"""``python -m sitl.swarm_test``: evaluate a policy in the paper's scenarios (the code is :mod:`sitl.eval.evaluate`)."""

from sitl.eval.evaluate import main

if __name__ == "__main__":
    raise SystemExit(main())
