"""Flight modes of the two autopilots, as they travel in HEARTBEAT.custom_mode.

PX4 packs its mode as ``custom_mode = (main_mode << 16) | (sub_mode << 24)`` (the sub mode
only matters for the AUTO modes); OFFBOARD is main mode 6. ArduCopter's custom_mode is the
mode number itself; GUIDED is 4. Shared by the companion and the simulated vehicle.
"""

from __future__ import annotations

from enum import Enum

#: HEARTBEAT.autopilot values (MAV_AUTOPILOT).
MAV_AUTOPILOT_ARDUPILOTMEGA = 3
MAV_AUTOPILOT_INVALID = 8
MAV_AUTOPILOT_PX4 = 12


class AutopilotKind(str, Enum):
    """Which firmware flies the vehicle, told by HEARTBEAT.autopilot."""

    PX4 = "px4"
    ARDUPILOT = "ardupilot"

    @classmethod
    def from_heartbeat(cls, autopilot: int) -> "AutopilotKind | None":
        return {MAV_AUTOPILOT_PX4: cls.PX4, MAV_AUTOPILOT_ARDUPILOTMEGA: cls.ARDUPILOT}.get(autopilot)


# PX4 (main, sub) -> name, as QGroundControl and MAVSDK name them.
PX4_MODES: dict[tuple[int, int], str] = {
    (1, 0): "MANUAL", (2, 0): "ALTCTL", (3, 0): "POSCTL",
    (4, 1): "AUTO.READY", (4, 2): "AUTO.TAKEOFF", (4, 3): "AUTO.LOITER", (4, 4): "AUTO.MISSION",
    (4, 5): "AUTO.RTL", (4, 6): "AUTO.LAND", (4, 8): "AUTO.FOLLOW_TARGET", (4, 9): "AUTO.PRECLAND",
    (5, 0): "ACRO", (6, 0): "OFFBOARD", (7, 0): "STABILIZED",
}
PX4_MODE_BY_NAME: dict[str, tuple[int, int]] = {name: key for key, name in PX4_MODES.items()}
PX4_MAIN_MODE_AUTO = 4
PX4_MAIN_MODE_OFFBOARD = 6

# ArduCopter mode number -> name.
ARDUCOPTER_MODES: dict[int, str] = {
    0: "STABILIZE", 1: "ACRO", 2: "ALT_HOLD", 3: "AUTO", 4: "GUIDED", 5: "LOITER", 6: "RTL", 7: "CIRCLE",
    9: "LAND", 11: "DRIFT", 13: "SPORT", 15: "AUTOTUNE", 16: "POSHOLD", 17: "BRAKE", 18: "THROW",
    20: "GUIDED_NOGPS", 21: "SMART_RTL",
}
ARDUCOPTER_MODE_BY_NAME: dict[str, int] = {name: number for number, name in ARDUCOPTER_MODES.items()}
ARDUCOPTER_GUIDED = 4
ARDUCOPTER_LAND = 9


def px4_custom_mode(main_mode: int, sub_mode: int = 0) -> int:
    """HEARTBEAT.custom_mode of a PX4 mode."""
    return (main_mode << 16) | (sub_mode << 24)


def px4_main_sub(custom_mode: int) -> tuple[int, int]:
    """(main_mode, sub_mode) of a PX4 HEARTBEAT.custom_mode."""
    return (custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF


def mode_name(kind: AutopilotKind, custom_mode: int) -> str:
    """A readable name for a custom_mode, e.g. ``OFFBOARD`` or ``GUIDED``."""
    if kind is AutopilotKind.PX4:
        main, sub = px4_main_sub(custom_mode)
        return PX4_MODES.get((main, sub)) or PX4_MODES.get((main, 0)) or f"PX4({main},{sub})"
    return ARDUCOPTER_MODES.get(custom_mode, f"MODE{custom_mode}")


def is_companion_mode(kind: AutopilotKind, custom_mode: int) -> bool:
    """True in the mode in which the autopilot follows the companion: OFFBOARD or GUIDED."""
    if kind is AutopilotKind.PX4:
        return px4_main_sub(custom_mode)[0] == PX4_MAIN_MODE_OFFBOARD
    return custom_mode == ARDUCOPTER_GUIDED


def is_landing_mode(kind: AutopilotKind, custom_mode: int) -> bool:
    """True in the autopilot's landing mode (AUTO.LAND or LAND)."""
    if kind is AutopilotKind.PX4:
        return px4_main_sub(custom_mode) == PX4_MODE_BY_NAME["AUTO.LAND"]
    return custom_mode == ARDUCOPTER_LAND
