"""Tables and JSON of evaluation results (shared by ``swarm_test`` and its ``paper`` reproduction)."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

def collision_rate(summary: dict) -> float:
    """1 - success: every failure (UAV-UAV, ground, timeout), as the issue reports it."""
    if not summary.get("uav_episodes") or summary.get("success_rate") is None:
        return float("nan")
    return 1.0 - summary["success_rate"]


_TABLE_HEAD = ("success (± 95% CI)", "collision: all / UAV / ground / timeout", "SPL", "extra distance (m)",
               "average speed (m/s)")
_TABLE_HEAD_OBSTACLES = ("success (± 95% CI)", "collision: all / UAV / ground / obstacle / timeout", "SPL",
                         "extra distance (m)", "average speed (m/s)")


def _num(value, digits: int) -> str:
    """A number for a table; '-' for a missing one (NaN, or null read back from JSON)."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    return f"{value:.{digits}f}"


def _metric_cells(summary: dict | None, note: str = "not trained", obstacles: bool = False) -> list[str]:
    if summary is None:
        return [note] + ["-"] * (len(_TABLE_HEAD) - 1)
    ed, sp = summary["extra_distance_m"], summary["average_speed_m_s"]

    def mean_std(d: dict) -> str:
        return "-" if _num(d["mean"], 2) == "-" else f"{_num(d['mean'], 2)} ± {_num(d['std'], 2)}"

    half_width = summary.get("success_ci95_half_width")  # absent from cells saved before it existed
    success = _num(summary["success_rate"], 3)
    if _num(half_width, 3) != "-" and success != "-":
        success += f" ± {half_width:.3f}"
    return [
        success,
        f"{_num(collision_rate(summary), 3)} / {_num(summary['collision_uav_rate'], 3)} / "
        f"{_num(summary['collision_ground_rate'], 3)} / "
        + (f"{_num(summary.get('collision_obstacle_rate'), 3)} / " if obstacles else "")
        + f"{_num(summary['timeout_rate'], 3)}",
        _num(summary["spl"], 3),
        mean_std(ed),
        mean_std(sp),
    ]


def markdown_table(key_names: list[str], rows: list[tuple[list[str], dict | None]]) -> str:
    """A Markdown table of summaries; a row whose summary is None reads 'not trained'.

    Columns: the key columns, success rate, collision rate (1 - success) with its split,
    SPL, extra distance and average speed as mean ± std over UAVs and episodes.
    """
    # The obstacle column appears once a summary has obstacle collisions (the paper's scenes have none).
    obstacles = any(s is not None and s.get("collision_obstacle_rate") for _, s in rows)
    head = list(key_names) + list(_TABLE_HEAD_OBSTACLES if obstacles else _TABLE_HEAD)
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for keys, summary in rows:
        lines.append("| " + " | ".join(list(keys) + _metric_cells(summary, obstacles=obstacles)) + " |")
    return "\n".join(lines)


def _json_safe(value):
    """NaN/inf (e.g. the extra distance when no UAV succeeded) as null: strict JSON for any reader."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    return value


def write_json(path: Path, data: dict) -> None:
    """Write atomically: an interrupted run never leaves half a file (``paper`` resumes from them)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(_json_safe(data), indent=1, allow_nan=False))
    os.replace(tmp, path)
