"""``swarm_test --mavlink``: the evaluation's episodes flown by the whole product over MAVLink (:mod:`sitl.realtime.mavlink_swarm`)."""

from __future__ import annotations

import dataclasses
from dataclasses import replace
from pathlib import Path

import numpy as np

from companion.governor import GOVERNOR_PRESETS, governor_name
from companion.spec import TaskSpec
from sitl.eval.evaluate import EvalResult, EvalSettings
from sitl.eval.methods import EvaluationError, Method
from sitl.sim.metrics import summarize

def evaluate_beside_in_process(method: Method, settings: EvalSettings, in_process: EvalResult, out: Path,
                               start: str, base_port: int, depth_port: int, gcs_port: int,
                               progress: bool = True) -> tuple[EvalResult, dict]:
    """Fly the evaluation's episodes with the real processes (:mod:`sitl.realtime.mavlink_swarm`).

    Returns the MAVLink result and what the JSON says about it: settings, costs, each
    episode's processes, and the agreement with ``in_process`` (same policy, same episodes).
    """
    from sitl.realtime.mavlink_swarm import MavlinkSettings, evaluate_over_mavlink
    from sitl.sim.scenarios import sample_scenario

    # The in-process evaluation draws its episodes in this order from this seed, so both
    # runs meet the same starts and goals.
    rng = np.random.default_rng(settings.env_seed)
    samples = [sample_scenario(settings.num_uavs, settings.scenario, rng) for _ in range(settings.episodes)]
    sim_config = in_process.sim_config
    camera = sim_config.camera
    # A policy trained with the governor carries it: the companions read its settings from the file.
    from_file = method.trained_with_governor
    governor = governor_name(method.governor) if method.governor is not None and not from_file else None
    if governor == "custom":
        raise EvaluationError("over MAVLink the companions fly the governor's named settings only "
                              f"({', '.join(GOVERNOR_PRESETS)})")
    mav_settings = MavlinkSettings(
        policy_path=str(method.path), start=start, base_port=base_port, depth_port=depth_port,
        gcs_port=gcs_port, dynamics=settings.dynamics, camera_size=(camera.width, camera.height),
        hfov_deg=camera.hfov_deg, max_range_m=camera.max_range_m,
        time_limit_s=settings.max_episode_steps * sim_config.control_period_s,
        task=TaskSpec(collision_radius_m=sim_config.collision_radius_m,  # scored as the in-process run beside it
                      arrival_radius_m=sim_config.reward.arrival_radius_m, max_episode_steps=settings.max_episode_steps),
        governor=governor, face_goal_s=None if method.face_goal is None else method.face_goal.hold_s)
    evaluation = evaluate_over_mavlink(samples, mav_settings, out, progress=progress)
    label = f"{method.label} (MAVLink)"
    result = EvalResult(replace(method, label=label), settings, sim_config, evaluation.records,
                        summarize(evaluation.records), evaluation.wall_s)
    ours, theirs = result.summary, in_process.summary
    info = {
        "agreement": {"success_mavlink": ours["success_rate"], "success_in_process": theirs["success_rate"],
                      "success_difference_points": 100.0 * (ours["success_rate"] - theirs["success_rate"]),
                      "spl_mavlink": ours["spl"], "spl_in_process": theirs["spl"]},
        "settings": dataclasses.asdict(mav_settings),
        "costs": evaluation.costs(),
        "episodes": [{"episode": k, "wall_s": round(e.wall_s, 2), "ready_s": round(e.ready_s, 2),
                      "companions": e.companions, "world": e.world} for k, e in enumerate(evaluation.episodes)],
    }
    return result, info
