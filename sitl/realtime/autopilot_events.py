"""What the autopilots said about their failsafes, read back from their own logs after a run.

PX4 announces a failsafe, and why, as an *event* (the MAVLink EVENT message of libevents), not as STATUSTEXT;
the text needs the firmware's event metadata, which every PX4 ULog embeds. ``pyulog`` (PX4's own ULog library)
reads the log and decodes the events with that metadata, so nothing is fetched over the network. A failsafe event
("Failsafe activated: switching to RTL") is logged together with the mode checks that fail at that moment; the ones
that were not failing at the previous check ("No offboard signal") are its reason.

ArduCopter says the same in STATUSTEXT, which each companion already logs as ``autopilot_text``.

    python -m sitl.real_autopilots events runs/px4_circle8   # prints each vehicle's failsafes

Every ``circle`` and ``stop`` run stores the same under ``summary.json`` ``autopilot_failsafes``.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

from sitl.realtime.mavlink_swarm import JsonLinesTail

#: Events logged within this long of each other belong to one check (PX4 writes a check's events in one go).
SAME_CHECK_S = 0.05
#: MAVLink severities up to WARNING (4) are what an ArduPilot failsafe is announced with.
MAV_SEVERITY_WARNING = 4


class EventsError(RuntimeError):
    """A run folder whose autopilot logs cannot be read (said in one line)."""


@dataclass
class AutopilotEvent:
    """One decoded PX4 event. ``t_unix_s`` is None where the log has no UTC boot time."""

    t_boot_s: float
    t_unix_s: float | None
    level: str  # "WARNING", "INFO", ...
    group: str  # "default" (what a ground station shows), "arming_check", "health", ...
    name: str  # e.g. "commander_failsafe_enter_generic"
    message: str


@dataclass
class Failsafe:
    """An autopilot failsafe, with the checks that started failing with it (its reason) and all failing then."""

    vehicle: int
    t_boot_s: float | None  # None: known only from the companion's log (ArduCopter)
    t_unix_s: float | None
    message: str
    because: list[str] = field(default_factory=list)
    failing_checks: list[str] = field(default_factory=list)


_LEVELS = {0: "EMERGENCY", 1: "ALERT", 2: "CRITICAL", 3: "ERROR", 4: "WARNING", 5: "NOTICE", 6: "INFO", 7: "DEBUG"}


def read_px4_events(ulog_path: Path) -> list[AutopilotEvent]:
    """Every event a PX4 ULog holds, decoded with the metadata embedded in the log (all groups, in order)."""
    import lzma

    try:
        from pyulog import ULog
        from pyulog.libevents_parse.parser import Parser
    except ImportError as err:
        raise EventsError("reading PX4 logs needs pyulog: pip install 'swarmnav[sim]'") from err
    try:
        ulog = ULog(str(ulog_path), message_name_filter_list=["event"])
    except Exception as err:  # pyulog raises plain exceptions for a truncated or foreign file
        raise EventsError(f"{ulog_path}: not a readable ULog ({err})") from err
    blobs = ulog.msg_info_multiple_dict.get("metadata_events")
    if not blobs:
        raise EventsError(f"{ulog_path}: the log carries no event metadata (PX4 before v1.13?)")
    parser = Parser()
    parser.load_definitions(json.loads(lzma.decompress(b"".join(blobs[0]))))
    parser.set_profile("dev")
    try:
        data = ulog.get_dataset("event").data
    except (KeyError, IndexError, ValueError):
        return []  # no event was logged
    boot_utc_us = ulog.msg_info_dict.get("boot_time_utc_us") or None
    n_args = sum(1 for key in data if key.startswith("arguments["))
    events = []
    for k, event_id in enumerate(data["id"]):
        level = (int(data["log_levels"][k]) >> 4) & 0xF  # the external log level, as a ground station shows it
        args = bytes(int(data[f"arguments[{j}]"][k]) for j in range(n_args))
        parsed = parser.parse(int(event_id), args)
        t_us = int(data["timestamp"][k])
        events.append(AutopilotEvent(
            t_boot_s=t_us / 1e6, t_unix_s=None if boot_utc_us is None else (boot_utc_us + t_us) / 1e6,
            level=_LEVELS.get(level, str(level)),
            group="?" if parsed is None else parsed.group(),
            name=f"unknown event {int(event_id)}" if parsed is None else parsed.name(),
            message="" if parsed is None else parsed.message()))
    return events


def px4_failsafes(events: list[AutopilotEvent], vehicle: int) -> list[Failsafe]:
    """The failsafe events, each with the arming/mode checks logged with it: new since the previous check = the reason."""
    checks: list[tuple[float, set[str]]] = []  # (time, failing check messages) per check round
    for event in events:
        if event.group != "arming_check" or event.name.endswith("_summary"):
            continue
        if checks and event.t_boot_s - checks[-1][0] <= SAME_CHECK_S:
            checks[-1][1].add(event.message)
        else:
            checks.append((event.t_boot_s, {event.message}))
    failsafes = []
    for event in events:
        if event.group != "default" or not event.name.startswith("commander_failsafe_enter"):
            continue
        now = [i for i, (t, _) in enumerate(checks) if abs(t - event.t_boot_s) <= SAME_CHECK_S]
        failing = checks[now[-1]][1] if now else set()
        before = checks[now[-1] - 1][1] if now and now[-1] > 0 else set()
        failsafes.append(Failsafe(vehicle, round(event.t_boot_s, 3),
                                  None if event.t_unix_s is None else round(event.t_unix_s, 3),
                                  event.message, sorted(failing - before), sorted(failing)))
    return failsafes


def ardupilot_failsafes(companion_log: Path, vehicle: int) -> list[Failsafe]:
    """ArduCopter's failsafe STATUSTEXTs as its companion logged them (``autopilot_text``, severity <= WARNING)."""
    out = []
    for r in JsonLinesTail(companion_log).read():
        if r.get("event") == "autopilot_text" and r.get("severity", 7) <= MAV_SEVERITY_WARNING \
                and "failsafe" in str(r.get("text", "")).lower():
            out.append(Failsafe(vehicle, None, round(float(r["t"]), 3), str(r["text"])))
    return out


def run_failsafes(run: Path) -> list[Failsafe]:
    """Every vehicle's failsafes in a ``sitl.real_autopilots`` run folder (PX4: px4_I/log/**.ulg; ArduCopter: logs)."""
    run = Path(run)
    px4_dirs = sorted(run.glob("px4_*"), key=lambda p: int(p.name.split("_")[1]) if p.name[4:].isdigit() else -1)
    px4_dirs = [p for p in px4_dirs if p.is_dir() and p.name[4:].isdigit()]
    failsafes: list[Failsafe] = []
    if px4_dirs:
        for folder in px4_dirs:
            vehicle = int(folder.name[4:])
            for ulog in sorted(folder.glob("log/*/*.ulg")):
                failsafes += px4_failsafes(read_px4_events(ulog), vehicle)
        return failsafes
    logs = sorted(run.glob("companion_*.jsonl"))
    if not logs:
        raise EventsError(f"{run}: no px4_I/ log folders and no companion_I.jsonl (not a sitl.real_autopilots run?)")
    for log in logs:
        failsafes += ardupilot_failsafes(log, int(log.stem.split("_")[1]))
    return failsafes


def failsafe_summary(failsafes: list[Failsafe], since_unix_s: float | None = None) -> list[dict]:
    """JSON-ready records; with ``since_unix_s`` each also says how long after that time it fired."""
    out = []
    for f in failsafes:
        record = asdict(f)
        if since_unix_s is not None and f.t_unix_s is not None:
            record["t_after_s"] = round(f.t_unix_s - since_unix_s, 2)
        out.append(record)
    return out


def format_failsafes(failsafes: list[Failsafe]) -> str:
    """One line per failsafe: vehicle, PX4 boot time, what it did and why."""
    if not failsafes:
        return "no autopilot failsafe"
    lines = []
    for f in failsafes:
        why = f"because: {', '.join(f.because)}" if f.because else (
            f"failing then: {', '.join(f.failing_checks)}" if f.failing_checks else "")
        when = "(from the companion's log)" if f.t_boot_s is None else f"{f.t_boot_s:7.1f} s after boot"
        lines.append(f"vehicle {f.vehicle}: {when}: {f.message}" + (f" ({why})" if why else ""))
    return "\n".join(lines)
