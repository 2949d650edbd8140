"""The paper's Table II and Fig. 6 reproduction (``python -m sitl.swarm_test paper``): cells, resumable runs, report."""

from __future__ import annotations

import dataclasses
import json
import sys
from dataclasses import dataclass, replace
from pathlib import Path

from sitl.eval.evaluate import EvalSettings, density_label, evaluate_method
from sitl.eval.methods import DEFAULT_POLICY, Method, file_digest, resolve_method
from sitl.eval.report import write_json, markdown_table
from sitl.sim.config import CIRCLE_RADIUS_M, DENSITIES, ScenarioConfig, density_from_name

#: Learning methods of Table II whose policy files ``paper`` looks for.
PAPER_METHODS = ("sac_ae", "cnn", "vae")


DEFAULT_FIG6_NS = (8, 10, 12, 14, 16, 20, 24, 28, 32)


def parse_policies(text: str) -> dict[str, Path]:
    """``sac_ae=PATH,cnn=PATH`` -> paths, defaulting to ``models/policy_<method>.pt``.

    sac_ae, when not given and ``models/policy_sac_ae.pt`` does not exist, falls back to
    the bundled ``models/policy.pt`` (the project's SAC+AE policy).
    """
    paths = {m: Path(f"models/policy_{m}.pt") for m in PAPER_METHODS}
    given = set()
    for item in filter(None, (s.strip() for s in text.split(","))):
        name, sep, value = item.partition("=")
        if not sep or not value:
            raise ValueError(f"--policies items are METHOD=PATH, got {item!r}")
        if name not in PAPER_METHODS:
            raise ValueError(f"--policies: unknown method {name!r}; the paper's methods are {', '.join(PAPER_METHODS)}")
        paths[name] = Path(value)
        given.add(name)
    if "sac_ae" not in given and not paths["sac_ae"].exists() and DEFAULT_POLICY.exists():
        paths["sac_ae"] = DEFAULT_POLICY
    return paths


@dataclass
class PaperCell:
    """One evaluation of the reproduction: a method in one scene."""

    name: str  # file stem under OUT/cells
    method: str  # sac_ae, cnn, vae, orca, straight
    spec: str | None  # what resolve_method gets; None: policy file missing
    settings: EvalSettings
    plot: bool = False  # also draw the first episode's trajectories


def _cell_key(cell: PaperCell, method: Method | None) -> dict:
    """What a stored cell must match to be reused: the settings and the exact policy file."""
    s = cell.settings
    return {"method": cell.method, "scenario": dataclasses.asdict(s.scenario), "num_uavs": s.num_uavs,
            "episodes": s.episodes, "seed": s.seed, "dynamics": s.dynamics, "camera_noise": s.camera_noise,
            "max_episode_steps": s.max_episode_steps,
            "policy_sha256": file_digest(method.path) if method is not None and method.path else None}


def stored_cell(cell: PaperCell, out: Path) -> dict | None:
    """The summary of an identical cell already under ``out`` (same settings and policy file), else None."""
    path = out / "cells" / f"{cell.name}.json"
    if cell.spec is None or not path.is_file():
        return None
    try:
        stored = json.loads(path.read_text())
        # compared as stored: JSON turns the scenario's tuples (e.g. obstacle size ranges) into lists
        if stored.get("key") == json.loads(json.dumps(_cell_key(cell, resolve_method(cell.spec)))):
            return stored["summary"]
    except (json.JSONDecodeError, KeyError):
        pass  # unreadable: compute it again
    return None


def run_cell(cell: PaperCell, out: Path, progress: bool = True) -> tuple[dict | None, str]:
    """Evaluate one cell unless an identical one is stored; return (summary or None, status)."""
    if cell.spec is None:
        return None, "not trained"
    method = resolve_method(cell.spec)
    if method.kind == "policy" and method.provenance.get("method") not in (None, cell.method):
        print(f"warning: {method.path} was trained with method {method.provenance['method']!r} "
              f"but is evaluated as {cell.method!r}", file=sys.stderr)
    stored = stored_cell(cell, out)
    if stored is not None:
        return stored, "stored"
    path = out / "cells" / f"{cell.name}.json"
    key = _cell_key(cell, method)
    settings = replace(cell.settings, record_paths=cell.plot)
    result = evaluate_method(method, settings, progress=progress, desc=cell.name, leave=False)
    if cell.plot:
        from sitl.eval.plots import plot_trajectories

        plot_trajectories(result.records, out / "trajectories" / f"{cell.name}.png",
                          f"{cell.method}, {settings.describe()}")
    data = {"key": key, "settings": {**dataclasses.asdict(settings), "eval_seed": settings.env_seed},
            **result.to_json(with_records=False)}
    write_json(path, data)
    return result.summary, "computed"


def paper_cells(episodes: int, seed: int, dynamics: str, camera_noise: bool, max_steps: int, batch: int,
                policy_paths: dict[str, Path], table_n: int = 8, densities: list[str] | None = None,
                ns: list[int] | None = None, radius: float = CIRCLE_RADIUS_M,
                table_episodes: int | None = None) -> tuple[list[PaperCell], list[PaperCell]]:
    """The cells of Table II (``table_episodes`` each, default ``episodes``) and of Fig. 6 (``episodes``)."""
    densities = list(DENSITIES) if densities is None else densities
    ns = list(DEFAULT_FIG6_NS) if ns is None else ns
    common = dict(episodes=episodes, seed=seed, dynamics=dynamics, camera_noise=camera_noise,
                  max_episode_steps=max_steps, batch_worlds=batch, record_paths=False)
    specs: dict[str, str | None] = {m: (str(p) if p.exists() else None) for m, p in policy_paths.items()}
    specs |= {"orca": "orca", "straight": "straight"}
    table = []
    for density in densities:
        scen = ScenarioConfig(name="random", density=density_from_name(density))
        for m in (*PAPER_METHODS, "orca", "straight"):
            table.append(PaperCell(f"table2-{density}-{m}", m, specs[m],
                                   EvalSettings(scenario=scen, num_uavs=table_n,
                                                **(common | {"episodes": table_episodes or episodes}))))
    fig6 = []
    circle = ScenarioConfig(name="circle", circle_radius_m=radius)
    for n in ns:
        for m in ("sac_ae", "vae", "orca", "straight"):  # the paper's Fig. 6 compares ours with RL+VAE
            fig6.append(PaperCell(f"fig6-n{n}-{m}", m, specs[m], EvalSettings(scenario=circle, num_uavs=n, **common),
                                  plot=True))
    return table, fig6


def run_paper(out: Path, table: list[PaperCell], fig6: list[PaperCell], progress: bool = True,
              policy_paths: dict[str, Path] | None = None, ray_address: str | None = None) -> dict:
    """Evaluate every cell (skipping stored ones), then write ``paper.md``, ``paper.json`` and ``fig6_scaling.png``.

    ``ray_address`` (``local``, ``auto`` or a cluster's): the cells to compute are Ray tasks
    (:func:`sitl.eval.paper_ray.run_cells_on_ray`), their files written here as a local run writes them.
    """
    from tqdm import tqdm

    from sitl.eval.plots import plot_scaling

    out.mkdir(parents=True, exist_ok=True)
    summaries: dict[str, dict | None] = {}
    status: dict[str, str] = {}
    cells = table + fig6
    if ray_address is not None:
        from sitl.eval.paper_ray import run_cells_on_ray

        for name, (summary, state) in run_cells_on_ray(cells, out, ray_address, progress).items():
            summaries[name], status[name] = summary, state
        cells_here: list[PaperCell] = []
    else:
        cells_here = cells
    with tqdm(total=len(cells_here), unit="cell", desc="paper", disable=not progress or not cells_here,
              file=sys.stderr) as bar:
        for cell in cells_here:
            bar.set_postfix_str(cell.name)
            summaries[cell.name], status[cell.name] = run_cell(cell, out, progress)
            bar.update(1)
    summaries = {c.name: summaries[c.name] for c in cells}  # the tables' order, whatever order tasks ended in

    lines = ["# Reproduction of Huang et al., Table II and Fig. 6", "",
             "Generated by `python -m sitl.swarm_test paper`. Success with the half-width of its ~95 % "
             "confidence interval (clustered by episode); other columns mean ± std over UAVs and episodes; "
             "collision = 1 - success, split into UAV-UAV, ground and timeout. `orca` is privileged "
             "(true states of all UAVs); `straight` flies at its goal without avoiding anyone.", ""]
    if cells:
        s = cells[0].settings
        lines += [f"Settings: episodes per cell: Table II {table[0].settings.episodes if table else '-'}, Fig. 6 "
                  f"{fig6[0].settings.episodes if fig6 else '-'}; evaluation seed {s.env_seed}, {s.dynamics} dynamics, "
                  f"camera noise {'on' if s.camera_noise else 'off'}, time limit {s.max_episode_steps} steps.", ""]
    if policy_paths:
        lines += ["Policy files: " + ", ".join(f"{m} = `{p}`" + ("" if p.exists() else " (not trained)")
                                              for m, p in policy_paths.items()), ""]
    if table:
        lines += [f"## Table II: random scenes, N = {table[0].settings.num_uavs}", "",
                  markdown_table(["density", "method"],
                                 [([density_label(c.settings.scenario.density), c.method], summaries[c.name])
                                  for c in table]), ""]
    scaling: dict[str, dict[int, dict]] = {}
    if fig6:
        lines += [f"## Fig. 6: circle scenario, radius {fig6[0].settings.scenario.circle_radius_m:g} m", "",
                  markdown_table(["N", "method"],
                                 [([str(c.settings.num_uavs), c.method], summaries[c.name]) for c in fig6]), "",
                  "![success rate and SPL against N](fig6_scaling.png)", ""]
        for c in fig6:
            by_n = scaling.setdefault(c.method, {})
            if summaries[c.name] is not None:
                by_n[c.settings.num_uavs] = summaries[c.name]
        plot_scaling(scaling, out / "fig6_scaling.png", "circle scenario: success and SPL against the swarm size")
    (out / "paper.md").write_text("\n".join(lines))
    write_json(out / "paper.json", {"cells": {name: {"summary": summaries[name], "status": status[name]}
                                               for name in summaries}})
    return {"summaries": summaries, "status": status}
