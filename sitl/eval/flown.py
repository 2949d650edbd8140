"""The ``flown`` evaluation protocol (``python -m sitl.swarm_test flown``): the task as drone builders fly it.

Where the ``paper`` protocol keeps the paper's geometry (random boxes on a 6 m floor, a 12 m
circle at 10 m), this one draws what a low-flying swarm meets (issue 15): starts and goals
1.5-15 m above the ground, circles of 8-20 m radius at 2-15 m, starts off by up to 0.5 m per
axis, static obstacles, the camera's noise, and a JSBSim cell. Cells (N = 8 each):

* ``random-small`` / ``random-medium`` / ``random-large``: the paper's densities at 1.5-15 m;
* ``circle-n8``: antipodal circle, radius and altitude drawn per episode, each UAV facing its goal;
* ``circle-n8-common``: the same circle with the whole swarm facing one heading drawn per episode (as
  a swarm set out on a field faces, and as the PX4 SIH and ArduCopter SITL vehicles of
  ``sitl.real_autopilots`` start: north);
* ``circle-n8-scatter``: ``circle-n8`` with each start moved horizontally within
  :data:`FLOWN_CIRCLE_SCATTER_M` of its point on the ring, the goals still at the nominal antipodes (a
  swarm whose starts are off by GPS errors or a takeoff's drift; how PX4 SIH's circles started before the
  companion kept station);
* ``circle-n8-px4-sih``: the simulator's twin of ``sitl.real_autopilots circle --autopilot px4`` (12 m radius,
  8 m up, starts scattered within 1 m as PX4 SIH's do) with each UAV's velocity response drawn apart from
  the spread fitted to PX4 SIH's vehicles (``--response px4-sih``; docs/real_autopilots.md "Fitting each
  vehicle's response"): where policies that fly every other circle meet on PX4 SIH;
* ``obstacles``: poles, trees and boxes among the UAVs (:data:`OBSTACLE_SCENE_DENSITY`);
* ``random-medium-delay``: ``random-medium`` with each UAV acting on its commands late, by a pure delay drawn
  per UAV from :data:`FLOWN_COMMAND_DELAY_S` (the kinematic ``command_delay_s``): the tilt a real airframe needs
  before it accelerates and the link's latency, what costs the JSBSim cell its points (docs/results.md "Why
  JSBSim costs points"), at a kinematic cell's price;
* ``random-medium-jsbsim``: ``random-medium`` on the JSBSim rigid-body backend.

Every cell flies the controller and, on the same episodes, the straight-to-goal reference; it
reports the paper's metrics plus success split by goal altitude (below 3 m, 3-6 m, above 6 m).
Episodes come from the held-out test seeds (``EVAL_SEED_OFFSET + seed``), 500 per cell by
default. Results: one JSON per cell under ``OUT/cells`` (reused when settings and policy file
match, so a run resumes), ``flown.md``, ``flown.json`` and ``flown_success.png``.
"""

from __future__ import annotations

import dataclasses
import json
import sys
from dataclasses import dataclass, replace
from pathlib import Path

from companion.face_goal import FaceGoalSpec
from companion.governor import GovernorSpec
from sitl.eval.evaluate import EvalSettings, evaluate_method
from sitl.eval.methods import ORCA_BASELINES, Method, file_digest, resolve_method
from sitl.eval.report import markdown_table, write_json
from sitl.sim.camera import StereoNoise
from sitl.sim.config import (DENSITIES, FLOWN_ALTITUDE_RANGE_M, FLOWN_CIRCLE_SCATTER_M, OBSTACLE_SCENE_DENSITY,
                             scenario_for)
from sitl.sim.dynamics import KinematicRandomization, describe_response, layer_response, nominal_ranges, parse_response
from sitl.sim.metrics import GOAL_ALTITUDE_BINS_M, success_by_goal_altitude

#: Episodes per cell: random-scene success differs between controllers by a few points, which
#: needs ~500 episodes (4000 UAV-episodes) to resolve.
DEFAULT_EPISODES = 500
PROTOCOL_N = 8
#: The ``circle-n8-px4-sih`` cell: ``sitl.real_autopilots circle``'s default layout (radius, altitude m) and PX4
#: SIH's start scatter (0.2-1.0 m off the ring in session 54's circles), with the ``px4-sih`` response.
PX4_SIH_CIRCLE = dict(circle_radius_m=12.0, circle_alt_m=8.0, circle_scatter_m=1.0)
#: The ``random-medium-delay`` cell's command delay range, s: a JSBSim F450 behaves like ~0.15 s from rest, PX4
#: SIH's vehicles fit 0-0.25 s (``python -m sitl.real_autopilots fit``; docs/real_autopilots.md).
FLOWN_COMMAND_DELAY_S = (0.0, 0.2)


@dataclass
class FlownCell:
    """One scene of the protocol: what every controller flies in it."""

    name: str
    settings: EvalSettings


def flown_cells(episodes: int = DEFAULT_EPISODES, seed: int = 0, camera_noise: bool = True,
                noise_model: StereoNoise | None = None, max_steps: int = 400, batch: int = 100,
                jsbsim: bool = True, jsbsim_episodes: int | None = None, camera: str | None = None,
                response: KinematicRandomization | None = None) -> list[FlownCell]:
    """The protocol's cells (see the module doc); ``noise_model`` is the camera's error model (default
    :class:`StereoNoise`), ``jsbsim_episodes`` the JSBSim cell's episodes (default ``episodes``),
    ``camera`` the camera preset the UAVs carry (default: the policy's own, the paper camera for references),
    ``response``: every kinematic cell also flies these ranges, over its own (``swarm_test flown --response``)."""
    common = dict(num_uavs=PROTOCOL_N, episodes=episodes, seed=seed, camera_noise=camera_noise, camera=camera,
                  noise_model=noise_model or StereoNoise(), max_episode_steps=max_steps, batch_worlds=batch,
                  record_paths=False)
    cells = [FlownCell(f"random-{name}", EvalSettings(scenario=scenario_for("flown", "random", density=density),
                                                      **common))
             for name, density in DENSITIES.items()]
    cells.append(FlownCell("circle-n8", EvalSettings(scenario=scenario_for("flown", "circle"), **common)))
    cells.append(FlownCell("circle-n8-common", EvalSettings(
        scenario=scenario_for("flown", "circle", circle_heading="common"), **common)))
    cells.append(FlownCell("circle-n8-scatter", EvalSettings(
        scenario=scenario_for("flown", "circle", circle_scatter_m=FLOWN_CIRCLE_SCATTER_M), **common)))
    cells.append(FlownCell("circle-n8-px4-sih", EvalSettings(
        scenario=scenario_for("paper", "circle", **PX4_SIH_CIRCLE),
        response=parse_response("px4-sih", nominal_ranges()), **common)))
    cells.append(FlownCell("obstacles", EvalSettings(
        scenario=scenario_for("flown", "obstacles", density=OBSTACLE_SCENE_DENSITY), **common)))
    cells.append(FlownCell("random-medium-delay", EvalSettings(
        scenario=scenario_for("flown", "random", density=DENSITIES["medium"]),
        response=replace(nominal_ranges(), command_delay_s=FLOWN_COMMAND_DELAY_S), **common)))
    if jsbsim:
        cells.append(FlownCell("random-medium-jsbsim", EvalSettings(
            scenario=scenario_for("flown", "random", density=DENSITIES["medium"]), dynamics="jsbsim",
            **(common | {"episodes": jsbsim_episodes or episodes}))))
    if response is not None:
        cells = [FlownCell(c.name, replace(c.settings, response=layer_response(c.settings.response, response)))
                 if c.settings.dynamics == "kinematic" else c for c in cells]
    return cells


#: The cells' names, in the order they are flown (``--cells`` picks among them).
FLOWN_CELL_NAMES: tuple[str, ...] = tuple(cell.name for cell in flown_cells())


def _cell_key(cell: FlownCell, method: Method) -> dict:
    """What a stored result must match to be reused: the settings and the exact controller."""
    settings = json.loads(json.dumps(dataclasses.asdict(replace(cell.settings, record_paths=False))))
    if settings.get("response") is None:  # cells with the nominal response keep the keys they were stored with
        settings.pop("response", None)
    elif settings["response"].get("command_delay_s") == [0.0, 0.0]:  # likewise cells stored before the delay existed
        del settings["response"]["command_delay_s"]
    key = {"protocol": "flown", "cell": cell.name, "method": method.label, "settings": settings,
           "policy_sha256": file_digest(method.path) if method.path else None}
    if method.governor is not None:  # only then: the keys of stored ungoverned cells stay as they were
        key["governor"] = method.governor.to_dict()
    if method.face_goal is not None:  # likewise
        key["face_goal"] = dataclasses.asdict(method.face_goal)
    if method.kind == "baseline" and method.label in ORCA_BASELINES:  # its settings, obstacle-seeing included
        key["orca"] = method.info()["orca"]  # (since 2026-11-27); info() hashes no file for a baseline
    return key


def run_flown_cell(cell: FlownCell, method: Method, out: Path, progress: bool = True) -> tuple[dict, str]:
    """One controller in one cell (or its stored result): ``({"summary", "by_goal_altitude"}, status)``."""
    path = out / "cells" / f"{cell.name}-{method.label}.json"
    key = _cell_key(cell, method)
    if path.is_file():
        try:
            stored = json.loads(path.read_text())
            if stored.get("key") == key:
                return {"summary": stored["summary"], "by_goal_altitude": stored["by_goal_altitude"]}, "stored"
        except (json.JSONDecodeError, KeyError):
            pass  # unreadable: compute it again
    result = evaluate_method(method, cell.settings, progress=progress, desc=f"{cell.name} {method.label}", leave=False)
    data = {"summary": result.summary, "by_goal_altitude": success_by_goal_altitude(result.records)}
    write_json(path, {"key": key, "settings": {**dataclasses.asdict(cell.settings), "eval_seed": cell.settings.env_seed},
                      "describe": cell.settings.describe(), "wall_s": round(result.wall_s, 3), **data})
    stored = json.loads(path.read_text())  # as written: NaN already null, like a reused cell
    return {"summary": stored["summary"], "by_goal_altitude": stored["by_goal_altitude"]}, "computed"


def _altitude_cells(split: dict) -> list[str]:
    out = []
    for label, *_ in GOAL_ALTITUDE_BINS_M:
        b = split[label]
        rate = b["success_rate"]
        half = b.get("success_ci95_half_width")
        ci = f" ± {half:.3f}" if half is not None and half == half else ""
        out.append("-" if rate is None or rate != rate else f"{rate:.3f}{ci} ({b['uav_episodes']})")
    return out


def run_flown(out: Path, cells: list[FlownCell], methods: list[Method], progress: bool = True,
              response: KinematicRandomization | None = None) -> dict:
    """Evaluate every controller in every cell (reusing stored results); write ``flown.md``, ``flown.json``
    and ``flown_success.png``. Returns ``{cell: {method: result}}`` and the status of each. ``response``: the
    ranges the kinematic cells were given over their own (:func:`flown_cells`), named in ``flown.md``."""
    from tqdm import tqdm

    from sitl.eval.plots import plot_protocol

    out.mkdir(parents=True, exist_ok=True)
    results: dict[str, dict[str, dict]] = {}
    status: dict[str, str] = {}
    with tqdm(total=len(cells) * len(methods), unit="cell", desc="flown", disable=not progress, file=sys.stderr) as bar:
        for cell in cells:
            for method in methods:
                bar.set_postfix_str(f"{cell.name} {method.label}")
                res, status[f"{cell.name}-{method.label}"] = run_flown_cell(cell, method, out, progress)
                results.setdefault(cell.name, {})[method.label] = {"summary": res["summary"],
                                                                   "by_goal_altitude": res["by_goal_altitude"]}
                bar.update(1)
    first = cells[0].settings if cells else None
    lo, hi = FLOWN_ALTITUDE_RANGE_M
    lines = ["# The `flown` protocol: low altitude, obstacles, camera noise, start jitter, JSBSim", "",
             "Generated by `python -m sitl.swarm_test flown`. Starts and goals "
             f"{lo:g}-{hi:g} m above the ground (random box floor drawn per episode), circles of 8-20 m radius "
             "at 2-15 m (circle-n8-px4-sih: PX4 SIH's 12 m at 8 m, starts within 1 m), starts off by up to 0.5 m "
             "per axis, N = 8. Success with the half-width of its ~95 % "
             "confidence interval (clustered by episode); collision = 1 - success, split into UAV-UAV, ground, "
             "obstacle and timeout. `straight` flies at its goal without avoiding anything, on the same "
             "episodes (with camera noise the episodes beyond the first batch differ between controllers).", ""]
    if first is not None:
        lines += [f"Settings: {first.episodes} episodes per cell, evaluation seed {first.env_seed} (held out from "
                  f"training and validation), camera noise "
                  f"{'on: ' + str(dataclasses.asdict(first.noise_model)) if first.camera_noise else 'off'}, "
                  f"time limit {first.max_episode_steps} steps, dynamics kinematic (nominal) except the jsbsim "
                  "cell, circle-n8-px4-sih (each UAV's response drawn from the px4-sih ranges) and "
                  "random-medium-delay (a command delay drawn per UAV in "
                  f"{FLOWN_COMMAND_DELAY_S[0]:g}-{FLOWN_COMMAND_DELAY_S[1]:g} s; its episodes are not "
                  "random-medium's: the draw moves the episode generator).",
                  ""]
        if response is not None:
            lines += [f"Every kinematic cell also flies the response `{describe_response(response, nominal_ranges())}` "
                      "(`--response`, over its own; each UAV's drawn per episode), so no kinematic cell is "
                      "nominal here.", ""]
    for m in methods:
        if m.path:
            lines += [f"Policy file: `{m.path}` (sha256 {file_digest(m.path)[:12]}...)", ""]
    lines += ["## Metrics", "",
              markdown_table(["cell", "method"], [([c.name, m.label], results[c.name][m.label]["summary"])
                                                   for c in cells for m in methods]), "",
              "## Success by goal altitude (± 95 % CI, UAV-episodes in brackets)", "",
              "| cell | method | " + " | ".join(label for label, *_ in GOAL_ALTITUDE_BINS_M) + " |",
              "|---|---|" + "---|" * len(GOAL_ALTITUDE_BINS_M)]
    for c in cells:
        for m in methods:
            lines.append(f"| {c.name} | {m.label} | " + " | ".join(_altitude_cells(results[c.name][m.label]["by_goal_altitude"]))
                         + " |")
    lines += ["", "![success per cell and goal altitude](flown_success.png)", ""]
    plot_protocol(results, out / "flown_success.png", "flown protocol: success per cell (bars) and by goal altitude")
    (out / "flown.md").write_text("\n".join(lines))
    write_json(out / "flown.json", {"protocol": "flown", "cells": {c.name: {"describe": c.settings.describe(),
                                                                              "eval_seed": c.settings.env_seed,
                                                                              "results": results[c.name]}
                                                                     for c in cells},
                                    "methods": [m.info() for m in methods], "status": status})
    return {"results": results, "status": status}


def protocol_methods(policy: str, reference: bool = True, governor: GovernorSpec | None = None,
                     face_goal: FaceGoalSpec | None = None) -> list[Method]:
    """The controller named ``policy`` (turning to face its goal first with ``face_goal``, with the speed
    ``governor`` after it, if given) and, unless ``reference`` is off or the controller is the plain ``straight``
    line itself, ``straight`` (always plain)."""
    method = resolve_method(policy)
    if face_goal is not None:
        method = method.with_face_goal(face_goal)
    if governor is not None:
        method = method.with_governor(governor)
    methods = [method]
    if reference and method.label != "straight":
        methods.append(resolve_method("straight"))
    return methods
