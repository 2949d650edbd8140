"""``python -m sitl.swarm_test``: evaluate a policy in the paper's scenarios (the command line is :mod:`sitl.eval.cli`)."""

from sitl.eval.cli import main

if __name__ == "__main__":
    raise SystemExit(main())
