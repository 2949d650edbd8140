"""Figures of the evaluation: trajectories (paper Figs. 5 and 7) and scaling with N (Fig. 6).

Everything is drawn with matplotlib's non-interactive Agg backend, so it works on a
headless machine. Positions are local NED; the plots show east/north/altitude, which is
how a reader expects a map (north up, altitude up).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sitl.sim.metrics import UAVRecord


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: Path, title: str, dpi: int = 100) -> Path:
    """Title, lay out, write ``path`` (its folder made) and close ``fig``; returns ``path``."""
    fig.suptitle(title)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    _pyplot().close(fig)
    return path


def _colours(plt, count: int) -> np.ndarray:
    """One distinct colour per UAV (tab20 up to 20 UAVs, then a continuous map)."""
    if count <= 10:
        return plt.cm.tab10(np.arange(count))
    if count <= 20:
        return plt.cm.tab20(np.arange(count))
    return plt.cm.turbo(np.linspace(0.05, 0.95, count))


def episode_records(records: list[UAVRecord], episode: int | None = None) -> list[UAVRecord]:
    """The records of one episode (the first one in ``records`` when ``episode`` is None)."""
    if not records:
        return []
    if episode is None:
        episode = records[0].episode
    return sorted((r for r in records if r.episode == episode), key=lambda r: r.uav)


def plot_trajectories(records: list[UAVRecord], path: str | Path, title: str, episode: int | None = None) -> Path:
    """One episode's paths: 3D perspective plus top, front and side views, one colour per UAV.

    Start: filled dot; goal: cross; a failed UAV ends in a red ring (collision) or a grey
    square (timeout). Needs records with ``path_ned`` (``SimConfig.record_paths``).
    Returns the written path.
    """
    plt = _pyplot()
    chosen = episode_records(records, episode)
    if not chosen:
        raise ValueError("no records to plot")
    if any(r.path_ned is None for r in chosen):
        raise ValueError("records carry no paths: evaluate with record_paths=True")
    path = Path(path)
    fig = plt.figure(figsize=(12, 10))
    ax3d = fig.add_subplot(2, 2, 1, projection="3d")
    top, front, side = (fig.add_subplot(2, 2, k) for k in (2, 3, 4))
    colours = _colours(plt, len(chosen))
    # (axes, horizontal coordinate, vertical coordinate) of each 2D view; NED index, sign.
    views = ((top, (1, 1.0), (0, 1.0)), (front, (1, 1.0), (2, -1.0)), (side, (0, 1.0), (2, -1.0)))
    for rec, colour in zip(chosen, colours):
        xyz = np.asarray(rec.path_ned, dtype=float)
        east, north, alt = xyz[:, 1], xyz[:, 0], -xyz[:, 2]
        goal = np.asarray(rec.goal_ned, dtype=float)
        ax3d.plot(east, north, alt, color=colour, lw=1.4)
        ax3d.scatter(east[0], north[0], alt[0], color=colour, s=18)
        ax3d.scatter(goal[1], goal[0], -goal[2], color=colour, marker="x", s=30)
        for ax, (hi, hs), (vi, vs) in views:
            ax.plot(hs * xyz[:, hi], vs * xyz[:, vi], color=colour, lw=1.4)
            ax.plot(hs * xyz[0, hi], vs * xyz[0, vi], "o", color=colour, ms=4)
            ax.plot(hs * goal[hi], vs * goal[vi], "x", color=colour, ms=6)
            if rec.outcome.startswith("collision"):
                ax.plot(hs * xyz[-1, hi], vs * xyz[-1, vi], "o", mfc="none", mec="red", ms=10, mew=1.5)
            elif rec.outcome == "timeout":
                ax.plot(hs * xyz[-1, hi], vs * xyz[-1, vi], "s", mfc="none", mec="grey", ms=9, mew=1.5)
    ax3d.set(xlabel="east (m)", ylabel="north (m)", zlabel="altitude (m)", title="3D view")
    top.set(xlabel="east (m)", ylabel="north (m)", title="top view", aspect="equal")
    front.set(xlabel="east (m)", ylabel="altitude (m)", title="front view (looking north)")
    side.set(xlabel="north (m)", ylabel="altitude (m)", title="side view (looking west)")
    for ax in (top, front, side):
        ax.grid(alpha=0.3)
    failed = sum(not r.success for r in chosen)
    return _save(fig, path, f"{title}\nepisode {chosen[0].episode}: {len(chosen) - failed}/{len(chosen)} arrived "
                 "(dot: start, x: goal, red ring: collision, grey square: timeout)", dpi=90)


def plot_scaling(results: dict[str, dict[int, dict]], path: str | Path, title: str) -> Path:
    """Paper Fig. 6: success rate and SPL against the number of UAVs, one line per method.

    ``results[method][n]`` is a :func:`sitl.sim.metrics.summarize` dict; missing cells are gaps.
    """
    plt = _pyplot()
    path = Path(path)
    fig, (ax_s, ax_p) = plt.subplots(1, 2, figsize=(11, 4.5))
    markers = "osd^v<>"
    for k, (method, by_n) in enumerate(results.items()):
        ns = sorted(by_n)
        if not ns:
            continue
        for ax, key in ((ax_s, "success_rate"), (ax_p, "spl")):
            # Colour and marker follow the method's position, so a method keeps its look when another has no data.
            ax.plot(ns, [by_n[n][key] for n in ns], marker=markers[k % len(markers)], color=f"C{k % 10}",
                    label=method)
    for ax, label in ((ax_s, "success rate"), (ax_p, "SPL")):
        ax.set(xlabel="number of UAVs N", ylabel=label, ylim=(-0.03, 1.03))
        ax.grid(alpha=0.3)
    ax_s.legend()
    return _save(fig, path, title)


def plot_protocol(results: dict[str, dict[str, dict]], path: str | Path, title: str) -> Path:
    """A protocol's success per cell, one bar per method (left), and the first method's success by goal
    altitude per cell (right). ``results[cell][method]`` holds ``summary`` and ``by_goal_altitude``
    (:func:`sitl.sim.metrics.success_by_goal_altitude`); empty altitude bins are left out."""
    plt = _pyplot()
    path = Path(path)
    cells = list(results)
    methods = list(dict.fromkeys(m for c in cells for m in results[c]))
    fig, (ax_c, ax_a) = plt.subplots(1, 2, figsize=(13, 4.8))
    width = 0.8 / max(1, len(methods))
    x = np.arange(len(cells))
    for k, method in enumerate(methods):
        rates = [results[c].get(method, {}).get("summary", {}).get("success_rate", np.nan) for c in cells]
        ax_c.bar(x + (k - (len(methods) - 1) / 2) * width, [np.nan if r is None else r for r in rates], width,
                 label=method, color=f"C{k % 10}")
    first = methods[0] if methods else None
    bins = list(results[cells[0]][first]["by_goal_altitude"]) if cells and first else []
    width_a = 0.8 / max(1, len(bins))
    for k, label in enumerate(bins):
        rates = []
        for c in cells:
            rate = results[c][first]["by_goal_altitude"][label]["success_rate"]
            rates.append(np.nan if rate is None else rate)
        ax_a.bar(x + (k - (len(bins) - 1) / 2) * width_a, rates, width_a, label=f"goal {label}", color=f"C{(k + 3) % 10}")
    for ax, sub in ((ax_c, "success rate"), (ax_a, f"success by goal altitude ({first})")):
        ax.set_xticks(x, cells, rotation=25, ha="right")
        ax.set(ylabel="success rate", ylim=(0, 1.05), title=sub)
        ax.grid(alpha=0.3, axis="y")
        ax.legend(fontsize=8)
    return _save(fig, path, title)


def plot_seed_spread(columns: dict[str, dict[str, dict[int, float]]], path: str | Path, title: str) -> Path:
    """A sweep's successes over seeds: one panel per grid point, per column (a final or evaluation
    scene) one dot per seed with its seed number and a bar at the mean; the spread (max - min) in
    the tick label. ``columns[grid point][column][seed]`` is a success rate."""
    plt = _pyplot()
    path = Path(path)
    points = list(columns)
    fig, axes = plt.subplots(1, max(1, len(points)), figsize=(max(6.0, 1.6 * max(len(c) for c in columns.values())
                                                                  * len(points)), 4.6), squeeze=False)
    for ax, point in zip(axes[0], points):
        names = list(columns[point])
        labels = []
        for k, name in enumerate(names):
            seeds = columns[point][name]
            rates = np.array(list(seeds.values()), dtype=float)
            ax.scatter(np.full(len(rates), k), rates, color=f"C{k % 10}", zorder=3)
            for seed, rate in seeds.items():
                ax.annotate(f"s{seed}", (k, rate), xytext=(5, -3), textcoords="offset points", fontsize=7)
            if len(rates):
                ax.hlines(rates.mean(), k - 0.3, k + 0.3, color="k", lw=1.5)
            labels.append(f"{name}\nspread {np.ptp(rates):.3f}" if len(rates) else name)
        ax.set_xticks(range(len(names)), labels, rotation=25, ha="right", fontsize=8)
        ax.set(ylabel="success rate", title=point, xlim=(-0.6, len(names) - 0.4))
        ax.grid(alpha=0.3, axis="y")
    return _save(fig, path, title)


def plot_response_fits(runs: dict[str, list[dict]], path: str | Path, title: str) -> Path:
    """Each vehicle's fitted velocity response (``sitl.realtime.response_fit``), one colour per run: lag against drag,
    and lag against the quick share of a step's speed. ``runs[name]`` is a list of ``VehicleFit`` dicts."""
    plt = _pyplot()
    path = Path(path)
    fig, (ax_d, ax_g) = plt.subplots(1, 2, figsize=(11, 4.5))
    markers = "osd^v<>P*X"
    rng = np.random.default_rng(0)  # a small jitter: fits on one grid point would hide each other
    for k, (name, fits) in enumerate(runs.items()):
        tau = np.array([f["tau_horizontal_s"] for f in fits]) + rng.uniform(-0.01, 0.01, len(fits))
        style = dict(marker=markers[k % len(markers)], color=f"C{k % 10}", alpha=0.8, label=name, linestyle="none")
        ax_d.plot(tau, [f["drag_horizontal_per_s"] for f in fits], **style)
        ax_g.plot(tau, [f["quick_gain"] for f in fits], **style)
    ax_d.set(xlabel="horizontal lag tau (s)", ylabel="drag (1/s)")
    ax_g.set(xlabel="horizontal lag tau (s)", ylabel="quick gain 1 / (1 + drag tau)")
    for ax in (ax_d, ax_g):
        ax.grid(alpha=0.3)
    ax_d.legend(fontsize=7)
    return _save(fig, path, title)
