"""Sending each simulated vehicle's depth frames to its companion (format: :mod:`companion.depth_wire`).

Vehicle ``i`` sends one UDP datagram per rendered frame to ``host:base_port + i``, where the
companion's ``--camera sitl:<port>`` source listens. The sender can be told to fail like a
real camera (``MAV_CMD_INJECT_FAILURE`` on the depth sensor, see :mod:`sitl.realtime.mavlink_autopilot`):
stop sending (``off``), send truncated datagrams (``garbage``) or frames without a single
valid pixel (``wrong``).
"""

from __future__ import annotations

import socket
import time

import numpy as np

from companion.depth_wire import encode_frame

CAMERA_FAULTS = ("ok", "off", "garbage", "wrong")
DEPTH_BASE_PORT = 14640  # vehicle i's frames go to 14640 + i by default (beside PX4's 14540 + i)


class DepthFrameSender:
    """One UDP socket that sends every vehicle's frames to its companion's port."""

    def __init__(self, host: str, base_port: int, num_vehicles: int, hfov_deg: float, max_range_m: float) -> None:
        self.host, self.base_port = host, base_port
        self.hfov_deg, self.max_range_m = hfov_deg, max_range_m
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setblocking(False)
        self.seq = np.zeros(num_vehicles, dtype=np.int64)
        self.fault = ["ok"] * num_vehicles
        self.sent = np.zeros(num_vehicles, dtype=np.int64)

    def port_of(self, vehicle: int) -> int:
        return self.base_port + vehicle

    def send(self, vehicle: int, depth_m: np.ndarray) -> None:
        """Send vehicle's newest frame [H, W] (planar metres), unless its camera is failed off."""
        fault = self.fault[vehicle]
        if fault == "off":
            return
        if fault == "wrong":
            depth_m = np.full_like(depth_m, np.nan)
        datagram = encode_frame(depth_m, vehicle=vehicle, seq=int(self.seq[vehicle]), stamp_us=int(time.time() * 1e6),
                                hfov_deg=self.hfov_deg, max_range_m=self.max_range_m)
        if fault == "garbage":
            datagram = datagram[: len(datagram) // 2]  # a truncated frame, as from a broken transport
        self.seq[vehicle] += 1
        try:
            self.sock.sendto(datagram, (self.host, self.port_of(vehicle)))
            self.sent[vehicle] += 1
        except OSError:
            pass  # nobody listening yet (ICMP port unreachable) or buffer full: a camera does not care

    def close(self) -> None:
        self.sock.close()
