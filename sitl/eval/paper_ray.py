"""``python -m sitl.swarm_test paper --ray [ADDRESS]``: the reproduction's cells as Ray tasks.

Each cell still to compute (not stored under OUT with the same settings and policy file)
is one task holding one CPU. The task gets the policy file's bytes, not its path — a
cluster's nodes need not see this machine's files — evaluates the cell exactly as
:func:`sitl.eval.paper.run_cell` does into a scratch folder, and returns the files it
wrote (the cell's JSON, its trajectory figure); they are written under OUT here, with the
policy's path as given on this machine, so the folder is the one a run without Ray writes.
"""

from __future__ import annotations

import json
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

from sitl.distributed import connect, describe_cluster, log, single_thread
from sitl.eval.paper import PaperCell, run_cell, stored_cell
from sitl.eval.report import write_json


def evaluate_cell_task(cell: PaperCell, policy_name: str | None, policy_bytes: bytes | None) -> dict:
    """Inside a task: evaluate ``cell`` (its policy file given as bytes) and return the files it wrote."""
    single_thread()
    with tempfile.TemporaryDirectory(prefix="swarmnav-cell-") as tmp:
        scratch = Path(tmp)
        if policy_bytes is not None:
            local = scratch / "policy" / policy_name
            local.parent.mkdir()
            local.write_bytes(policy_bytes)
            cell = replace(cell, spec=str(local))
        summary, _ = run_cell(cell, scratch / "out", progress=False)
        files = {str(p.relative_to(scratch / "out")): p.read_bytes()
                 for p in sorted((scratch / "out").rglob("*")) if p.is_file()}
    return {"summary": summary, "files": files}


def write_cell_files(out: Path, cell: PaperCell, files: dict[str, bytes]) -> None:
    """Write the files a cell's task returned under ``out``, naming the policy by its path here."""
    for rel, data in files.items():
        path = out / rel
        if rel == f"cells/{cell.name}.json":
            record = json.loads(data)
            if isinstance(record.get("method"), dict) and record["method"].get("path"):
                record["method"]["path"] = cell.spec  # the path a user gave, not the task's scratch copy
            write_json(path, record)
            continue
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data)


def run_cells_on_ray(cells: list[PaperCell], out: Path, address: str, progress: bool = True) -> dict[str, tuple]:
    """``{cell name: (summary or None, status)}`` for every cell, the ones to compute computed on Ray."""
    results: dict[str, tuple] = {}
    todo = []
    for cell in cells:
        if cell.spec is None:
            results[cell.name] = (None, "not trained")
        elif (stored := stored_cell(cell, out)) is not None:
            results[cell.name] = (stored, "stored")
        else:
            todo.append(cell)
    if not todo:
        return results
    ray = connect(address, log_to_driver=True)
    log(f"{describe_cluster(ray)}; {len(todo)} cell(s) to compute, 1 CPU each")
    blobs: dict[str, object] = {}  # policy path -> object ref of its bytes, shipped once
    for cell in todo:
        if Path(cell.spec).is_file() and cell.spec not in blobs:
            blobs[cell.spec] = ray.put(Path(cell.spec).read_bytes())
    task = ray.remote(num_cpus=1, max_retries=1)(evaluate_cell_task)
    pending = {task.remote(cell, Path(cell.spec).name if cell.spec in blobs else None, blobs.get(cell.spec)): cell
               for cell in todo}
    from tqdm import tqdm

    with tqdm(total=len(todo), unit="cell", desc="paper on Ray", disable=not progress, file=sys.stderr) as bar:
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1)
            cell = pending.pop(ready[0])
            outcome = ray.get(ready[0])  # a failed cell fails the run, as it does without Ray
            write_cell_files(out, cell, outcome["files"])
            results[cell.name] = (outcome["summary"], "computed")
            bar.set_postfix_str(cell.name)
            bar.update(1)
    return results
