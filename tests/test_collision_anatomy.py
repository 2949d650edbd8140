"""sitl.collision_anatomy: the frustum test and the classification of real collisions."""

import json
import math

import numpy as np
import pytest

from sitl.eval.collision_anatomy import analyse, bearing_elevation_deg, main, moving_in_view
from sitl.eval.visibility import in_view
from sitl.sim.config import ScenarioConfig
from sitl.eval.evaluate import EvalSettings

HALF_PI = math.pi / 2


def test_in_view_is_the_level_camera_frustum_of_the_heading():
    fov, rng = math.radians(90), 20.0
    east = np.array([0.0, 5.0, 0.0])  # 5 m east of a UAV at the origin
    assert in_view(np.zeros(3), np.array(HALF_PI), east, fov, fov, rng)  # facing east: straight ahead
    assert not in_view(np.zeros(3), np.array(0.0), east, fov, fov, rng)  # facing north: 90 deg to the right
    assert not in_view(np.zeros(3), np.array(-HALF_PI), east, fov, fov, rng)  # facing west: behind
    assert in_view(np.zeros(3), np.array(math.radians(50)), east, fov, fov, rng)  # 40 deg to the left
    assert not in_view(np.zeros(3), np.array(HALF_PI), np.array([0.0, 5.0, -5.5]), fov, fov, rng)  # too high
    assert in_view(np.zeros(3), np.array(HALF_PI), np.array([0.0, 5.0, 4.5]), fov, fov, rng)  # below, inside
    assert not in_view(np.zeros(3), np.array(HALF_PI), np.array([0.0, 25.0, 0.0]), fov, fov, rng)  # beyond range


def test_bearing_and_elevation_in_the_heading_frame():
    assert bearing_elevation_deg(np.array([1.0, 0.0, -1.0]), 0.0) == pytest.approx((0.0, 45.0))  # ahead, 1 m up
    assert bearing_elevation_deg(np.array([1.0, 0.0, 0.0]), HALF_PI) == pytest.approx((-90.0, 0.0))  # facing east: left
    assert bearing_elevation_deg(np.array([0.0, 0.0, 2.0]), 0.0)[1] == pytest.approx(-90.0)  # straight below


def test_head_on_collisions_are_seen_by_both(tmp_path, capsys):
    """Two UAVs flying straight at each other: every collision is one each saw coming, mid-way."""
    out = tmp_path / "anatomy.json"
    assert main(["--policy", "straight", "--scenario", "circle", "--n", "2", "--episodes", "10",
                 "--json", str(out)]) == 0
    result = json.loads(out.read_text())
    summary = result["summary"]
    assert result["collisions"] >= 10  # at least half of the 10 pairs meet (jitter can make some miss)
    assert result["collisions"] == len(result["events"]) and result["collisions"] % 2 == 0
    # Every collision the env recorded is classified, and nothing else.
    assert math.isclose(result["collisions"] / result["uav_episodes"], result["collision_uav_rate"])
    assert summary["collider_saw_partner"] == result["collisions"] and summary["neither_saw"] == 0
    assert all(4.0 < e["time_s"] < 8.0 for e in result["events"])  # 24 m closing at up to 4 m/s
    assert summary["time_5_inf_s"] + summary["time_2_5_s"] == result["collisions"]
    # Both fly straight at full speed (2 m/s) into each other.
    assert 1.8 < summary["median_speed_when_saw_m_s"] <= 2.05 and 3.5 < summary["median_closing_speed_m_s"] <= 4.1
    assert summary["collider_moved_out_of_view"] == 0  # level flight along the heading
    # 1 s before, the partner was straight ahead at the same altitude (jitter: a few degrees off).
    assert all(abs(e["partner_bearing_deg_lookback"]) < 10 and abs(e["partner_elevation_deg_lookback"]) < 10
               and not e["beyond_vertical_view"] for e in result["events"])
    assert summary["neither_saw_partner_above_or_below"] == 0
    # In view from 20 m (the paper camera's range), 1-2 s after the start: 4.5-5 s (the window looked back)
    # before the collision; flying straight, neither slows down.
    assert all(4.5 <= e["warning_s"] <= 5.0 for e in result["events"])
    assert summary["saw_with_warning_at_least_2_s"] == result["collisions"]
    assert abs(summary["median_speed_change_when_saw_m_s"]) < 0.1
    assert result["blind_flight"]["moving_steps"] > 0 and result["blind_flight"]["blind_share_of_distance"] == 0.0
    assert "| all UAV-UAV collisions |" in capsys.readouterr().out


def test_the_anatomy_of_a_governed_controller(tmp_path):
    """--governor: the same head-on pairs, with the speed governor after the straight line, are classified
    as that controller's (they stop and pass: fewer collisions than straight's one per pair)."""
    out = tmp_path / "anatomy.json"
    assert main(["--policy", "straight", "--governor", "--scenario", "circle", "--n", "2", "--episodes", "10",
                 "--json", str(out)]) == 0
    result = json.loads(out.read_text())
    assert result["method"] == "straight+governor"
    assert result["collisions"] < 10 and math.isclose(result["collisions"] / result["uav_episodes"],
                                                      result["collision_uav_rate"])


def test_moving_in_view_is_the_velocity_direction_in_the_frustum():
    """Climbing at 0.5 m/s is blind to a D435 (58 deg vertical FOV) unless the UAV also flies forward fast enough."""
    hfov, vfov = math.radians(87), math.radians(58)
    north = 0.0
    assert moving_in_view(np.array([2.0, 0.0, 0.0]), north, hfov, vfov)  # forward
    assert moving_in_view(np.array([2.0, 0.0, -0.5]), north, hfov, vfov)  # 14 deg up
    assert not moving_in_view(np.array([0.3, 0.0, -0.5]), north, hfov, vfov)  # 59 deg up
    assert not moving_in_view(np.array([0.0, 0.0, 0.5]), north, hfov, vfov)  # straight down
    assert not moving_in_view(np.array([0.0, 1.0, 0.0]), north, hfov, vfov)  # sideways (east, facing north)
    assert moving_in_view(np.array([0.0, 1.0, 0.0]), HALF_PI, hfov, vfov)  # east, facing east
    assert moving_in_view(np.zeros(3), north, hfov, vfov)  # hovering


def test_bad_arguments_are_refused(capsys):
    for argv in (["--episodes", "0"], ["--n", "1"], ["--density", "huge"], ["--protocol", "flown", "--n=4"],
                 ["--protocol", "flown", "--cell", "moon"]):
        try:
            main(argv)
        except SystemExit as exit_:
            assert exit_.code == 2
        else:
            raise AssertionError(f"{argv} accepted")
    err = capsys.readouterr().err
    assert "--episodes must be at least 1" in err and "--n: a paper-protocol scene setting" in err


def test_worlds_that_restart_give_the_same_anatomy_as_all_at_once():
    """With fewer parallel worlds than episodes, worlds restart mid-run: the lookback must not mix episodes."""
    def events(batch_worlds: int) -> list[dict]:
        settings = EvalSettings(scenario=ScenarioConfig(name="random"), num_uavs=6, episodes=12,
                                batch_worlds=batch_worlds, record_paths=False)
        return analyse("straight", settings)["events"]

    all_at_once = events(12)
    assert len(all_at_once) >= 4  # straight flight in the random scene collides now and then
    assert events(5) == all_at_once


def test_a_flown_cell_is_flown_with_the_cameras_real_vertical_field_of_view(tmp_path):
    """--protocol flown flies the protocol's cell; the D435's 58 deg vertical FOV is the frustum, not 87 deg."""
    from companion.spec import REALSENSE_D435
    from sitl.eval.collision_anatomy import CollisionObserver
    from sitl.sim.config import SimConfig

    observer = CollisionObserver(SimConfig(num_uavs=2, num_worlds=1, camera=REALSENSE_D435))
    assert math.degrees(observer.vfov) == pytest.approx(58.0)
    out = tmp_path / "flown.json"
    assert main(["--policy", "straight", "--protocol", "flown", "--cell", "random-medium", "--episodes", "6",
                 "--json", str(out)]) == 0
    result = json.loads(out.read_text())
    assert "at 1.5-15 m" in result["scenario"] and result["uav_episodes"] == 48
    assert math.isclose(result["collisions"] / result["uav_episodes"], result["collision_uav_rate"])


def test_timeouts_are_located_and_classified():
    """Two UAVs flying straight across a 12 m circle, stopped after 3 s: both time out mid-way, still flying."""
    settings = EvalSettings(scenario=ScenarioConfig(name="circle", circle_radius_m=12.0), num_uavs=2, episodes=4,
                            max_episode_steps=30, record_paths=False)
    result = analyse("straight", settings)
    t = result["timeouts"]
    assert result["collisions"] == 0 and t["timeouts"] == 8 == len(result["timeout_events"])
    assert math.isclose(t["rate"], result["timeout_rate"])  # every timeout the env recorded, and nothing else
    assert t["still_flying"]["count"] == 8 and t["stalled_near_goal"]["count"] == t["stalled_elsewhere"]["count"] == 0
    for e in result["timeout_events"]:
        # 3 s at up to 2 m/s from 24 m out: 4-6.5 m flown, all of it towards the goal; no obstacles here
        assert 4.0 < e["moved_last_window_m"] <= 6.5 and math.isclose(e["progress_last_window_m"], e["moved_last_window_m"], abs_tol=0.05)
        assert 17.5 < e["distance_to_goal_m"] < 20.5 and e["nearest_obstacle_m"] is None


@pytest.mark.parametrize("moved, to_goal, kind", [(0.1, 1.0, "stalled_near_goal"), (0.1, 8.0, "stalled_elsewhere"),
                                                  (0.6, 1.0, "still_flying"), (3.0, 15.0, "still_flying")])
def test_timeout_kinds(moved, to_goal, kind):
    from sitl.eval.collision_anatomy import summarize_timeouts, timeout_kind

    event = {"moved_last_window_m": moved, "distance_to_goal_m": to_goal, "nearest_obstacle_m": None,
             "altitude_m": 5.0, "progress_last_window_m": 0.0}
    assert timeout_kind(event) == kind
    summary = summarize_timeouts([event], 10)
    assert summary[kind]["count"] == 1 and math.isclose(summary[kind]["rate"], 0.1)
    assert math.isnan(summary[kind]["median_nearest_obstacle_m"])


def test_obstacle_clearance_is_for_the_obstacle_cell_only(capsys):
    for argv in (["--obstacle-clearance", "3"], ["--protocol", "flown", "--cell", "random-medium", "--obstacle-clearance", "3"],
                 ["--protocol", "flown", "--cell", "obstacles", "--obstacle-clearance", "0.1"]):
        with pytest.raises(SystemExit) as exit_info:
            main(argv)
        assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert "needs --protocol flown --cell obstacles" in err and "obstacle_clearance_m must be in [0.5, 100]" in err
    assert main(["--policy", "straight", "--protocol", "flown", "--cell", "obstacles", "--episodes", "1",
                 "--obstacle-clearance", "3"]) == 0


def test_blind_flight_is_measured_and_mostly_vertical_for_a_straight_line_to_goals_above_and_below():
    """Flying straight at goals at other altitudes climbs and descends too steeply for the camera at times."""
    result = analyse("straight", EvalSettings(scenario=ScenarioConfig(name="random"), num_uavs=8, episodes=10,
                                              record_paths=False))
    blind = result["blind_flight"]
    assert 0.0 < blind["blind_share_of_moving_steps"] < 0.5 and 0.0 < blind["blind_share_of_distance"] < 0.5
    assert blind["vertical_share_of_blind"] > 0.5
