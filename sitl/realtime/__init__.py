"""The real-time MAVLink layer: processes that run on the wall clock beside real ``companion`` processes.

* :mod:`sitl.realtime.vehicle` — simulated PX4/ArduCopter vehicles (``python -m sitl.vehicle``);
* :mod:`sitl.realtime.depth_bridge` — depth cameras for autopilots simulated elsewhere
  (PX4/ArduPilot SITL; ``python -m sitl.world``);
* :mod:`sitl.realtime.mavlink_autopilot` — the flight-mode logic and telemetry of one simulated autopilot;
* :mod:`sitl.realtime.udp_endpoint` — the one MAVLink UDP endpoint of the simulator side;
* :mod:`sitl.realtime.camera_feed` — render-and-send of depth frames and the camera's options;
* :mod:`sitl.realtime.loop` — the one real-time loop both processes run;
* :mod:`sitl.realtime.depth_transport`, :mod:`sitl.realtime.event_log` — frames to companions, JSON-lines logs;
* :mod:`sitl.realtime.mavlink_swarm` — the whole stack as a swarm (``swarm_test --mavlink``).

It imports the simulator core (camera, dynamics, collision) and ``companion``; nothing imports it
but the evaluation layer and the thin entry modules.
"""
