"""Argument types shared by the simulator's command lines (clear argparse errors, exit 2)."""

from __future__ import annotations

import argparse
import math


def positive_int(text: str) -> int:
    """An integer >= 1."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def positive_float(text: str) -> float:
    """A finite number > 0."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not value > 0 or not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {text}")
    return value


def udp_port(text: str) -> int:
    """A port number in 0..65535."""
    if not text.isdigit() or not 0 <= int(text) <= 65535:
        raise argparse.ArgumentTypeError(f"port must be a number in 0..65535, got {text!r}")
    return int(text)


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


def image_size(text: str) -> tuple[int, int]:
    """``WIDTHxHEIGHT`` in pixels, both >= 1."""
    try:
        width, height = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"camera size must be WIDTHxHEIGHT, got {text!r}") from None
    if width < 1 or height < 1:
        raise argparse.ArgumentTypeError(f"camera size must be positive, got {text!r}")
    return width, height


def cylinder_rows(cylinders: list[list[float]] | None) -> list[list[float]] | None:
    """``--cylinder N,E,R[,H]`` values as the camera's rows (north, east, radius, z_top, z_bottom)."""
    if not cylinders:
        return None
    return [[c[0], c[1], c[2], -(c[3] if len(c) == 4 else 30.0), 0.0] for c in cylinders]


def check_camera(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Exit 2 with the reason unless ``--camera-size``, ``--hfov`` and ``--max-range`` make a valid camera."""
    from companion.spec import CameraSpec

    try:
        CameraSpec(width=args.camera_size[0], height=args.camera_size[1], hfov_deg=args.hfov, max_range_m=args.max_range)
    except ValueError as err:
        parser.error(str(err))
