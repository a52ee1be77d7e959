"""A coverage sweep run (or resumed) into a folder: the configuration's tasks (`skyview.bench.coverage`) on
the executor, each task's records saved as it completes (DIR/chunks/task-NNNNNN.npz, atomic rename),
then the outputs (`skyview.bench.coverage_map`). Run again on the same folder with the same
configuration and only the missing tasks run."""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from skyview.bench.coverage import CoverageConfig, load_results, n_tasks, orientations, run_task
from skyview.bench.coverage_map import write_outputs
from skyview.bench.executor import INLINE, run_tasks
from skyview.core.errors import BadInput


def _task_path(out: Path, task: int) -> Path:
    return out / "chunks" / f"task-{task:06d}.npz"


def _save_task(out: Path, task: int, rec: dict) -> None:
    path = _task_path(out, task)
    tmp = path.with_suffix(".tmp.npz")
    np.savez(tmp, **rec)
    os.replace(tmp, path)


def _prepare(cfg: CoverageConfig, out: Path) -> None:
    """DIR/config.json: written on the first run; a later run must have the same configuration."""
    if out.exists() and not out.is_dir():
        raise BadInput(f"--out {out} is a file, not a folder: give the folder the sweep is written to")
    try:
        out.mkdir(parents=True, exist_ok=True)
        (out / "chunks").mkdir(exist_ok=True)
    except OSError as exc:  # a file of that name, a folder not writable, a parent that is a file
        raise BadInput(f"--out {out}: cannot make the sweep's folder there ({exc.strerror or exc})") from None
    path = out / "config.json"
    if path.exists():
        try:
            old = json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            raise BadInput(f"{path} is not a coverage configuration ({exc}): use another --out") from None
        if old != cfg.to_dict():
            diff = sorted(k for k in set(old) | set(cfg.to_dict()) if old.get(k) != cfg.to_dict().get(k))
            raise BadInput(f"{out} holds a sweep with another configuration ({', '.join(diff)} differ): "
                           f"use another --out, or the same options to resume it")
    else:
        tmp = path.with_suffix(".tmp")
        tmp.write_text(json.dumps(cfg.to_dict(), indent=1))
        os.replace(tmp, path)


def done_tasks(out: Path) -> set[int]:
    return {int(p.stem.split("-")[1]) for p in (out / "chunks").glob("task-*.npz") if not p.stem.endswith(".tmp")}


class _Bar:
    def __init__(self, total: int, done: int, label: str, enabled: bool):
        self.total, self.done, self.label, self.enabled = total, done, label, enabled
        self.t0 = time.perf_counter()
        self.start = done

    def update(self, n_orient: int) -> None:
        self.done += 1
        if not self.enabled:
            return
        dt = time.perf_counter() - self.t0
        rate = (self.done - self.start) / dt if dt > 0 else 0.0
        eta = (self.total - self.done) / rate if rate > 0 else float("nan")
        end = "\n" if self.done == self.total else ""
        sys.stderr.write(f"\r{self.label}: {self.done}/{self.total} tasks, {rate * n_orient:.0f} orientations/s, "
                         f"eta {eta:.0f} s   {end}")
        sys.stderr.flush()


def run_coverage(cfg: CoverageConfig, out: str | Path, *, scheduler: str | None = None, n_workers: int = 2,
                 processes: bool = True, progress: bool = True, max_tasks: int | None = None) -> dict:
    """Sweep (or resume) the configuration into DIR `out`; the summary once every task is done, else
    (max_tasks cut the run short) {"complete": False, ...}. See the module docstring."""
    cfg = cfg.checked()
    out = Path(out)
    _prepare(cfg, out)
    n = len(orientations(cfg))
    total = n_tasks(cfg, n)
    have = done_tasks(out)
    todo = [t for t in range(total) if t not in have]
    if max_tasks is not None:
        todo = todo[:max(0, int(max_tasks))]
    bar = _Bar(total, len(have), f"coverage {cfg.method}({cfg.variant}) {cfg.fov_deg:g} deg", progress)
    t0 = time.perf_counter()

    def save(a, rec):
        _save_task(out, a[1], rec)
        bar.update(cfg.chunk)

    run_tasks(run_task, [(cfg.to_dict(), t) for t in todo], scheduler=scheduler, n_workers=n_workers,
              processes=processes, on_result=save)
    wall = time.perf_counter() - t0
    if len(done_tasks(out)) < total:
        return {"complete": False, "tasks_done": len(done_tasks(out)), "tasks": total}
    res = load_results(out)
    workers = 1 if scheduler == INLINE else n_workers
    return write_outputs(cfg, res, out, run={"wall_s": wall, "tasks_run": len(todo), "workers": workers,
                                             "scheduler": scheduler or "LocalCluster"})
