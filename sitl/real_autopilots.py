"""``python -m sitl.real_autopilots``: fly real ArduCopter / PX4 SITL swarms and measure them.

    python -m sitl.real_autopilots circle --autopilot px4 --n 8 --out runs/px4_circle8
    python -m sitl.real_autopilots stop --autopilot arducopter --signal TERM --out runs/ap_sigterm
    python -m sitl.real_autopilots fit runs/px4_circle8      # each vehicle's velocity response, fitted
    python -m sitl.real_autopilots events runs/px4_circle8   # each autopilot failsafe and its reason

See docs/real_autopilots.md and :mod:`sitl.realtime.autopilot_sitl`.
"""

from sitl.realtime.autopilot_sitl import main

if __name__ == "__main__":
    raise SystemExit(main())
