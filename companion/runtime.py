"""The onboard flight procedure: connect, wait for health, stream setpoints, engage, fly, hand back.

:class:`Companion` runs one thread that owns everything: the MAVLink link, the depth source
and the policy. It sleeps in ``select`` until a message or a frame arrives or the next
control tick is due, so frames are timestamped the moment they arrive and the tick fires
on time. Each tick runs the handler of the current :class:`FlightPhase`:

=======================  ====================================================================
phase                    what the vehicle is doing / what the companion sends
=======================  ====================================================================
waiting_for_telemetry    link up, waiting for fresh odometry and depth; nothing sent
streaming_hold           healthy; zero-velocity setpoints for 1.5 s (PX4 accepts OFFBOARD
                         only with a setpoint stream running)
waiting_for_pilot        hold setpoints until the pilot/GCS selects OFFBOARD (PX4) or GUIDED
                         (ArduPilot); engaging happens on that change, never on our request
arming                   (``--arm``) arming the vehicle
switching_mode           (``--arm``) asking for OFFBOARD / GUIDED
taking_off               (``--arm --takeoff``) PX4: climbing in OFFBOARD with velocity
                         setpoints; ArduPilot: NAV_TAKEOFF in GUIDED, nothing streamed
flying_to_goal           the policy flies; every step may become a hold (failsafes below)
holding_at_goal          within 0.5 m of the goal: a position target at the goal (LOCAL_NED
                         position + yaw), so the vehicle settles on it instead of drifting on
                         after a zero-velocity stop
landing                  (``--land-on-arrival``) the autopilot lands; nothing sent
landed                   disarmed on the ground
handed_back              the pilot changed the mode: nothing sent, the mode is never requested back;
                         final for the life of the process (a later link loss and return
                         stays here: a takeover is never undone by the companion)
link_lost                no autopilot heartbeat: nothing sent, the autopilot's failsafe acts
=======================  ====================================================================

Failsafes while the policy flies (each step, logged with its reason): depth or odometry
older than ``stale_periods`` control periods (1.5), the newest depth frame malformed, the
policy output not finite or the policy raising, or the policy's answer not ready by its
deadline (the newest frame's arrival + the stale limit, or the next tick if sooner:
``policy inference late``) ->
zero-velocity hold; every command is clamped to the policy's action bounds. Inference
runs on its own thread (:class:`companion.inference.InferenceWorker`), so a slow policy cannot stall the loop;
a late answer is discarded when it comes, and the ticks hold while it is still running.
The loop also wakes when the inputs would go stale, so a stale-input hold goes out at once
(an extra step between ticks), not at the next tick.

Leaving on purpose (SIGTERM/SIGINT, ``--exit-on-arrival`` without landing, ``--timeout``, a
failed step) while the companion flies the vehicle ends with :meth:`Companion._leave`: a
position hold streamed for ``EXIT_HOLD_STREAM_S``, then the autopilot's hold mode (PX4
AUTO.LOITER, ArduPilot BRAKE) requested and confirmed from its HEARTBEAT, then the exit. After
a pilot's takeover no mode is ever requested.

Frame stacking: each policy step pushes the newest frame *if it is newer than the last one
pushed*; when the camera missed the period (no new frame by the tick, the newest still fresh),
the stack is not advanced and the policy sees the same stack as at its previous step (every
entry a distinct real frame one camera period apart, as in training), never a frame twice.

The control clock ticks at the policy's control period. With ``camera_sync`` it slowly
shifts its phase (at most 2 ms per tick) so that ticks fall just after depth frames arrive:
a frame then waits a few ms instead of up to a whole period before the policy sees it.
"""

from __future__ import annotations

import gc
import math
import select
import signal
import time
from dataclasses import dataclass
from enum import Enum, IntEnum

import numpy as np

from companion.clock import ControlClock
from companion.depth_sources import DepthFault, DepthFrame, DepthSource
from companion.flightlog import FlightLog, RunningStats, resident_memory_mb
from companion.mavlink_link import AutopilotLink, PendingCommand, mavlink
from companion.flight_modes import (
    ARDUCOPTER_GUIDED,
    ARDUCOPTER_MODE_BY_NAME,
    PX4_MAIN_MODE_OFFBOARD,
    PX4_MODE_BY_NAME,
    AutopilotKind,
)
from companion.face_goal import FaceGoalSpec, face_goal_commands, goal_bearing_frd_rad, goal_heading_rad
from companion.governor import GovernorSpec, SpeedGovernor
from companion.inference import InferenceWorker
from companion.observation import DepthFrameStack, RememberedDepth, build_state
from companion.obstacle_distance import ObstacleDistancePublisher
from companion.policy import LoadedPolicy, torchscript_error_line
from companion.recording import FlightRecorder
from companion.sdnotify import SystemdNotifier
from companion.spec import goal_problem


#: Below this much time before an inference's deadline, no call is started (its answer could not
#: arrive in time); the step holds instead.
MIN_INFERENCE_TIME_S = 0.001

#: Leaving on purpose while flying: a hold (zero velocity, or a position target at the goal when
#: holding there) is streamed at least this long (at EXIT_HOLD_RATE_HZ)
#: before the hold mode is requested and the link closed. Issue 18: zero setpoints sent only
#: just before closing were lost with the TCP link on ArduPilot; 0.5 s of them stopped it.
EXIT_HOLD_STREAM_S = 0.5
EXIT_HOLD_RATE_HZ = 20.0
#: Before the hold mode is requested the vehicle is stopped (zero velocity until slower than
#: EXIT_SETTLED_SPEED_M_S) and a position hold where it stopped (or at the goal) streamed until it has
#: settled on it (within EXIT_SETTLED_DISTANCE_M of the point and slower than EXIT_SETTLED_SPEED_M_S),
#: at most EXIT_SETTLE_MAX_S. Why: ArduCopter's BRAKE limits its position correction to the speed
#: it was entered at (mode_brake.cpp: set_correction_speed_accel_NE_cm(current speed)), so entered
#: while still decelerating it crept 1.9-2.2 m from the hold point (real ArduCopter SITL, issue 18).
EXIT_SETTLED_DISTANCE_M = 0.3
EXIT_SETTLED_SPEED_M_S = 0.1
EXIT_SETTLE_MAX_S = 5.0
#: How long to wait for the autopilot's HEARTBEAT to show the hold mode after asking for it:
#: HEARTBEAT comes at 1 Hz and the command may need a retry (1.5-1.9 s measured unloaded),
#: so 5 s leaves room for a busy link or computer; the hold is streamed meanwhile.
HAND_OVER_TIMEOUT_S = 5.0
#: The mode a companion that stops commanding on purpose hands the vehicle to. PX4: AUTO.LOITER
#: ("Hold"), which holds position without RC input. ArduCopter: BRAKE, which stops and then
#: holds position without reading the sticks; LOITER would follow the RC throttle (SITL's
#: default 1000 makes it descend into the ground, issue 18 item 10, and so would a pilot's
#: stick left low). The pilot takes over from either by selecting any mode.
HOLD_MODES = {AutopilotKind.PX4: "AUTO.LOITER", AutopilotKind.ARDUPILOT: "BRAKE"}
#: A gap between two setpoints sent while streaming longer than this is a stall of this computer, logged
#: (``stall``) with its length: autopilots leave OFFBOARD/GUIDED when setpoints stop (PX4 after COM_OF_LOSS_T,
#: 1 s by default; the setpoints go out at 10 Hz). Half of PX4's limit warns before the failsafe would fire.
STALL_WARN_S = 0.5
#: A mode change this soon after a stall is reported as the autopilot's offboard-loss failsafe, not a pilot's
#: switch (PX4 switches at COM_OF_LOSS_T after the last setpoint; the heartbeat shows it within ~1 s).
STALL_TAKEOVER_WINDOW_S = 3.0


class ExitCode(IntEnum):
    """The process's exit status (documented in docs/companion.md)."""

    OK = 0  # arrived (--exit-on-arrival) or stopped by SIGTERM/SIGINT
    ERROR = 1  # unexpected internal error
    USAGE = 2  # bad command line (argparse)
    BAD_MODEL = 3  # the policy file is missing or breaks the contract
    CAMERA = 4  # the depth source cannot start
    LINK = 5  # no autopilot heartbeat at start, or the link was lost (--exit-on-arrival)
    PILOT_TOOK_OVER = 6  # the mode left OFFBOARD/GUIDED (--exit-on-arrival)
    TIMEOUT = 7  # --timeout elapsed before arrival
    ENGAGE_FAILED = 8  # --arm/--takeoff/landing refused or unanswered by the autopilot


class FlightPhase(str, Enum):
    """What the vehicle is doing, as seen by the companion."""

    WAITING_FOR_TELEMETRY = "waiting_for_telemetry"
    STREAMING_HOLD = "streaming_hold"
    WAITING_FOR_PILOT = "waiting_for_pilot"
    ARMING = "arming"
    SWITCHING_MODE = "switching_mode"
    TAKING_OFF = "taking_off"
    FLYING_TO_GOAL = "flying_to_goal"
    HOLDING_AT_GOAL = "holding_at_goal"
    LANDING = "landing"
    LANDED = "landed"
    HANDED_BACK = "handed_back"
    LINK_LOST = "link_lost"


#: Phases in which the companion streams setpoints.
_STREAMING = {FlightPhase.STREAMING_HOLD, FlightPhase.WAITING_FOR_PILOT, FlightPhase.ARMING,
              FlightPhase.SWITCHING_MODE, FlightPhase.FLYING_TO_GOAL, FlightPhase.HOLDING_AT_GOAL}


@dataclass
class CompanionConfig:
    """Flight options from the command line."""

    goal_ned: np.ndarray | None = None
    arm: bool = False
    takeoff_alt_m: float | None = None
    land_on_arrival: bool = False
    exit_on_arrival: bool = False
    timeout_s: float | None = None
    arrival_radius_m: float | None = None  # None: the policy's (policy.json task, 0.5 m by default)
    link_timeout_s: float = 2.0
    stale_periods: float = 1.5
    hold_stream_s: float = 1.5  # PX4 wants >= 1 s of setpoints before OFFBOARD: keep a margin
    stream_rate_hz: float = 50.0
    camera_sync: bool = True
    takeoff_timeout_s: float = 60.0
    obstacle_distance: bool = True  # publish OBSTACLE_DISTANCE per depth frame (companion.obstacle_distance)
    # The speed governor after the policy (companion.governor); None: off, unless the policy file has one.
    governor: GovernorSpec | None = None
    # Turn in place to face each new goal and fly a fixed time after it arrived (companion.face_goal); None: off.
    face_goal: FaceGoalSpec | None = None


class Companion:
    """The flight procedure around a policy, a depth source and an autopilot link.

    ``model``, ``depth`` and ``link`` must already be loaded, started and connected (the
    autopilot's heartbeat received): :meth:`run` flies and returns the exit code.
    """

    def __init__(self, policy: LoadedPolicy, depth: DepthSource, link: AutopilotLink, config: CompanionConfig,
                 log: FlightLog, recorder: FlightRecorder | None = None,
                 notifier: SystemdNotifier | None = None) -> None:
        self.policy, self.depth, self.link, self.config = policy, depth, link, config
        self.log, self.recorder = log, recorder
        self.notifier = notifier or SystemdNotifier()
        self.period_s = policy.control_period_s
        self.stale_s = config.stale_periods * self.period_s
        self.arrival_radius_m = (policy.task.arrival_radius_m if config.arrival_radius_m is None
                                 else config.arrival_radius_m)
        self.low = policy.action.low_array().astype(np.float64)
        self.high = policy.action.high_array().astype(np.float64)
        self.stack = DepthFrameStack(1, policy.camera)
        # A policy with remembered depth: the points of recent frames, moved with odometry (as in training).
        self.memory = RememberedDepth(1, policy.camera, policy.memory) if policy.memory is not None else None
        self.obstacles = ObstacleDistancePublisher(policy.camera, link) if config.obstacle_distance else None
        # A policy trained with the governor flies with its own settings; others with the configured one, if any.
        governor = policy.governor if policy.governor is not None else config.governor
        self.governor = SpeedGovernor(policy.camera, governor) if governor is not None else None
        self.goal_ned = None if config.goal_ned is None else np.asarray(config.goal_ned, dtype=np.float64)
        self._goal_set_s = -math.inf  # when the goal last changed (--face-goal's hold counts from it or engagement)
        self._facing = False  # --face-goal: turning in place, the policy's commands held back
        #: This tick's position target (NED point, yaw) instead of a velocity setpoint: set by the phase
        #: handlers that keep the vehicle on a point (face-goal turn, PX4 takeoff, waiting for a goal).
        self._point_target: tuple[np.ndarray, float] | None = None
        #: Where the vehicle keeps station while it has no goal (NED, yaw).
        self._station: tuple[np.ndarray, float] | None = None
        #: Where a PX4 takeoff started (NED, yaw): the climb goes straight up from it.
        self._takeoff_from: tuple[np.ndarray, float] | None = None
        self._face_hold_ned: np.ndarray | None = None  # where the current turn in place started

        self.phase = FlightPhase.WAITING_FOR_TELEMETRY
        self.phase_since_s = time.monotonic()
        self.exit_code: ExitCode | None = None
        self.exit_reason = ""
        self.step_index = 0
        self.engaged = False  # the autopilot has followed us since we engaged
        self.taken_over = False  # the pilot took the vehicle: final for the life of the process
        self.landed = False  # landed and disarmed: the flight is over, never armed again by us
        self._link_down_after_takeover = False
        self.latest_frame: DepthFrame | None = None
        self.latest_fault: DepthFault | None = None
        self._last_pushed_s = -math.inf  # when the stack last fed the policy
        self._last_stacked_arrival_s = -math.inf  # arrival time of the newest frame in the stack
        self._stack_seqs: list[int] = []  # seq numbers of the stack's frame history, oldest first (logged)
        self._hold_point: tuple[np.ndarray, float] | None = None  # (goal NED, yaw) held at the goal
        self._last_hold_reason: str | None = None
        self._last_mode: tuple[int, bool] | None = None
        self._was_in_companion_mode_at_start: bool | None = None
        self._pending: PendingCommand | None = None
        self._sequence: list[FlightPhase] = []
        self._last_setpoint: np.ndarray | None = None
        self._last_setpoint_s = -math.inf
        self._stop_signal: str | None = None
        self._started_s = time.monotonic()
        self._odometry_request: PendingCommand | None = None
        self._fallback_requested = False
        self.clock = ControlClock(self.period_s, self._started_s, lock=config.camera_sync)
        self.worker = InferenceWorker(policy)
        self.depth.set_stale_limit(self.stale_s)  # a frame older than this on arrival is refused

        # statistics: windowed since the last summary + a bounded histogram for the whole flight
        self.latency_s = RunningStats()
        self.inference_s = RunningStats()
        self.tick_late_s = RunningStats()
        self.period_dev_s = RunningStats()
        self.overruns = 0
        self._last_tick_s: float | None = None
        self._streamed_last_tick = False  # the previous scheduled tick sent a setpoint
        self._last_stall: tuple[float, float] | None = None  # (when it ended, its length in s)
        self._last_summary_s = time.monotonic()
        self.holds = 0
        self.policy_steps = 0
        self.governed_steps = 0  # policy steps whose forward speed the governor lowered
        self._governor_turning = np.zeros(1, dtype=np.float32)  # the governor's turn in progress (sticky)

    # ================================================================== main loop
    def run(self) -> ExitCode:
        """Fly until an exit condition (or SIGTERM/SIGINT); return the exit code."""
        previous = {sig: signal.signal(sig, self._on_signal) for sig in (signal.SIGTERM, signal.SIGINT)}
        # Start-up objects (torch, the model) never die: keep the cyclic collector off them, or a
        # full collection walks them all and delays a tick by milliseconds.
        gc.collect()
        gc.freeze()
        now = time.monotonic()
        clock = self.clock
        clock.start(now)  # ticks count from the loop's start, not from construction (model loading lies between)
        self.worker.start()
        next_heartbeat_s = now
        self.link.send_heartbeat()
        self._request_streams()
        self._event("phase", f"phase {self.phase.value}: waiting for fresh odometry and depth", to=self.phase.value)
        try:
            while self.exit_code is None:
                now = time.monotonic()
                deadline = min(clock.next_tick_s, next_heartbeat_s, self.depth.next_due_s() or math.inf,
                               self._stale_deadline_s())
                fds = [fd for fd in (self.link.fileno(), self.depth.fileno()) if fd is not None]
                timeout = max(0.0, deadline - now)
                if self.link.fileno() is None:
                    timeout = min(timeout, 0.005)  # a link without a descriptor is polled
                if timeout > 0:
                    try:
                        select.select(fds, [], [], timeout) if fds else time.sleep(timeout)
                    except InterruptedError:
                        pass
                now = time.monotonic()
                self._read_depth(now)
                self._read_link(now)
                if self._stop_signal is not None:
                    self._finish(ExitCode.OK, f"stopping on {self._stop_signal}")
                    break
                if now >= next_heartbeat_s:
                    self.link.send_heartbeat()
                    next_heartbeat_s = max(next_heartbeat_s + 1.0, now + 0.5)
                self.link.service_commands(now)
                if now >= clock.next_tick_s:
                    self._tick(now, clock)
                elif now >= self._stale_deadline_s():
                    self._tick(now, clock, extra=True)  # hold now, not at the next tick
                elif (self.phase in _STREAMING and self._last_setpoint is not None
                      and now - self._last_setpoint_s > 0.2):
                    self._send(self._last_setpoint)  # keep PX4's > 2 Hz stream alive with long periods
            try:
                self._leave()
            except OSError as err:  # the link broke while handing over: say so, exit as decided
                self._event("handover", f"hand-over interrupted: link error {err}", level="error", confirmed=False)
            self._event("exit", f"exit {int(self.exit_code)} ({self.exit_code.name}): {self.exit_reason}",
                        level="info" if self.exit_code is ExitCode.OK else "error",
                        code=int(self.exit_code), reason=self.exit_reason)
        except Exception as err:  # never leave the vehicle flying on our last command
            self._hold_on_the_way_out()
            self._event("exit", f"internal error: {type(err).__name__}: {err}", level="error")
            self.exit_code, self.exit_reason = ExitCode.ERROR, f"{type(err).__name__}: {err}"
            raise
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)
            self.worker.close()
            self._write_summary(final=True)
            self.notifier.stopping(self.exit_reason or "stopping")
        return self.exit_code

    def _on_signal(self, signum, _frame) -> None:
        self._stop_signal = signal.Signals(signum).name

    def _request_streams(self) -> None:
        rate = self.config.stream_rate_hz
        if self.link.heartbeat.kind is AutopilotKind.PX4:
            self._odometry_request = self.link.request_message_interval(mavlink.MAVLINK_MSG_ID_ODOMETRY, rate)
        else:  # ArduPilot sends no ODOMETRY
            self._request_fallback_streams()

    # ================================================================== inputs
    def _read_depth(self, now: float) -> None:
        for item in self.depth.poll(now):
            if isinstance(item, DepthFrame):
                self.latest_frame, self.latest_fault = item, None
                self.clock.frame_arrived(item.arrival_s)
                if self.obstacles is not None:  # the autopilot's collision prevention, from every frame used
                    self.obstacles.publish(item.depth_m)
            else:
                if self.latest_fault is None or self.latest_fault.reason != item.reason:
                    self._event("depth_fault", item.reason, level="warning")
                self.latest_fault = item

    def _read_link(self, now: float) -> None:
        events = self.link.receive(now)
        for event in events:
            if event.kind == "goal":
                self._on_goal(event.detail)
            elif event.kind == "refused_unsigned":
                self._event("refused_unsigned", f"refused {event.detail['count']} unsigned message(s): "
                            f"{', '.join(event.detail['messages'])}", level="warning", **event.detail)
            elif event.kind == "statustext":
                self._event("autopilot_text", f"autopilot: {event.detail['text']}", **event.detail)
            elif event.kind == "odometry_frame":
                self._event("odometry_frame", f"ignoring ODOMETRY: {event.detail['error']}; "
                            "using LOCAL_POSITION_NED + ATTITUDE", level="warning")
                self._request_fallback_streams()
            elif event.kind == "io_error":
                self._event("link", f"link I/O error: {event.detail['error']}", level="warning")
            elif event.kind == "relocked":  # the autopilot restarted on a new UDP port
                self._event("link", event.detail["reason"], level="warning", relocked=True)
            elif event.kind == "ignored_traffic":  # another sender or link id posing as the autopilot
                self._event("ignored_traffic", event.detail["reason"], level="warning", count=event.detail["count"])
        req = self._odometry_request
        if req is not None and req.done and not req.accepted:
            self._odometry_request = None
            if req.result is not None:  # refused: ask for the ArduPilot-style pair instead
                self._event("streams", f"{req.describe_failure()}; using LOCAL_POSITION_NED + ATTITUDE", level="warning")
                self._request_fallback_streams()
            else:  # unanswered: more requests would only delay the commands queued behind them
                self._event("streams", f"{req.describe_failure()}; using the autopilot's default streams",
                            level="warning")
        hb = self.link.heartbeat
        if hb is not None:
            key = (hb.custom_mode, hb.armed)
            if self._last_mode != key:
                if self._last_mode is not None:
                    self._event("mode", f"autopilot mode {hb.mode}, {'armed' if hb.armed else 'disarmed'}",
                                mode=hb.mode, armed=hb.armed)
                else:
                    self._was_in_companion_mode_at_start = hb.in_companion_mode
                self._last_mode = key

    def _request_fallback_streams(self) -> None:
        if self._fallback_requested:
            return
        self._fallback_requested = True
        self.link.request_message_interval(mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, self.config.stream_rate_hz)
        self.link.request_message_interval(mavlink.MAVLINK_MSG_ID_ATTITUDE, self.config.stream_rate_hz)

    def _on_goal(self, detail: dict) -> None:
        goal = np.asarray(detail["goal_ned"], dtype=np.float64)
        sender = f"system {detail['from'][0]}, {'signed' if detail['signed'] else 'unsigned'}"
        odom = self.link.odometry
        problem = goal_problem(goal, None if odom is None else odom.pos_ned)
        if problem is not None:  # keep flying (or holding) on the goal we had
            self._event("goal", f"goal {np.round(goal, 2).tolist()} from {sender} refused: {problem}; keeping "
                        f"{None if self.goal_ned is None else np.round(self.goal_ned, 2).tolist()}", level="warning",
                        refused=True, reason=problem, sender=detail["from"], signed=detail["signed"])
            try:
                self.link.send_statustext(mavlink.MAV_SEVERITY_WARNING, f"companion: goal refused: {problem}"[:50])
            except OSError:
                pass
            return
        if self.phase in (FlightPhase.LANDING, FlightPhase.LANDED, FlightPhase.HANDED_BACK, FlightPhase.LINK_LOST):
            self._event("goal", f"goal {np.round(goal, 2).tolist()} ignored while {self.phase.value}", level="warning")
            return
        if self.goal_ned is None or not np.array_equal(goal, self.goal_ned):  # a resent copy is not a new goal
            self._goal_set_s = time.monotonic()
        self.goal_ned = goal
        text = f"goal set to N {goal[0]:.1f} E {goal[1]:.1f} D {goal[2]:.1f}"
        self._event("goal", f"{text} (from system {detail['from'][0]}, {'signed' if detail['signed'] else 'unsigned'})",
                    goal_ned=goal, sender=detail["from"], signed=detail["signed"])
        self.link.send_statustext(mavlink.MAV_SEVERITY_INFO, f"companion: {text}")
        if self.phase is FlightPhase.HOLDING_AT_GOAL:
            self._set_phase(FlightPhase.FLYING_TO_GOAL, "new goal")

    def _input_problem(self, now: float, need_depth: bool = True) -> str | None:
        """Why the inputs cannot be trusted right now, or None."""
        if self.link.odometry_fault is not None:  # refused at the link: blame the telemetry, not the policy
            return self.link.odometry_fault
        odom_age = self.link.odometry_age_s(now)
        if odom_age > self.stale_s:
            return "no odometry yet" if math.isinf(odom_age) else f"odometry stale ({odom_age * 1000:.0f} ms old)"
        if not need_depth:
            return None
        if self.latest_fault is not None:
            return self.latest_fault.reason
        if self.latest_frame is None:
            return "no depth frame yet"
        depth_age = now - self.latest_frame.arrival_s
        if depth_age > self.stale_s:
            return f"depth stale ({depth_age * 1000:.0f} ms old: camera stopped?)"
        return None

    # ================================================================== the tick
    def _stale_deadline_s(self) -> float:
        """When the inputs the policy flies on go stale (inf unless it is flying on fresh ones)."""
        if self.phase is not FlightPhase.FLYING_TO_GOAL or self._last_hold_reason is not None:
            return math.inf
        odom = self.link.odometry
        if odom is None or self.latest_frame is None or self.latest_fault is not None:
            return math.inf
        return min(odom.received_s, self.latest_frame.arrival_s) + self.stale_s + 1e-4

    def _tick(self, now: float, clock: ControlClock, extra: bool = False) -> None:
        """One control step: at the scheduled time, or ``extra`` when inputs went stale between ticks."""
        scheduled = clock.next_tick_s
        self.step_index += 1
        late = period = None
        # Measured from the last setpoint actually sent, not the last scheduled tick: an extra tick
        # in between (a hold sent when inputs went stale) did reach the autopilot. Checked on extra ticks too:
        # after a stall the first tick is often an extra one (the inputs went stale meanwhile), and it must
        # know of the stall before it reads a mode change, or the autopilot's failsafe reads as the pilot.
        gap_s = now - self._last_setpoint_s
        if gap_s > STALL_WARN_S and self._streamed_last_tick:
            self._last_stall = (now, gap_s)
            self._streamed_last_tick = False  # one event per stall, whichever tick sees it first
            self._event("stall", f"this computer stalled: no setpoint for {gap_s:.2f} s (autopilots leave "
                        "OFFBOARD/GUIDED when setpoints stop: PX4 after COM_OF_LOSS_T, 1 s by default)",
                        level="warning", gap_s=round(gap_s, 3))
        if not extra:
            late = now - scheduled
            period = None if self._last_tick_s is None else now - self._last_tick_s
            self._last_tick_s = now
            self.tick_late_s.append(max(late, 0.0))
            if period is not None:
                self.period_dev_s.append(abs(period - self.period_s))

        info: dict = {}
        while self.worker.discarded:
            seconds = self.worker.discarded.pop(0)
            self._event("policy_late", f"discarded a late policy answer (inference took {seconds * 1000:.0f} ms)",
                        level="warning", inference_ms=seconds * 1000.0)
        self._point_target = None  # set again by this tick's phase handler only
        command = self._run_phase(now, info)
        sent_s = None
        if command is not None:
            sent_s = self._send(command)
        if not extra:
            self._streamed_last_tick = command is not None
        frame = info.get("frame")
        if info.get("policy_step") and sent_s is not None and frame is not None:
            self.latency_s.append(sent_s - frame.arrival_s)
        if not extra:
            clock.advance(now)
            if time.monotonic() > clock.next_tick_s:
                self.overruns += 1

        hold = info.get("hold")
        if hold:
            self.holds += 1
        hb = self.link.heartbeat
        odom = self.link.odometry
        self.log.step(
            step=self.step_index, phase=self.phase.value, mode=hb.mode if hb else None, armed=hb.armed if hb else None,
            sent=command is not None, hold=hold, cmd=command, policy=info.get("policy"), clamped=info.get("clamped", False),
            governor=info.get("governor"), face_goal_s=info.get("face_goal_s"),
            pos_ned=None if odom is None else odom.pos_ned, goal_ned=self.goal_ned,
            dist_m=info.get("dist_m"),
            depth_age_ms=None if self.latest_frame is None else (now - self.latest_frame.arrival_s) * 1000.0,
            odom_age_ms=None if odom is None else (now - odom.received_s) * 1000.0,
            frame_seq=None if frame is None else frame.seq,
            frame_to_setpoint_ms=None if not (info.get("policy_step") and sent_s is not None and frame is not None)
            else (sent_s - frame.arrival_s) * 1000.0,
            inference_ms=None if info.get("inference_s") is None else info["inference_s"] * 1000.0,
            tick_late_ms=None if late is None else late * 1000.0, period_ms=None if period is None else period * 1000.0,
            extra=extra, stacked=info.get("stacked"), stack_seqs=info.get("stack_seqs"),
            hold_point_ned=None if command is None else (self._hold_point[0] if self._holding_point() else (
                None if self._point_target is None else self._point_target[0])),
        )
        if self.recorder is not None and frame is not None and info.get("state") is not None:
            try:
                self.recorder.write(t_wall_s=time.time(), t_mono_s=now, step=self.step_index, frame_seq=frame.seq,
                                    hold=bool(hold), depth_m=frame.depth_m, state=info["state"],
                                    action=command if command is not None else np.zeros(3),
                                    pos_ned_m=odom.pos_ned, yaw_rad=odom.yaw_rad)
            except (OSError, ValueError) as err:  # a full disk or a pulled SD card must not end the flight
                self.recorder = None
                self._event("recording", f"recording stopped: {err}; the flight goes on", level="warning")
        self.notifier.watchdog(now)
        if now - self._last_summary_s >= 10.0:
            self._write_summary(final=False)

    def _holding_point(self) -> bool:
        return self.phase is FlightPhase.HOLDING_AT_GOAL and self._hold_point is not None

    def _send(self, command: np.ndarray) -> float:
        if self._holding_point():  # at the goal: hold the point, not a zero velocity that drifts on
            self.link.send_position_target(*self._hold_point)
        elif self._point_target is not None:  # keeping a point (turning to the goal, taking off, no goal yet)
            self.link.send_position_target(*self._point_target)
        else:
            self.link.send_velocity_setpoint(command[0], command[1], command[2])
        sent_s = time.monotonic()
        self._last_setpoint, self._last_setpoint_s = command, sent_s
        return sent_s

    def _run_phase(self, now: float, info: dict) -> np.ndarray | None:
        if self.taken_over:  # final: nothing is ever sent or requested again
            self._watch_link_after_takeover(now)
            if self.config.timeout_s is not None and now - self._started_s > self.config.timeout_s:
                self._finish(ExitCode.TIMEOUT, f"not arrived within --timeout {self.config.timeout_s:g} s")
            return None
        # Whole-flight conditions first: the link, the mode, the clock.
        if self.phase is not FlightPhase.LINK_LOST and self.link.heartbeat_age_s(now) > self.config.link_timeout_s:
            self._set_phase(FlightPhase.LINK_LOST, f"link lost: no heartbeat for {self.link.heartbeat_age_s(now):.1f} s; "
                            "leaving it to the autopilot's failsafe", level="error")
            if self.config.exit_on_arrival:
                self._finish(ExitCode.LINK, "link to the autopilot lost")
            return None
        if self.engaged and self.phase not in (FlightPhase.LANDING, FlightPhase.LANDED, FlightPhase.HANDED_BACK,
                                               FlightPhase.LINK_LOST):
            hb = self.link.heartbeat
            if not hb.in_companion_mode:
                who = self._who_took_over(now)
                self._hand_back(f"{who}: mode {hb.mode}; stopped commanding (restart the companion to engage again)")
                if self.config.exit_on_arrival:
                    self._finish(ExitCode.PILOT_TOOK_OVER, f"{who} (mode {hb.mode})")
                return None
        if (self.config.timeout_s is not None and now - self._started_s > self.config.timeout_s
                and self.phase not in (FlightPhase.HOLDING_AT_GOAL, FlightPhase.LANDED)):
            self._finish(ExitCode.TIMEOUT, f"not arrived within --timeout {self.config.timeout_s:g} s")
            return self._hold_if_streaming()
        handler = getattr(self, f"_phase_{self.phase.value}")
        return handler(now, info)

    def _hold_if_streaming(self) -> np.ndarray | None:
        return np.zeros(3) if self.phase in _STREAMING else None

    # ================================================================== phases
    def _phase_waiting_for_telemetry(self, now: float, info: dict) -> np.ndarray | None:
        problem = self._input_problem(now)
        if problem is None:
            self._set_phase(FlightPhase.STREAMING_HOLD, "odometry and depth are fresh: streaming hold setpoints")
            return np.zeros(3)
        info["hold"] = problem
        return None

    def _phase_streaming_hold(self, now: float, info: dict) -> np.ndarray | None:
        problem = self._input_problem(now)
        if problem is not None:  # do not offer a mode switch to a companion that cannot see
            self._set_phase(FlightPhase.WAITING_FOR_TELEMETRY, f"stopped streaming: {problem}", level="warning")
            return None
        if now - self.phase_since_s >= self.config.hold_stream_s:
            if self.config.arm:
                self._start_engagement(now)
            else:
                hb = self.link.heartbeat
                note = (f" (already in {hb.mode} at start: switch out and back to engage)"
                        if hb.in_companion_mode else "")
                self._set_phase(FlightPhase.WAITING_FOR_PILOT,
                                f"ready: waiting for the pilot to select {self._companion_mode_name()}{note}")
        return np.zeros(3)

    def _phase_waiting_for_pilot(self, now: float, info: dict) -> np.ndarray | None:
        hb = self.link.heartbeat
        problem = self._input_problem(now)
        if problem is not None:
            self._set_phase(FlightPhase.WAITING_FOR_TELEMETRY, f"stopped streaming: {problem}", level="warning")
            return None
        entered = hb.in_companion_mode and not self._was_in_companion_mode_at_start
        if not hb.in_companion_mode:
            self._was_in_companion_mode_at_start = False  # from now on, a switch into it engages
        if entered:
            self._engage("pilot selected " + hb.mode)
            return self._phase_flying_to_goal(now, info)
        return np.zeros(3)

    def _companion_mode_name(self) -> str:
        return "OFFBOARD" if self.link.heartbeat.kind is AutopilotKind.PX4 else "GUIDED"

    def _engage(self, why: str) -> None:
        self.engaged = True
        self._set_phase(FlightPhase.FLYING_TO_GOAL, f"engaged ({why}): flying to the goal")

    def _airborne(self) -> bool:
        odom = self.link.odometry
        return odom is not None and -odom.pos_ned[2] > 0.5 and self.link.heartbeat.armed

    def _start_engagement(self, now: float) -> None:
        """Plan the --arm sequence for this autopilot and start it."""
        hb = self.link.heartbeat
        airborne = self._airborne()
        if hb.kind is AutopilotKind.PX4:  # arm, OFFBOARD, climb in OFFBOARD
            sequence = [] if hb.armed else [FlightPhase.ARMING]
            sequence += [FlightPhase.SWITCHING_MODE]
        else:  # GUIDED, arm, NAV_TAKEOFF
            sequence = [FlightPhase.SWITCHING_MODE] + ([] if hb.armed else [FlightPhase.ARMING])
        if not airborne and self.config.takeoff_alt_m is not None:
            sequence.append(FlightPhase.TAKING_OFF)
        self._sequence = sequence
        self._next_in_sequence(now, "starting automatic engagement (--arm)")

    def _next_in_sequence(self, now: float, why: str) -> None:
        if not self._sequence:
            self._engage(why)
            return
        phase = self._sequence.pop(0)
        self._pending = None
        hb = self.link.heartbeat
        if phase is FlightPhase.ARMING:
            self._pending = self.link.queue_command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1, label="arming")
        elif phase is FlightPhase.SWITCHING_MODE:
            main = PX4_MAIN_MODE_OFFBOARD if hb.kind is AutopilotKind.PX4 else ARDUCOPTER_GUIDED
            self._pending = self.link.queue_command(mavlink.MAV_CMD_DO_SET_MODE,
                                                    mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, main, 0,
                                                    label=f"switch to {self._companion_mode_name()}")
        elif phase is FlightPhase.TAKING_OFF:
            self.engaged = hb.in_companion_mode
            if hb.kind is AutopilotKind.ARDUPILOT:
                self._pending = self.link.queue_command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, 0, 0,
                                                        self.config.takeoff_alt_m, label="takeoff")
        self._set_phase(phase, why)

    def _command_failed(self, now: float) -> bool:
        """True (and the process ends) if the engagement step's command failed or stalled."""
        reason = None
        if self._pending is not None and self._pending.done and not self._pending.accepted:
            reason = self._pending.describe_failure()
        elif self.phase in (FlightPhase.ARMING, FlightPhase.SWITCHING_MODE) and now - self.phase_since_s > 10.0:
            reason = f"{self.phase.value}: the autopilot accepted but did not get there within 10 s"
        if reason is None:
            return False
        self._event("engage", reason, level="error")
        self._finish(ExitCode.ENGAGE_FAILED, reason)
        return True

    def _phase_arming(self, now: float, info: dict) -> np.ndarray | None:
        if self._command_failed(now):
            return self._hold_if_streaming()
        if self.link.heartbeat.armed and self._pending is not None and self._pending.done:
            self._next_in_sequence(now, "armed")
        return self._hold_or_none(now, info)

    def _phase_switching_mode(self, now: float, info: dict) -> np.ndarray | None:
        if self._command_failed(now):
            return self._hold_if_streaming()
        hb = self.link.heartbeat
        if hb.in_companion_mode:
            # The autopilot is there, answered or not: engaged from now on, so leaving the mode is a
            # takeover, and an unanswered request must not be retried later (it would take the vehicle
            # back from a pilot who switched away in between).
            if self._pending is not None and not self._pending.done:
                self.link.cancel_commands()
            self._pending = None
            self.engaged = True
            self._was_in_companion_mode_at_start = True
            self._next_in_sequence(now, f"autopilot in {hb.mode}")
        return self._hold_or_none(now, info)

    def _hold_or_none(self, now: float, info: dict) -> np.ndarray | None:
        """Hold setpoints during engagement (PX4 needs the stream; ArduPilot does not mind)."""
        if self.phase not in _STREAMING:
            return None
        problem = self._input_problem(now, need_depth=False)
        if problem is not None:
            info["hold"] = problem
        return np.zeros(3)

    def _phase_taking_off(self, now: float, info: dict) -> np.ndarray | None:
        odom = self.link.odometry
        target = float(self.config.takeoff_alt_m)
        if now - self.phase_since_s > self.config.takeoff_timeout_s:
            self._finish(ExitCode.ENGAGE_FAILED, f"takeoff to {target:g} m not done within {self.config.takeoff_timeout_s:g} s")
            return np.zeros(3) if self.link.heartbeat.kind is AutopilotKind.PX4 else None
        if self.link.heartbeat.kind is AutopilotKind.ARDUPILOT:
            if self._command_failed(now):
                return None
            if odom is not None and -odom.pos_ned[2] >= target - 0.2 and self._pending is not None and self._pending.done:
                self.engaged = True
                self._next_in_sequence(now, f"reached {-odom.pos_ned[2]:.1f} m")
            return None  # ArduPilot's guided takeoff: a velocity setpoint would cancel it
        problem = self._input_problem(now, need_depth=False)
        if problem is not None:
            info["hold"] = problem
            return np.zeros(3)
        altitude_error_m = target - (-odom.pos_ned[2])
        if abs(altitude_error_m) < 0.2:
            self._next_in_sequence(now, f"reached {-odom.pos_ned[2]:.1f} m")
            return np.zeros(3)
        # Climb in OFFBOARD at the policy's own vertical bound, straight above the point where the takeoff
        # started: a position target that rises at that rate (velocity setpoints alone let PX4 SIH drift by
        # up to 3.2 m on the way up to 8 m). The velocity logged is the climb the target asks for.
        if self._takeoff_from is None:
            self._takeoff_from = (np.array(odom.pos_ned, dtype=np.float64), float(odom.yaw_rad))
        start, yaw = self._takeoff_from
        climb_m_s = -float(self.low[1])  # the policy's climb bound (down is positive)
        rise_m = min(climb_m_s * (now - self.phase_since_s), max(target + start[2], 0.0))
        self._point_target = (np.array([start[0], start[1], start[2] - rise_m]), yaw)
        vel_down = float(np.clip(-1.0 * altitude_error_m, self.low[1], self.high[1]))
        return np.array([0.0, vel_down, 0.0])

    def _phase_flying_to_goal(self, now: float, info: dict) -> np.ndarray | None:
        odom = self.link.odometry
        if self.goal_ned is None:
            info["hold"] = "no goal (send one with SET_POSITION_TARGET_LOCAL_NED to component 191)"
            self._keep_station(now)
            return self._hold(info)
        self._station = None
        if odom is not None and self.link.odometry_age_s(now) <= self.stale_s:
            dist = float(np.linalg.norm(self.goal_ned - odom.pos_ned))
            info["dist_m"] = dist
            if dist <= self.arrival_radius_m:
                return self._arrive(now, dist, info)
        problem = self._input_problem(now)
        if problem is not None:
            info["hold"] = problem
            return self._hold(info)
        frame = self.latest_frame
        # The answer is due before its frame goes stale (acting on older data is acting on stale
        # data) and before the next tick (a late answer must not delay that tick's setpoint).
        deadline_s = min(frame.arrival_s + self.stale_s, now + self.period_s)
        busy_since = self.worker.busy_since_s
        if busy_since is not None:  # a late call is still running: it cannot take a new observation
            info["hold"] = (f"policy inference late (a call abandoned at its deadline is still running after "
                            f"{(now - busy_since) * 1000:.0f} ms)")
            return self._hold(info)
        if deadline_s - now < MIN_INFERENCE_TIME_S:  # no time left to act on this frame: do not start a call
            info["hold"] = (f"policy inference late (no time left: the frame is {(now - frame.arrival_s) * 1000:.0f} ms "
                            f"old, stale at {self.stale_s * 1000:.0f} ms)")
            return self._hold(info)
        info["frame"] = frame
        # After a gap in depth (no policy step for longer than the stale limit), start the stack
        # afresh (as at an episode start) rather than mixing frames from before the gap with new
        # ones. Otherwise push the newest frame if the camera delivered one since the last push;
        # if it missed this period, keep the stack as it is: a frame twice in the stack is
        # something training never shows (the simulator renders a new frame every step).
        pose = (odom.pos_ned[None], np.array([odom.yaw_rad]))
        if now - self._last_pushed_s > self.stale_s:
            self.stack.reset(frame.depth_m)
            if self.memory is not None:
                self.memory.reset(frame.depth_m[None], *pose)
            self._governor_turning[:] = 0.0  # a turn decided before the gap is not carried over it
            self._stack_seqs = [frame.seq] * self.policy.camera.history_frames
            info["stacked"] = "reset"
        elif frame.arrival_s > self._last_stacked_arrival_s:
            self.stack.push(frame.depth_m)
            if self.memory is not None:
                self.memory.push(frame.depth_m[None], *pose)
            self._stack_seqs = self._stack_seqs[1:] + [frame.seq]
            info["stacked"] = "pushed"
        else:
            info["stacked"] = "kept"  # the camera missed this period: no new frame to add
        self._last_stacked_arrival_s = max(self._last_stacked_arrival_s, frame.arrival_s)
        info["stack_seqs"] = [self._stack_seqs[c] for c in self.policy.camera.history_columns]  # the frames the policy sees
        self._last_pushed_s = now
        state = build_state(odom.pos_ned[None], np.array([odom.yaw_rad]), odom.vel_ned[None],
                            np.array([odom.yaw_rate_rad_s]), self.goal_ned[None])
        if self.memory is not None:
            state = np.concatenate([state, self.memory.sector_ranges(*pose)], axis=1)
        info["state"] = state[0]
        job = self.worker.submit(self.stack.frames, state)
        answer = self.worker.wait(job, deadline_s)
        if answer is None:  # the hold goes out now; the answer is discarded when it comes
            given_up = time.monotonic()
            info["hold"] = (f"policy inference late (no answer {(given_up - now) * 1000:.0f} ms into the call, "
                            f"{(given_up - frame.arrival_s) * 1000:.0f} ms since the frame; deadline: the frame's "
                            f"{self.stale_s * 1000:.0f} ms stale limit or the next tick)")
            return self._hold(info)
        raw, error, info["inference_s"] = answer
        if error is not None:  # a TorchScript runtime error must not take the loop down
            info["hold"] = f"policy raised {type(error).__name__}: {torchscript_error_line(error)}"
            return self._hold(info)
        self.inference_s.append(info["inference_s"])
        info["policy"] = raw
        if raw.shape != (3,) or not np.all(np.isfinite(raw)):
            info["hold"] = f"policy output not finite: {np.round(raw, 3).tolist()}"
            return self._hold(info)
        command = np.clip(raw, self.low, self.high)
        info["clamped"] = bool(np.any(command != raw))
        if self.config.face_goal is not None:  # the policy ran (its stack stays fresh); its command waits
            facing_s = now - max(self._goal_set_s, self.phase_since_s)
            facing = facing_s < self.config.face_goal.hold_s
            if facing != self._facing:  # the turn starts or ends: say so, with the bearing left
                bearing_deg = math.degrees(float(goal_bearing_frd_rad(odom.pos_ned, odom.yaw_rad, self.goal_ned)))
                self._event("face_goal", f"turning to face the goal ({bearing_deg:+.0f} deg off): the policy flies "
                                         f"{self.config.face_goal.hold_s:g} s after the goal" if facing else
                            f"facing the goal ({bearing_deg:+.0f} deg off): the policy flies", bearing_deg=bearing_deg)
            if facing:
                # What the simulator flies (zero velocity, a yaw rate to the goal) is logged as the command; the
                # autopilot gets the same as a position target: the point where the turn started and the heading
                # to the goal, so it holds its altitude while it turns (PX4 drifted by metres on zero velocity
                # and a yaw rate) and turns at its own rate.
                command = face_goal_commands(odom.pos_ned[None], np.array([odom.yaw_rad]), self.goal_ned[None],
                                             float(self.high[2]), self.config.face_goal)[0].astype(np.float64)
                info["face_goal_s"] = facing_s
                if not self._facing:
                    self._face_hold_ned = np.array(odom.pos_ned, dtype=np.float64)
                self._point_target = (self._face_hold_ned, goal_heading_rad(self._face_hold_ned, self.goal_ned))
            self._facing = facing
        if self.governor is not None:  # on the newest frame the policy saw, as in the simulator's evaluation
            governed, capped, nearest, self._governor_turning = self.governor.apply(
                self.stack.frames[:, -1], command[None], self._governor_turning)
            info["governor"] = {"nearest_m": float(nearest[0]) if np.isfinite(nearest[0]) else None,
                                "capped": bool(capped[0]), "turned": bool(governed[0, 2] != command[2])}
            self.governed_steps += int(capped[0])
            command = governed[0].astype(np.float64)
        info["policy_step"] = True
        self.policy_steps += 1
        self._note_hold(None)
        return command

    def _hold(self, info: dict) -> np.ndarray:
        self._note_hold(info.get("hold"))
        return np.zeros(3)

    def _keep_station(self, now: float) -> None:
        """No goal yet: hold the point where the wait began (a position target) rather than a zero velocity,
        on which PX4 drifts (by 1-2 m in 5-8 s on PX4 SIH). Without fresh odometry: zero velocity."""
        odom = self.link.odometry
        if odom is None or self.link.odometry_age_s(now) > self.stale_s:
            return
        if self._station is None:
            self._station = (np.array(odom.pos_ned, dtype=np.float64), float(odom.yaw_rad))
            self._event("station", f"no goal: holding the point {np.round(self._station[0], 2).tolist()} until one "
                                   "arrives", hold_point_ned=self._station[0])
        self._point_target = self._station

    def _note_hold(self, reason: str | None) -> None:
        """Log failsafe holds when they start, change reason, and end (not every step)."""
        kind = None if reason is None else reason.split(" (")[0].split(":")[0]
        last = None if self._last_hold_reason is None else self._last_hold_reason.split(" (")[0].split(":")[0]
        if kind != last:
            if reason is None:
                self._event("failsafe", "failsafe cleared: the policy flies again", cleared=True)
            else:
                what = "zero velocity" if self._point_target is None else "position hold"
                self._event("failsafe", f"HOLD ({what}): {reason}", level="warning", reason=reason)
        self._last_hold_reason = reason

    def _arrive(self, now: float, dist: float, info: dict) -> np.ndarray | None:
        self._note_hold(None)
        self._event("arrived", f"arrived: {dist:.2f} m from the goal {np.round(self.goal_ned, 2).tolist()}",
                    dist_m=dist, goal_ned=self.goal_ned)
        if self.config.land_on_arrival:
            self._pending = self.link.queue_command(mavlink.MAV_CMD_NAV_LAND, 0, 0, 0, math.nan, 0, 0, 0, label="landing")
            self._set_phase(FlightPhase.LANDING, "landing on arrival (--land-on-arrival)")
            return np.zeros(3)  # one last hold; the land mode takes over
        odom = self.link.odometry
        self._hold_point = (self.goal_ned.copy(), float(odom.yaw_rad))  # keep the heading it arrived with
        self._set_phase(FlightPhase.HOLDING_AT_GOAL, "holding at the goal (position target)")
        if self.config.exit_on_arrival:
            self._finish(ExitCode.OK, "arrived at the goal")
        return np.zeros(3)

    def _phase_holding_at_goal(self, now: float, info: dict) -> np.ndarray | None:
        odom = self.link.odometry
        if odom is not None and self.goal_ned is not None:
            info["dist_m"] = float(np.linalg.norm(self.goal_ned - odom.pos_ned))
        return np.zeros(3)

    def _phase_landing(self, now: float, info: dict) -> np.ndarray | None:
        hb = self.link.heartbeat
        if self._pending is not None and self._pending.done and not self._pending.accepted:
            reason = self._pending.describe_failure()
            self._pending = None
            self._event("landing", reason, level="error")
            if self.config.exit_on_arrival:
                self._finish(ExitCode.ENGAGE_FAILED, reason)
            self._set_phase(FlightPhase.HOLDING_AT_GOAL, "landing refused: holding at the goal instead", level="warning")
            return np.zeros(3)
        if not hb.armed:
            self.landed = True
            self._set_phase(FlightPhase.LANDED, "landed and disarmed")
            if self.config.exit_on_arrival:
                self._finish(ExitCode.OK, "arrived and landed")
            return None
        if not hb.landing and not hb.in_companion_mode and self._pending is not None and self._pending.done:
            self._hand_back(f"pilot took over during landing: mode {hb.mode}")
            if self.config.exit_on_arrival:
                self._finish(ExitCode.PILOT_TOOK_OVER, f"pilot took over during landing (mode {hb.mode})")
        return None

    def _phase_landed(self, now: float, info: dict) -> np.ndarray | None:
        return None

    def _phase_handed_back(self, now: float, info: dict) -> np.ndarray | None:
        return None

    def _phase_link_lost(self, now: float, info: dict) -> np.ndarray | None:
        if self.link.heartbeat_age_s(now) <= self.config.link_timeout_s:
            if self.landed:  # a link blip on the ground must not start a second flight (--arm)
                self._set_phase(FlightPhase.LANDED, "link back; the flight is over (restart the companion to fly again)")
            elif self.engaged:
                self._hand_back("link back; not re-engaging on our own (restart the companion to fly again)")
            else:
                self._set_phase(FlightPhase.WAITING_FOR_TELEMETRY, "link back")
        return None

    def _who_took_over(self, now: float) -> str:
        """Who most likely changed the mode: the autopilot's setpoint-loss failsafe right after a stall, else the pilot.

        The heartbeat carries only the new mode; PX4 gives its failsafe's reason in an EVENT message whose text needs
        the autopilot's event metadata, so the companion names what it knows itself: its own stall.
        """
        if self._last_stall is not None and now - self._last_stall[0] <= STALL_TAKEOVER_WINDOW_S:
            ended_s, gap_s = self._last_stall
            return (f"autopilot took over (its setpoint-loss failsafe, most likely: {now - ended_s:.1f} s after "
                    f"this computer stalled {gap_s:.2f} s without a setpoint)")
        return "pilot took over"

    def _hand_back(self, why: str) -> None:
        """The pilot has the vehicle, for good: no setpoint, mode or arming request ever again."""
        self.engaged = False
        self.taken_over = True
        self._sequence, self._pending = [], None
        self.link.cancel_commands()  # no queued arm/mode/takeoff request may go out after this
        self._set_phase(FlightPhase.HANDED_BACK, why, level="warning")

    def _watch_link_after_takeover(self, now: float) -> None:
        """Report link loss and return after a takeover; the phase stays handed_back."""
        down = self.link.heartbeat_age_s(now) > self.config.link_timeout_s
        if down == self._link_down_after_takeover:
            return
        self._link_down_after_takeover = down
        if down:
            self._event("link", f"link lost after the takeover: no heartbeat for {self.link.heartbeat_age_s(now):.1f} s; "
                        "staying handed back", level="warning", lost=True)
            if self.config.exit_on_arrival:
                self._finish(ExitCode.LINK, "link to the autopilot lost")
        else:
            self._event("link", "link back after the takeover; staying handed back (the pilot has the vehicle)",
                        level="warning", lost=False)

    # ================================================================== bookkeeping
    def _set_phase(self, phase: FlightPhase, why: str, level: str = "info") -> None:
        old = self.phase
        self.phase = phase
        self.phase_since_s = time.monotonic()
        self._event("phase", f"{phase.value}: {why}" if old is not phase else why, level=level,
                    to=phase.value, **{"from": old.value})
        self.notifier.status(f"{phase.value}: {why}"[:200])
        if level in ("warning", "error"):
            severity = mavlink.MAV_SEVERITY_WARNING if level == "warning" else mavlink.MAV_SEVERITY_ERROR
            try:
                self.link.send_statustext(severity, f"companion: {phase.value}")
            except OSError:
                pass

    def _event(self, event: str, message: str, level: str = "info", **fields) -> None:
        self.log.event(event, message, level=level, step=self.step_index, phase=self.phase.value, **fields)

    def _finish(self, code: ExitCode, reason: str) -> None:
        """Stop the loop with ``code``; :meth:`_leave` then leaves the vehicle holding and the exit is logged."""
        if self.exit_code is None:
            self.exit_code, self.exit_reason = code, reason

    def _in_control(self, now: float) -> bool:
        """The autopilot follows our setpoints right now (engaged, in OFFBOARD/GUIDED, armed, link up)."""
        hb = self.link.heartbeat
        return (hb is not None and self.engaged and not self.taken_over and hb.in_companion_mode and hb.armed
                and self.link.heartbeat_age_s(now) <= self.config.link_timeout_s
                and self.phase not in (FlightPhase.LANDING, FlightPhase.LANDED, FlightPhase.HANDED_BACK,
                                       FlightPhase.LINK_LOST))

    def _leave(self) -> None:
        """Leave on purpose without leaving the vehicle to a failsafe (issue 18, items 1 and 8).

        While streaming: a hold for ``EXIT_HOLD_STREAM_S``, so the last setpoints cannot be the
        ones lost when the link closes — a position target at the goal when holding there,
        otherwise zero velocity (the vehicle stops where its braking takes it, instead of flying
        back to where the exit began). Then, if the companion flies the vehicle (ArduPilot; PX4 only
        at the goal), the stop is awaited and a position target streamed where it stopped (or at the
        goal) until the vehicle has settled on it (:meth:`_settled_at`, at most ``EXIT_SETTLE_MAX_S``); then its hold mode
        (:data:`HOLD_MODES`) is requested, the hold streamed on until the HEARTBEAT shows it (at
        most ``HAND_OVER_TIMEOUT_S``), and the result reported (log and STATUSTEXT). A pilot's
        takeover is final: then nothing is sent or requested.
        """
        now = time.monotonic()
        hb = self.link.heartbeat
        if hb is None or self.taken_over or self.phase not in _STREAMING | {FlightPhase.TAKING_OFF}:
            return
        in_control = self._in_control(now)
        # ArduCopter: stop (zero velocity), then hold where it stopped until settled, then BRAKE
        # (EXIT_SETTLE_MAX_S). PX4's AUTO.LOITER brakes from any speed by itself (it holds the
        # braking point it computes on entry), so PX4 stopped on the way gets a position hold where the
        # vehicle is and the hand-over at once: on real PX4 SIH that moved 0.75 m after the stop, the
        # settling sequence 1.35 m. At the goal, though, PX4 too settles on the goal first: handed over
        # at the arrival speed (up to 1.9 m/s), AUTO.LOITER held its braking point 1.65-1.84 m past the goal.
        settle = hb.kind is AutopilotKind.ARDUPILOT or self._holding_point()
        odom = self.link.odometry
        if self._holding_point():
            point = self._hold_point
        elif (hb.kind is AutopilotKind.PX4 and odom is not None and self.link.odometry_age_s(now) <= self.stale_s
              and self.phase is not FlightPhase.TAKING_OFF):
            point = (odom.pos_ned.copy(), float(odom.yaw_rad))
        else:
            point = None  # zero velocity
        hold = [point]  # what send_hold streams; _settle replaces it with where the vehicle stopped

        def send_hold() -> None:
            try:
                if hold[0] is not None:
                    self.link.send_position_target(*hold[0])
                else:
                    self.link.send_velocity_setpoint(0.0, 0.0, 0.0)
            except OSError:
                pass

        def pump(until_s: float, done=lambda: False) -> bool:
            """Stream the hold and serve the link until ``until_s`` or ``done()``; True if done."""
            next_send, next_heartbeat = time.monotonic(), time.monotonic() + 1.0
            while True:
                now_s = time.monotonic()
                self._read_link(now_s)
                self.link.service_commands(now_s)
                self.notifier.watchdog(now_s)  # leaving can take ~11 s; systemd's WatchdogSec is 2 s
                if done():
                    return True
                if now_s >= until_s:
                    return False
                if now_s >= next_send:
                    send_hold()
                    next_send += 1.0 / EXIT_HOLD_RATE_HZ
                if now_s >= next_heartbeat:
                    self.link.send_heartbeat()
                    next_heartbeat += 1.0
                fd = self.link.fileno()
                wait = max(0.0, min(next_send, until_s) - time.monotonic())
                if fd is not None:
                    select.select([fd], [], [], wait)
                else:
                    time.sleep(min(wait, 0.005))

        what = "zero velocity" if point is None else "a position hold at the goal" if self._holding_point() else "a position hold"
        self._event("leaving", f"leaving: streaming {what} for {EXIT_HOLD_STREAM_S:g} s"
                    + (", then a position hold until settled" if in_control and settle else "")
                    + (f", then handing over to {HOLD_MODES[hb.kind]}" if in_control else ""),
                    hold_point_ned=None if point is None else point[0], in_control=in_control)
        started = time.monotonic()
        pump(started + EXIT_HOLD_STREAM_S)
        if not in_control:
            return
        if settle:
            self._settle(pump, hold, started)
        self._hand_over(pump)

    def _settle(self, pump, hold: list, started: float) -> None:
        """ArduCopter, before BRAKE: wait for the stop, then hold a position target where it stopped
        (``hold[0]`` is what the pump streams: None, zero velocity, or the goal's hold) until the
        vehicle has settled on it, at most EXIT_SETTLE_MAX_S after ``started``."""
        if hold[0] is None:  # stopping: wait for the stop, then hold where it stopped
            pump(started + EXIT_SETTLE_MAX_S, lambda: self._settled_at(None) or self._odometry_lost())
            odom = self.link.odometry
            if odom is not None and self.link.odometry_age_s(time.monotonic()) <= self.stale_s:
                hold[0] = (odom.pos_ned.copy(), float(odom.yaw_rad))
        point = hold[0]
        if point is not None:
            pump(started + EXIT_SETTLE_MAX_S, lambda: self._settled_at(point[0]) or self._odometry_lost())
            settled = self._settled_at(point[0])
            odom = self.link.odometry
            self._event("hold_settled" if settled else "hold_not_settled",
                        f"{'settled' if settled else 'not settled'} on the position hold "
                        f"{time.monotonic() - started:.2f} s after leaving began", level="info" if settled else "warning",
                        hold_point_ned=point[0],
                        distance_m=None if odom is None else round(float(np.linalg.norm(odom.pos_ned - point[0])), 3),
                        speed_m_s=None if odom is None else round(float(np.linalg.norm(odom.vel_ned)), 3))

    def _odometry_lost(self) -> bool:
        """No odometry fresher than the staleness limit: nothing to wait for while leaving."""
        return self.link.odometry is None or self.link.odometry_age_s(time.monotonic()) > self.stale_s

    def _settled_at(self, point_ned: np.ndarray | None) -> bool:
        """The vehicle (fresh odometry) is slower than EXIT_SETTLED_SPEED_M_S and, given a point,
        within EXIT_SETTLED_DISTANCE_M of ``point_ned``."""
        odom = self.link.odometry
        if odom is None or self.link.odometry_age_s(time.monotonic()) > self.stale_s:
            return False
        near = point_ned is None or float(np.linalg.norm(odom.pos_ned - point_ned)) <= EXIT_SETTLED_DISTANCE_M
        return near and float(np.linalg.norm(odom.vel_ned)) <= EXIT_SETTLED_SPEED_M_S

    def _hand_over(self, pump) -> None:
        """Ask for the hold mode while streaming the hold; report whether the autopilot got there."""
        hb = self.link.heartbeat
        mode = HOLD_MODES[hb.kind]
        if hb.kind is AutopilotKind.PX4:
            main, sub = PX4_MODE_BY_NAME[mode]
        else:
            main, sub = ARDUCOPTER_MODE_BY_NAME[mode], 0
        self.link.cancel_commands()
        pending = self.link.queue_command(mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
                                          main, sub, label=f"switch to {mode}")
        started = time.monotonic()

        def settled() -> bool:
            current = self.link.heartbeat
            if current.mode == mode:
                return True
            if self.link.heartbeat_age_s(time.monotonic()) > self.config.link_timeout_s:
                return True  # the autopilot is gone: nobody to hand over to (reported as not confirmed)
            if not current.in_companion_mode:  # the pilot chose another mode meanwhile: theirs, final
                return True
            # Only a refusal ends the wait early: a lost COMMAND_ACK does not mean the switch was lost,
            # the HEARTBEAT can still show it (seen on a loaded TCP link).
            return pending.result is not None and not pending.accepted

        pump(started + HAND_OVER_TIMEOUT_S, settled)
        current = self.link.heartbeat
        elapsed = time.monotonic() - started
        if current.mode == mode:
            message, level = f"handed the vehicle to {mode} ({elapsed:.2f} s): holding position", "info"
        elif not current.in_companion_mode:
            message, level = f"the pilot selected {current.mode} while handing over: left to the pilot", "warning"
        else:
            why = pending.describe_failure() if pending.done else f"no {mode} in the HEARTBEAT within {HAND_OVER_TIMEOUT_S:g} s"
            tail = ("PX4's offboard-loss failsafe (COM_OBL_RC_ACT) acts after COM_OF_LOSS_T" if hb.kind is AutopilotKind.PX4
                    else "ArduPilot holds the last position target in GUIDED")
            message, level = f"hand-over to {mode} failed: {why}; {tail}", "error"
        self.link.cancel_commands()
        self._event("handover", message, level=level, mode=current.mode, requested=mode,
                    confirmed=current.mode == mode, seconds=round(elapsed, 3))
        try:
            self.link.send_statustext(mavlink.MAV_SEVERITY_INFO if level == "info" else mavlink.MAV_SEVERITY_WARNING,
                                      f"companion: exit, vehicle in {current.mode}")
        except OSError:
            pass

    def _hold_on_the_way_out(self) -> None:
        """Leave the vehicle stopped: a few zero-velocity setpoints before the stream ends."""
        if self.phase not in _STREAMING or self.link.heartbeat is None:
            return
        try:
            for _ in range(3):
                self.link.send_velocity_setpoint(0.0, 0.0, 0.0)
        except OSError:
            pass

    def _write_summary(self, final: bool) -> None:
        """Statistics since the last summary (every 10 s) or of the whole flight (``final``).

        Both cost O(samples in 10 s) or O(histogram bins), never O(flight length): the tick
        that writes one must stay on time after hours of flight.
        """
        self._last_summary_s = time.monotonic()

        def stats(series: RunningStats) -> dict:
            return series.total() if final else series.window()

        self.log.summary(
            final=final, window="flight" if final else "10 s", steps=self.step_index,
            policy_steps=self.policy_steps, holds=self.holds, governed_steps=self.governed_steps,
            frame_to_setpoint_ms=stats(self.latency_s), inference_ms=stats(self.inference_s),
            tick_late_ms=stats(self.tick_late_s), period_jitter_ms=stats(self.period_dev_s),
            overruns=self.overruns, missed_ticks=self.clock.missed_ticks,
            setpoints_sent=self.link.setpoints_sent, refused_unsigned=self.link.refused_unsigned,
            dropped_foreign_address=self.link.dropped_foreign_address, dropped_foreign_link=self.link.dropped_foreign_link,
            obstacle_distance_sent=self.obstacles.sent if self.obstacles else 0,
            phase=self.phase.value, **resident_memory_mb(),
        )
