"""Training recipes (sitl.learn.recipe): stages chained by their selected snapshots, resumable, one export."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
import pytest

from companion.policy import load_policy
from companion.spec import STATE_DIM
from sitl.learn.agent import AgentConfig
from sitl.learn.config import PRESETS, RecipeStage, resolve_configs
from sitl.learn.recipe import RECIPE_FILE, Recipe, scaled_stages, stage_configs

REPO = Path(__file__).resolve().parents[1]

#: a recipe small enough for a test: two stages of a few updates on tiny worlds and networks
TINY = {"num_worlds": 2, "num_uavs": 3, "image_size": 16, "init_steps": 48, "batch_size": 16,
        "replay_capacity": 2_000, "max_episode_steps": 30, "eval_episodes": 2, "final_eval_episodes": 3,
        "checkpoint_every_s": 1e6}
STAGES = (
    RecipeStage("first", "random scene", {"scenario": "random", "total_updates": 12, "eval_every_updates": 6}),
    RecipeStage("second", "mixed scenes at a lower learning rate",
                {"scenario": "mixed", "total_updates": 8, "eval_every_updates": 4}, {"actor_lr": 3e-4}),
)


class Interrupt(Exception):
    """Stands in for the end of a session in the middle of a recipe."""


def stop_at_stage_two(messages: list[str]):
    """A recipe log that records the messages and ends the "session" when stage 2 starts."""
    def log(message: str) -> None:
        messages.append(message)
        if message.startswith("=== stage 2/2"):
            raise Interrupt
    return log


def tiny_configs(run_dir: Path):
    return resolve_configs({**TINY, "run_dir": str(run_dir)}, {"hidden_dim": 32, "latent_dim": 8, "num_filters": 8})


def test_a_recipe_chains_its_stages_resumes_after_an_interruption_and_exports_once(tmp_path):
    cfg, agent_cfg = tiny_configs(tmp_path)
    messages: list[str] = []
    with pytest.raises(Interrupt):
        Recipe(cfg, agent_cfg, STAGES, tmp_path, rescore_top=2, rescore_episodes=2,
               log=stop_at_stage_two(messages)).run()
    state = json.loads((tmp_path / RECIPE_FILE).read_text())
    assert [s["name"] for s in state["stages"]] == ["first"] and not (tmp_path / "policy.pt").exists()
    first = state["stages"][0]
    assert first["updates"] == 12 and Path(first["snapshot"]).is_file()

    messages.clear()
    path = Recipe(cfg, agent_cfg, STAGES, tmp_path, rescore_top=2, rescore_episodes=2, log=messages.append).run()
    assert not any(m.startswith("=== stage 1/") for m in messages), "a finished stage must not run again"
    state = json.loads((tmp_path / RECIPE_FILE).read_text())
    assert state["done"] and [s["name"] for s in state["stages"]] == ["first", "second"]
    second = json.loads((tmp_path / "stage2-second" / "config.json").read_text())
    # the second stage starts from the first stage's selected snapshot, with its own overrides
    assert second["train"]["init_from"] == first["snapshot"] and second["train"]["scenario"] == "mixed"
    assert second["agent"]["actor_lr"] == 3e-4 and second["train"]["final_eval_episodes"] == 0
    rows = json.loads((tmp_path / "stage2-second" / "snapshots" / "validation.json").read_text())
    assert sum("rescored" in row for row in rows) == 2  # the two best were flown again

    provenance = load_policy(path).metadata["provenance"]
    recipe = provenance["recipe"]
    assert [s["name"] for s in recipe["stages"]] == ["first", "second"]
    assert recipe["wall_time_s"] >= sum(s["wall_s"] for s in recipe["stages"]) > 0
    assert provenance["selected_snapshot"]["rescored"]["episodes"] == 2
    assert provenance["evaluation"]["episodes"] == 3  # the test-seed evaluation ran once, at the end
    assert (tmp_path / "learning_curve.png").stat().st_size > 0


def test_explicit_flags_win_over_stage_overrides_and_scale_shrinks_a_recipe(tmp_path):
    cfg, agent_cfg = tiny_configs(tmp_path)
    train, agent = stage_configs(cfg, agent_cfg, STAGES[1], tmp_path, "", explicit=frozenset({"actor_lr"}))
    assert train.scenario == "mixed" and agent.actor_lr == AgentConfig().actor_lr
    small = scaled_stages(PRESETS["bundle-paper"]["stages"], 0.01)
    assert [s.train["total_updates"] for s in small] == [75, 50, 50, 100]
    assert all(s.train["eval_episodes"] >= 1 for s in small if "eval_episodes" in s.train)


def test_stage_scale_lengthens_single_stages_not_their_validations():
    stages = PRESETS["flown-fast"]["stages"]
    longer = scaled_stages(stages, 1.0, (1.5, 1.5, 1.0, 1.0))
    assert [s.train["total_updates"] for s in longer] == [12_000, 9_000, 6_000, 6_000]
    assert [s.train["eval_every_updates"] for s in longer] == [3_000, 3_000, 1_500, 1_500]
    assert [s.train.get("eval_episodes") for s in longer] == [s.train.get("eval_episodes") for s in stages]
    both = scaled_stages(stages, 0.1, (2.0, 1.0, 1.0, 1.0))  # on top of --recipe-scale
    assert [s.train["total_updates"] for s in both] == [1_600, 600, 600, 600]
    # A quick trial validates in proportion, also in stages that take the run's episode count.
    trial = scaled_stages(stages, 0.1, default_eval_episodes=40)
    assert [s.train["eval_episodes"] for s in trial] == [4, 4, 5, 5]
    assert "eval_episodes" not in scaled_stages(stages, 1.0, (1.5, 1.5, 1.0, 1.0), default_eval_episodes=40)[0].train
    with pytest.raises(ValueError, match="2 stage scale"):
        scaled_stages(stages, 1.0, (1.5, 1.5))


def test_stage_scales_are_kept_for_a_resume_and_in_the_provenance(tmp_path):
    cfg, agent_cfg = tiny_configs(tmp_path)
    path = Recipe(cfg, agent_cfg, STAGES, tmp_path, rescore_top=1, rescore_episodes=2, stage_scales=(0.5, 1.0)).run()
    state = json.loads((tmp_path / RECIPE_FILE).read_text())
    assert state["stage_scales"] == [0.5, 1.0] and [s["updates"] for s in state["stages"]] == [6, 8]
    assert load_policy(path).metadata["provenance"]["recipe"]["stage_scales"] == [0.5, 1.0]


def test_a_resume_whose_stage_scales_no_longer_fit_the_recipe_is_a_one_line_error(tmp_path):
    """A run started with --stage-scale for four stages, resumed after the preset changed its stage count."""
    train_cfg, agent_cfg = resolve_configs({"preset": "flown-fast", "run_dir": str(tmp_path)}, {})
    (tmp_path / "config.json").write_text(json.dumps({"train": asdict(train_cfg), "agent": asdict(agent_cfg)}))
    (tmp_path / RECIPE_FILE).write_text(json.dumps({"stages": [], "wall_s": 0.0, "scale": 1.0,
                                                    "stage_scales": [1.5, 1.5]}))
    out = subprocess.run([sys.executable, "-m", "sitl.train", "--resume", str(tmp_path)], cwd=REPO,
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert out.stderr.strip().splitlines()[-1] == "error: 2 stage scale(s) for a recipe of 4 stages"


def test_train_help_lists_a_recipes_stages():
    out = subprocess.run([sys.executable, "-m", "sitl.train", "--preset", "bundle-paper", "--help"], cwd=REPO,
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0
    assert "recipe of 4 stages" in out.stdout and "stage 4 'mixed15'" in out.stdout
    out = subprocess.run([sys.executable, "-m", "sitl.train", "--preset", "flown-distill", "--help"], cwd=REPO,
                         capture_output=True, text=True, timeout=120)
    text = " ".join(out.stdout.split())
    assert "final choice: only snapshots with paper-circle-n14" in text
    assert "flown again on 500 validation episodes each of random-medium, obstacles" in text


def test_a_stage_is_validated_only_on_the_scenes_it_trains_on():
    """The flown recipe's first stage has no circles: scoring it on circles picked its 2,000-update snapshot of 8,000."""
    from sitl.learn.config import evaluation_scenarios

    def scenes(**train):
        return evaluation_scenarios(resolve_configs({"scenario": "mixed", **train}, {})[0])

    assert scenes(circle_fraction=0.0, obstacle_fraction=0.2) == ("random", "obstacles")
    assert scenes(circle_fraction=0.3, obstacle_fraction=0.2) == ("random", "circle", "obstacles")
    assert scenes(circle_fraction=0.5) == ("random", "circle")
    assert evaluation_scenarios(resolve_configs({"scenario": "circle"}, {})[0]) == ("circle",)


def test_a_finished_recipe_that_gained_a_stage_continues_with_it(tmp_path):
    """flown-fast gained a fourth stage after three seeds had finished three: they continue, not restart."""
    cfg, agent_cfg = tiny_configs(tmp_path)
    Recipe(cfg, agent_cfg, STAGES[:1], tmp_path, rescore_top=1, rescore_episodes=2).run()
    finished = json.loads((tmp_path / RECIPE_FILE).read_text())
    assert finished["done"] and finished["wall_s"] > finished["stages"][0]["wall_s"]  # rescoring and export

    messages: list[str] = []
    path = Recipe(cfg, agent_cfg, STAGES, tmp_path, rescore_top=2, rescore_episodes=2, log=messages.append,
                  evaluation_steps=45).run()
    assert not any(m.startswith("=== stage 1/") for m in messages) and any("continuing" in m for m in messages)
    state = json.loads((tmp_path / RECIPE_FILE).read_text())
    assert state["done"] and [s["name"] for s in state["stages"]] == ["first", "second"]
    second = json.loads((tmp_path / "stage2-second" / "config.json").read_text())
    assert second["train"]["init_from"] == finished["stages"][0]["snapshot"]
    provenance = load_policy(path).metadata["provenance"]
    # the first export's rescoring and evaluation are not counted in the continued recipe's time
    stage_time = sum(s["wall_s"] for s in state["stages"])
    # Each stage's wall_s and policy.json's wall_time_s are rounded to 0.1 s once (the stages here take < 1 s):
    # their sum may exceed the unrounded total by half a step each. recipe.json's total is rounded the same
    # way from a later instant, so it is never below policy.json's.
    rounding_s = 0.05 * (len(state["stages"]) + 1)
    assert stage_time - rounding_s <= provenance["recipe"]["wall_time_s"] <= state["wall_s"]
    assert state["wall_s"] - provenance["recipe"]["wall_time_s"] < 10.0  # recipe.json agrees with policy.json
    # rescoring and the final evaluation fly the recipe's evaluation time limit, not training's 30 steps
    assert provenance["selected_snapshot"]["rescored"]["max_episode_steps"] == 45
    assert provenance["evaluation"]["max_episode_steps"] == 45
    assert provenance["recipe"]["rescore"] == {"top": 2, "episodes": 2, "scenes": ["random-medium"],
                                               "max_episode_steps": 45}

    # Another final choice (here more rescoring episodes) on the finished run: no stage runs again,
    # the rescoring made under the old settings is redone and the policy exported again.
    messages.clear()
    Recipe(cfg, agent_cfg, STAGES, tmp_path, rescore_top=2, rescore_episodes=3, log=messages.append,
           evaluation_steps=45).run()
    assert not any(m.startswith("=== stage") for m in messages) and any("continuing" in m for m in messages)
    rows = json.loads((tmp_path / "stage2-second" / "snapshots" / "validation.json").read_text())
    assert sorted(r["rescored"]["episodes"] for r in rows if "rescored" in r) == [3, 3]
    assert load_policy(tmp_path / "policy.pt").metadata["provenance"]["selected_snapshot"]["rescored"]["episodes"] == 3


def _actions(path: Path) -> np.ndarray:
    """The policy's actions on a fixed batch of observations (depth and state drawn once)."""
    policy = load_policy(path)
    rng = np.random.default_rng(7)
    cam = policy.camera
    depth = rng.uniform(0.5, cam.max_range_m, size=(4, cam.frames, cam.height, cam.width)).astype(np.float32)
    state = rng.normal(size=(4, STATE_DIM)).astype(np.float32)
    return policy.act(depth, state)


def test_a_rerun_with_the_same_seed_gives_the_same_policy_another_seed_another(tmp_path):
    """Issue 17 "do I get the same thing": on one machine the recipe is a function of its seed.

    A run interrupted at a stage boundary and resumed must give what one run in one go gives;
    another seed must not (the test would pass vacuously if the seed did nothing).
    """
    def run(name: str, seed: int, interrupt: bool = False) -> Path:
        (tmp_path / name).mkdir()
        cfg, agent_cfg = tiny_configs(tmp_path / name)
        cfg = replace(cfg, seed=seed)
        if interrupt:
            with pytest.raises(Interrupt):
                Recipe(cfg, agent_cfg, STAGES, tmp_path / name, rescore_top=2, rescore_episodes=2,
                       log=stop_at_stage_two([])).run()
        return Recipe(cfg, agent_cfg, STAGES, tmp_path / name, rescore_top=2, rescore_episodes=2,
                      log=lambda m: None).run()

    def scores(name: str) -> list[float]:
        rows = json.loads((tmp_path / name / "stage2-second" / "snapshots" / "validation.json").read_text())
        return [r["score"] for r in rows]

    one_go, resumed, other = run("a", 0), run("b", 0, interrupt=True), run("c", 1)
    np.testing.assert_array_equal(_actions(one_go), _actions(resumed))
    assert scores("a") == scores("b")
    assert np.abs(_actions(one_go) - _actions(other)).max() > 1e-3


def test_a_stage_header_names_the_flags_that_replace_its_settings(tmp_path):
    """A flag given on the command line beats what a stage sets (``stage_configs``); the stage's header
    says so, since its description is the preset's words ("random scene" while the flag says circle)."""
    cfg, agent_cfg = tiny_configs(tmp_path)
    headers: list[str] = []

    def log(message: str) -> None:
        if message.startswith("=== stage"):
            headers.append(message)
            raise Interrupt  # the header is all this test needs: no training

    for explicit, run_cfg in ((frozenset(), cfg), (frozenset({"scenario"}), replace(cfg, scenario="circle"))):
        run_dir = tmp_path / f"run{len(headers)}"
        run_dir.mkdir()
        with pytest.raises(Interrupt):
            Recipe(run_cfg, agent_cfg, STAGES, run_dir, rescore_top=2, rescore_episodes=2, explicit=explicit,
                   log=log).run()
    assert "command line" not in headers[0]
    assert "random scene" in headers[1] and "from the command line instead: scenario circle" in headers[1]


def test_a_resume_elsewhere_rewrites_where_every_stage_computes(tmp_path):
    """A recipe started on a GPU machine (--device cuda) continued on a CPU (--resume --device cpu)."""
    from sitl.learn.cli import move_run

    cfg, agent_cfg = tiny_configs(tmp_path)
    for path in (tmp_path / "config.json", tmp_path / "stage1-first" / "config.json"):
        path.parent.mkdir(exist_ok=True)
        path.write_text(json.dumps({"train": {**asdict(cfg), "device": "cuda", "threads": 4}, "agent": asdict(agent_cfg)}))
    move_run(tmp_path, {"device": "cpu"})
    for path in (tmp_path / "config.json", tmp_path / "stage1-first" / "config.json"):
        train = json.loads(path.read_text())["train"]
        assert (train["device"], train["threads"], train["seed"]) == ("cpu", 4, cfg.seed)


def test_the_final_choice_leaves_out_snapshots_that_fail_a_gate_unless_all_do():
    from sitl.learn.trainer import select_snapshot

    rows = [{"updates": 10, "score": 0.95, "gate": {"passed": False}},
            {"updates": 20, "score": 0.93, "gate": {"passed": True}},
            {"updates": 30, "score": 0.90}]  # flown before gates existed: competes
    assert select_snapshot(rows)["updates"] == 20
    assert select_snapshot([{**row, "gate": {"passed": False}} for row in rows])["updates"] == 10
    rescored = [{**rows[0], "rescored": {"score": 0.99}}, {**rows[1], "rescored": {"score": 0.80}}, rows[2]]
    assert select_snapshot(rescored)["updates"] == 20  # rescored rows only, and of those the cleared one


def test_the_rescoring_flies_only_snapshots_that_clear_the_gates_unless_none_does(tmp_path):
    """Gates are flown before the rescoring: a snapshot that cannot be chosen is not flown again."""
    from sitl.learn.config import SelectionGate

    cfg, agent_cfg = tiny_configs(tmp_path)
    gate = SelectionGate("paper-circle-n4", "circle", 4, "paper", camera_noise=False, min_success=0.0)
    stages = (STAGES[0], replace(STAGES[1], gates=(gate,)))

    def recipe() -> Recipe:
        return Recipe(cfg, agent_cfg, stages, tmp_path, rescore_top=10, rescore_episodes=2, gate_episodes=2)

    recipe().run()
    index = tmp_path / "stage2-second" / "snapshots" / "validation.json"
    rows = json.loads(index.read_text())
    assert len(rows) >= 2 and all("rescored" in row for row in rows)  # every snapshot cleared the bar of 0
    rows[0]["gate"]["passed"] = False  # as if it had lost the gate's scene
    for row in rows:
        del row["rescored"]
    index.write_text(json.dumps(rows))
    recipe()._rescore_last()
    rows = json.loads(index.read_text())
    assert "rescored" not in rows[0] and all("rescored" in row for row in rows[1:])

    for row in rows:  # nobody clears the gates: all compete, so all are flown again
        row["gate"]["passed"] = False
        row.pop("rescored", None)
    index.write_text(json.dumps(rows))
    recipe()._rescore_last()
    assert all("rescored" in row for row in json.loads(index.read_text()))


def test_flown_distill_rescores_every_last_stage_snapshot_in_random_and_obstacle_scenes():
    """The final choice of flown-distill (session 67) flies each stage-4 snapshot again, not the top few."""
    last = PRESETS["flown-distill"]["stages"][-1]
    recipe = PRESETS["flown-distill"]["recipe"]
    snapshots = last.train["total_updates"] // last.train["eval_every_updates"]
    assert recipe["rescore_top"] >= snapshots and recipe["rescore_episodes"] >= 500
    assert [scene[0] for scene in last.rescore_scenes] == ["random-medium", "obstacles"]


def test_a_gate_flies_its_own_circle_whatever_the_run_scatters():
    """A run that scatters its circles (``circle_scatter_m``) still gates on the paper's symmetric circle."""
    from sitl.learn.config import PAPER_CIRCLE_GATE, TrainConfig, make_sim_config
    from sitl.learn.rescore import gate_config

    cfg = TrainConfig(preset="flown-distill", geometry="flown", scenario="mixed", circle_scatter_m=3.0)
    gated = gate_config(cfg, PAPER_CIRCLE_GATE, 400)
    sim = make_sim_config(gated, 1, scenario_name=PAPER_CIRCLE_GATE.scenario)
    assert sim.scenario.circle_scatter_m == 0.0 and sim.num_uavs == 14 and gated.geometry == "paper"
    assert make_sim_config(cfg, 1, scenario_name="circle").scenario.circle_scatter_m == 3.0  # its own validation


def test_a_recipe_flies_its_gates_on_every_last_stage_snapshot_and_records_them(tmp_path):
    """A gate is flown once per snapshot (validation seeds), recorded in validation.json and the provenance;
    a gate nobody clears leaves the choice to the score (said in the log), and a recipe without gates forgets them."""
    from sitl.learn.config import SelectionGate

    cfg, agent_cfg = tiny_configs(tmp_path)
    gate = SelectionGate("paper-circle-n4", "circle", 4, "paper", camera_noise=False, min_success=0.0)
    stages = (STAGES[0], replace(STAGES[1], gates=(gate,)))
    messages: list[str] = []
    path = Recipe(cfg, agent_cfg, stages, tmp_path, rescore_top=0, rescore_episodes=0, gate_episodes=2,
                  log=messages.append).run()
    rows = json.loads((tmp_path / "stage2-second" / "snapshots" / "validation.json").read_text())
    assert rows and all(row["gate"]["passed"] and row["gate"]["episodes"] == 2 for row in rows)
    assert all(set(row["gate"]["scenes"]) == {"paper-circle-n4"} for row in rows)
    assert sum(m.startswith("gate: ") for m in messages) == len(rows)
    recipe = load_policy(path).metadata["provenance"]["recipe"]
    assert recipe["gates"] == {"episodes": 2, "gates": [asdict(gate)]}

    messages.clear()  # a bar nobody clears: the final choice is redone, every snapshot flown again, all compete
    Recipe(cfg, agent_cfg, (STAGES[0], replace(STAGES[1], gates=(replace(gate, min_success=1.01),))), tmp_path,
           rescore_top=0, rescore_episodes=0, gate_episodes=2, log=messages.append).run()
    assert not any(m.startswith("=== stage") for m in messages) and any("continuing" in m for m in messages)
    assert sum("left out of the final choice" in m for m in messages) == len(rows)
    assert any("no snapshot clears the gates" in m for m in messages)
    assert (tmp_path / "policy.pt").is_file()

    Recipe(cfg, agent_cfg, STAGES, tmp_path, rescore_top=0, rescore_episodes=0, log=messages.append).run()
    rows = json.loads((tmp_path / "stage2-second" / "snapshots" / "validation.json").read_text())
    assert not any("gate" in row for row in rows)
