"""Argument types shared by the simulator's command lines (clear argparse errors, exit 2).

Every option of ``sitl.vehicle``, ``sitl.world``, ``sitl.swarm_test`` and ``sitl.train``
goes through one of these parsers, so a bad value (NaN, inf, negative, zero, huge, wrong
type, unwritable path, missing file) ends in argparse's one-line ``error: ...`` and exit 2,
never a traceback. ``companion`` has its own (it must not import ``sitl``).
"""

from __future__ import annotations

import argparse
import math
import os
import socket
import tempfile
from pathlib import Path

from companion.depth_wire import HEADER_SIZE, MAX_DATAGRAM

#: Most vehicles one process simulates: vehicle i is MAVLink system i + 1 (1..255).
MAX_VEHICLES = 255
#: Largest rendered depth frame: sitl sends float32 metres, one frame per UDP datagram.
MAX_CAMERA_PIXELS = (MAX_DATAGRAM - HEADER_SIZE) // 4
#: Fastest simulated camera (Hz): a RealSense streams depth at up to 90 fps.
MAX_CAMERA_HZ = 200.0
#: Most sub-rays per pixel side (the render costs supersample^2 rays per pixel).
MAX_SUPERSAMPLE = 16
#: Most torch threads a command line may ask for.
MAX_THREADS = 256


class ArgumentParser(argparse.ArgumentParser):
    """argparse's parser, but a bad value prints one line, ``PROG: error: ...``, and exits 2.

    argparse prints the whole usage block first; in a log or a systemd journal the reason
    then hides below a wall of options. ``--help`` still shows the usage.
    """

    def error(self, message: str):  # noqa: D102 - argparse's API
        self.exit(2, f"{self.prog}: error: {' '.join(message.split())} (see --help)\n")

    def parse_known_args(self, args=None, namespace=None):  # noqa: D102 - argparse's API
        import sys

        from companion.cli import join_negative_values  # --start -24,0,-8 taken as written

        argv = sys.argv[1:] if args is None else list(args)
        return super().parse_known_args(join_negative_values(self, argv), namespace)


def positive_int(text: str) -> int:
    """An integer >= 1."""
    return int_range(1)(text)


def int_range(low: int, high: int | None = None):
    """A parser of integers in ``low..high`` (no upper limit if ``high`` is None)."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if value < low or (high is not None and value > high):
            limit = f">= {low}" if high is None else f">= {low} and <= {high}"
            raise argparse.ArgumentTypeError(f"must be {limit}, got {value}")
        return value
    return parse


def int_list(low: int, high: int | None = None, allow_empty: bool = False):
    """A parser of comma-separated integers in ``low..high`` (``""`` is ``[]`` only with ``allow_empty``)."""
    def parse(text: str) -> list[int]:
        try:
            values = [int(v) for v in text.split(",") if v.strip()]
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {text!r}") from None
        if (not values and not allow_empty) or any(v < low or (high is not None and v > high) for v in values):
            limit = f"of at least {low}" if high is None else f"in {low}..{high}"
            raise argparse.ArgumentTypeError(f"expected integers {limit}, got {text!r}")
        return values
    return parse


def integer(text: str) -> int:
    """Any integer (ranges are checked where the value is used)."""
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None


def finite_float(text: str) -> float:
    """Any finite number."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text}")
    return value


def positive_float(text: str) -> float:
    """A finite number > 0."""
    return float_range(0.0, math.inf, low_open=True)(text)


def positive_floats(text: str) -> list[float]:
    """Comma-separated finite numbers > 0 (e.g. ``1.5,1.5,1,1``)."""
    try:
        return [positive_float(v) for v in text.split(",")]
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers > 0, got {text!r}") from None


def float_range(low: float, high: float, *, low_open: bool = False, high_open: bool = False):
    """A parser of finite numbers between ``low`` and ``high`` (``*_open``: that end excluded)."""
    def parse(text: str) -> float:
        value = finite_float(text)
        above = value > low if low_open else value >= low
        below = value < high if high_open else value <= high
        if not (above and below):
            upper = "" if high == math.inf else f" and {'<' if high_open else '<='} {high:g}"
            raise argparse.ArgumentTypeError(f"must be a finite number {'>' if low_open else '>='} {low:g}{upper}, "
                                             f"got {text}")
        return value
    return parse


def port_in(low: int, high: int):
    """An argparse type for a port number in ``low .. high``."""
    def parse(text: str) -> int:
        if not text.isdigit() or not low <= int(text) <= high:
            raise argparse.ArgumentTypeError(f"port must be a number in {low}..{high}, got {text!r}")
        return int(text)
    return parse


#: A port number in 0..65535 (0: none, where the option allows it).
udp_port = port_in(0, 65535)
#: A port number in 1..65535 (something is sent to it).
udp_port_nonzero = port_in(1, 65535)


def check_port_block(parser: argparse.ArgumentParser, name: str, first: int, count: int) -> None:
    """Exit 2 unless ports ``first .. first + count - 1`` all exist."""
    if first + count - 1 > 65535:
        parser.error(f"{name} {first}: the ports of {count} vehicles ({first}..{first + count - 1}) would pass 65535")


def host(text: str) -> str:
    """A host name or IPv4 address that resolves now (a typo fails here, not in the first send)."""
    try:
        socket.getaddrinfo(text, None, socket.AF_INET, socket.SOCK_DGRAM)
    except (socket.gaierror, UnicodeError, ValueError) as err:
        raise argparse.ArgumentTypeError(f"cannot resolve host {text!r} ({getattr(err, 'strerror', None) or err})") from None
    return text


def finite_floats(count: tuple[int, ...], name: str):
    """A parser of ``count`` comma-separated finite numbers (e.g. ``N,E,D``) for option ``name``."""
    def parse(text: str) -> list[float]:
        try:
            values = [float(v) for v in text.split(",")]
        except ValueError:
            raise argparse.ArgumentTypeError(f"{name} must be comma-separated numbers, got {text!r}") from None
        if len(values) not in count or not all(math.isfinite(v) for v in values):
            raise argparse.ArgumentTypeError(f"{name} needs {' or '.join(map(str, count))} finite numbers, got {text!r}")
        return values
    return parse


def response_spec(text: str):
    """A ``--response`` specification over the nominal kinematic response (:func:`sitl.sim.dynamics.parse_response`):
    a :class:`sitl.sim.dynamics.KinematicRandomization`."""
    from sitl.sim.dynamics import nominal_ranges, parse_response  # numba-compiled: only where the option is used

    try:
        return parse_response(text, nominal_ranges())
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None


def cylinder(text: str) -> list[float]:
    """``N,E,R[,H]``: a pole at N,E (m) with radius R > 0 and height H > 0."""
    values = finite_floats((3, 4), "--cylinder")(text)
    if values[2] <= 0 or (len(values) == 4 and values[3] <= 0):
        raise argparse.ArgumentTypeError(f"--cylinder radius and height must be > 0 m, got {text!r}")
    return values


def box(text: str) -> list[float]:
    """``N,E,D,HN,HE,HD``: a box centre (m) and its half sizes, all > 0."""
    values = finite_floats((6,), "--box")(text)
    if min(values[3:]) <= 0:
        raise argparse.ArgumentTypeError(f"--box half sizes must be > 0 m, got {text!r}")
    return values


def image_size(text: str) -> tuple[int, int]:
    """``WIDTHxHEIGHT`` in pixels, both >= 1, small enough for one depth datagram."""
    try:
        width, height = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"camera size must be WIDTHxHEIGHT, got {text!r}") from None
    if width < 1 or height < 1:
        raise argparse.ArgumentTypeError(f"camera size must be positive, got {text!r}")
    if width * height > MAX_CAMERA_PIXELS:
        raise argparse.ArgumentTypeError(f"camera size {width}x{height} has more than the {MAX_CAMERA_PIXELS} pixels "
                                         "a float32 depth frame can carry in one UDP datagram (e.g. 128x96)")
    return width, height


def _writable_dir(directory: Path) -> bool:
    """Whether a file can be created in ``directory``: tried, since os.access says yes to root on read-only mounts."""
    if not directory.is_dir():
        return False
    try:
        with tempfile.TemporaryFile(dir=directory):
            return True
    except OSError:
        return False


def output_file(text: str) -> str:
    """A file to write: ``-`` (stdout) or a path whose directory exists and is writable.

    A missing directory is refused rather than created: a typo must not scatter files.
    """
    if text == "-":
        return text
    path = Path(text)
    if path.is_dir():
        raise argparse.ArgumentTypeError(f"{text} is a directory, expected a file")
    parent = path.parent
    if not parent.is_dir():
        raise argparse.ArgumentTypeError(f"cannot write {text}: no such directory {str(parent)!r}")
    if not _writable_dir(parent) or (path.exists() and not os.access(path, os.W_OK)):
        raise argparse.ArgumentTypeError(f"cannot write {text}: permission denied")
    return text


def output_dir(text: str) -> Path:
    """A directory to write into, created if missing: its nearest existing ancestor must be a writable directory."""
    path = Path(text)
    ancestor = path
    while not ancestor.exists() and ancestor != ancestor.parent:
        ancestor = ancestor.parent
    if ancestor.exists() and not ancestor.is_dir():
        raise argparse.ArgumentTypeError(f"cannot write into {text}: {str(ancestor)!r} is not a directory")
    if not _writable_dir(ancestor if ancestor.exists() else Path.cwd()):
        raise argparse.ArgumentTypeError(f"cannot write into {text}: permission denied in {str(ancestor)!r}")
    return path


def output_file_in_new_dir(text: str) -> Path:
    """A file to write whose directory is created if missing (same checks as :func:`output_dir`)."""
    path = Path(text)
    if path.is_dir():
        raise argparse.ArgumentTypeError(f"{text} is a directory, expected a file")
    output_dir(str(path.parent))
    return path


def existing_file(text: str) -> str:
    """A file that exists and can be read."""
    path = Path(text)
    if not path.is_file():
        raise argparse.ArgumentTypeError(f"no such file {text!r}")
    if not os.access(path, os.R_OK):
        raise argparse.ArgumentTypeError(f"cannot read {text}: permission denied")
    return text


def cylinder_rows(cylinders: list[list[float]] | None) -> list[list[float]] | None:
    """``--cylinder N,E,R[,H]`` values as the camera's rows (north, east, radius, z_top, z_bottom)."""
    if not cylinders:
        return None
    return [[c[0], c[1], c[2], -(c[3] if len(c) == 4 else 30.0), 0.0] for c in cylinders]


def add_governor_flag(parser: argparse.ArgumentParser, extra_help: str = "") -> None:
    """``--governor [NAME]``: the companion's speed governor (``companion.governor.GOVERNOR_PRESETS``) after the
    controller; ``args.governor`` is the preset's name or None."""
    from companion.governor import DEFAULT_GOVERNOR, add_governor_argument, describe_presets

    add_governor_argument(
        parser, help="apply the companion's speed governor (companion --governor) to the controller's "
                      f"commands ({DEFAULT_GOVERNOR} with --governor alone; {describe_presets()}); the label gains "
                      "+governor (+governor-swarm)" + extra_help)


def camera_preset(text: str) -> str:
    """The name of a camera preset (a key of ``companion.spec.CAMERA_PRESETS``)."""
    from companion.spec import CAMERA_PRESETS

    if text not in CAMERA_PRESETS:
        raise argparse.ArgumentTypeError(f"unknown camera {text!r}; choose one of {', '.join(CAMERA_PRESETS)}")
    return text


def fits_camera(policy_camera, sensor) -> str | None:
    """Why a policy's camera cannot be cut from ``sensor``'s image (narrower in an axis), or None."""
    for axis, need, have in (("horizontal", policy_camera.tan_half_hfov, sensor.tan_half_hfov),
                             ("vertical", policy_camera.tan_half_vfov, sensor.tan_half_vfov)):
        if need > have * (1 + 1e-6):
            wanted = policy_camera.hfov_deg if axis == "horizontal" else policy_camera.vertical_fov_deg
            got = sensor.hfov_deg if axis == "horizontal" else sensor.vertical_fov_deg
            return f"the camera's {axis} field of view {got:.1f} deg is narrower than the policy's {wanted:.1f} deg"
    return None


def check_camera(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Exit 2 with the reason unless ``--camera-size``, ``--hfov`` and ``--max-range`` make a valid camera."""
    from companion.spec import CameraSpec

    try:
        CameraSpec(width=args.camera_size[0], height=args.camera_size[1], hfov_deg=args.hfov, max_range_m=args.max_range)
    except ValueError as err:
        parser.error(str(err))
