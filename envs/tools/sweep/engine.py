"""Run a sweep as Ray tasks, one row per run, resumable.

Folder layout (``out_dir``):

- ``sweep.json``: marks the folder as a sweep (name, spec, first and last start); resuming needs it.
- ``spec.yaml``: the spec of the last start.
- ``runs/<run_id>.json``: one shard per finished run (written atomically when the run ends): the row.
- ``results.parquet``: the rows of the spec's runs, rewritten from the shards every few seconds, at the end
  and on Ctrl-C (atomically: an interrupted sweep leaves the previous complete table).

Resume: a run is keyed by :attr:`RunConfig.run_id` (hash of its whole configuration); starting again into
the same folder submits only the runs without a shard (and, with ``retry_failed``, those whose shard holds an
error). A run is a plain function call (:func:`execute_run`), which Ray runs as a task of ``num_cpus=1``; at
most ``workers`` tasks are in flight, so a task's clock (the per-run timeout) starts when it starts.
"""

from __future__ import annotations

import datetime
import json
import os
import shutil
import socket
import subprocess
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from viotb.envs.tools.sweep.runs import RunConfig, run_config
from viotb.envs.tools.sweep.spec import SweepSpec, load_spec, parse_spec

MARKER = "sweep.json"
RESULTS = "results.parquet"
SHARDS = "runs"
CONSOLIDATE_EVERY_S = 5.0
"""Rewrite the Parquet table at most this often while the sweep runs (seconds)."""
WORKER_ENV = {"OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MUJOCO_GL": "egl"}
"""Environment of the Ray workers: single-threaded BLAS (determinism), offscreen GL."""
META_COLUMNS = ("run_id", "config_id", "status", "error", "seed")
RUN_COLUMNS = ("wall_s", "host", "pid", "version", "git_commit", "finished_utc")


@dataclass(frozen=True)
class SweepProgress:
    """Where a sweep stands (passed to the progress callback after each finished run).

    Attributes:
        total: Runs of the spec.
        done: Runs with a row (skipped ones included).
        failed: Rows with an error (of this start and earlier ones).
        running: Tasks in flight.
    """

    total: int
    done: int
    failed: int
    running: int

    @property
    def remaining(self) -> int:
        """Runs without a row yet."""
        return self.total - self.done


@dataclass(frozen=True)
class SweepResult:
    """Outcome of :func:`run_sweep` (the ``viotb sweep --json`` keys).

    Attributes:
        runs: Runs of the spec.
        computed: Runs executed by this start (failed ones included).
        skipped: Runs found in the folder already.
        failed: Rows with an error, in all.
        results: The Parquet table.
        wall_s: Wall time of this start (s).
        interrupted: Stopped by Ctrl-C before every run had a row.
    """

    runs: int
    computed: int
    skipped: int
    failed: int
    results: Path
    wall_s: float
    interrupted: bool = False

    def as_json(self) -> dict:
        """Strict-JSON dict of the result."""
        return {
            "runs": self.runs,
            "computed": self.computed,
            "skipped": self.skipped,
            "failed": self.failed,
            "results": str(self.results),
            "wall_s": round(self.wall_s, 3),
            "interrupted": self.interrupted,
        }


class SweepInterrupted(KeyboardInterrupt):
    """Ctrl-C during a sweep, after the finished rows were saved; ``result`` holds the counts."""

    def __init__(self, result: SweepResult) -> None:
        """Keep the partial result."""
        super().__init__("sweep interrupted")
        self.result = result


def execute_run(cfg_dict: dict, meta: dict) -> dict:
    """One run as a row (what a Ray task executes); an exception becomes the row's ``error``.

    Args:
        cfg_dict: :meth:`RunConfig.as_dict` of the run.
        meta: Columns added to the row (``version``, ``git_commit``).

    Returns:
        The row: identifiers, ``config/<axis>`` columns, the metrics, wall time, host.
    """
    cfg = RunConfig.from_dict(cfg_dict)
    t0 = time.perf_counter()
    try:
        metrics, status, error = run_config(cfg), "ok", None
    except Exception as exc:  # noqa: BLE001 (a failing run is a row, the sweep goes on)
        tb = traceback.format_exc(limit=-3)
        metrics, status, error = {}, "error", f"{type(exc).__name__}: {exc}\n{tb}"
    return _row(cfg, status, error, metrics, time.perf_counter() - t0, meta)


def run_sweep(
    spec: SweepSpec | dict | Path | str,
    out_dir: Path | str,
    workers: int | None = None,
    address: str | None = None,
    *,
    timeout_s: float | None = None,
    retry_failed: bool = False,
    overwrite: bool = False,
    progress: Callable[[SweepProgress], None] | None = None,
) -> SweepResult:
    """Run (or resume) a sweep into ``out_dir``.

    Args:
        spec: A parsed spec, its dict, or the path of its YAML file.
        out_dir: Sweep folder (created; a non-empty folder that is not a sweep is refused unless
            ``overwrite``; a sweep folder is resumed).
        workers: Tasks in flight (and CPUs of a local Ray instance); default: the CPU count (local) or the
            cluster's CPUs (``address``).
        address: Ray cluster to join (``ray start --head`` prints it; ``"auto"`` finds a local one); None
            starts a local instance. An already initialized Ray (``ray.init`` by the caller) is used as is.
        timeout_s: Per-run timeout (s); default: the spec's ``timeout_s`` (None: no limit).
        retry_failed: Run again the runs whose row holds an error.
        overwrite: Empty a non-sweep ``out_dir`` (or a sweep one: start over) first.
        progress: Called with a :class:`SweepProgress` at the start and after each finished run.

    Returns:
        The counts and the Parquet path.

    Raises:
        SpecError: A bad spec (before anything is written).
        FileExistsError: ``out_dir`` is not empty and not a sweep folder.
        SweepInterrupted: Ctrl-C; the finished rows are in the table.
    """
    t_start = time.perf_counter()
    if not isinstance(spec, SweepSpec):
        spec = parse_spec(spec) if isinstance(spec, dict) else load_spec(spec)
    out = _prepare_out_dir(Path(out_dir), spec, overwrite)
    runs = list({cfg.run_id: cfg for cfg in spec.expand()}.values())
    rows = _read_shards(out / SHARDS)
    todo = [c for c in runs if c.run_id not in rows or (retry_failed and rows[c.run_id]["status"] != "ok")]
    skipped = len(runs) - len(todo)
    limit_s = timeout_s if timeout_s is not None else spec.timeout_s
    state = _State(out, runs, rows, progress)
    state.report(0)
    interrupted = False
    try:
        if todo:
            _run_on_ray(todo, workers, address, limit_s, _meta(), state)
    except KeyboardInterrupt:
        interrupted = True
    finally:
        write_results(out, runs, state.rows)
    result = SweepResult(
        runs=len(runs),
        computed=state.computed,
        skipped=skipped,
        failed=sum(1 for c in runs if c.run_id in state.rows and state.rows[c.run_id]["status"] != "ok"),
        results=out / RESULTS,
        wall_s=time.perf_counter() - t_start,
        interrupted=interrupted,
    )
    if interrupted:
        raise SweepInterrupted(result)
    return result


class _State:
    """Rows of the sweep so far, shard writing, progress and periodic consolidation."""

    def __init__(self, out: Path, runs: list[RunConfig], rows: dict, progress) -> None:
        self.out, self.runs, self.rows, self.progress = out, runs, rows, progress
        self.ids = {c.run_id for c in runs}
        self.computed = 0
        self.last_write = time.monotonic()

    def finish(self, row: dict, running: int) -> None:
        _write_json_atomic(self.out / SHARDS / f"{row['run_id']}.json", row)
        self.rows[row["run_id"]] = row
        self.computed += 1
        if time.monotonic() - self.last_write > CONSOLIDATE_EVERY_S:
            write_results(self.out, self.runs, self.rows)
            self.last_write = time.monotonic()
        self.report(running)

    def report(self, running: int) -> None:
        if self.progress is None:
            return
        mine = [self.rows[i] for i in self.ids if i in self.rows]
        failed = sum(1 for r in mine if r["status"] != "ok")
        self.progress(SweepProgress(total=len(self.ids), done=len(mine), failed=failed, running=running))


def _run_on_ray(todo: list[RunConfig], workers, address, limit_s, meta: dict, state: _State) -> None:
    """Submit ``todo`` as tasks (at most ``workers`` in flight) and collect the rows."""
    import ray

    started_here = not ray.is_initialized()
    if started_here:
        kwargs: dict[str, Any] = {
            "include_dashboard": False,
            "log_to_driver": False,
            "logging_level": "WARNING",
            "runtime_env": {"env_vars": dict(WORKER_ENV)},
        }
        if address is None:
            kwargs.update(num_cpus=workers or os.cpu_count() or 1, object_store_memory=128 * 1024**2)
        else:
            kwargs["address"] = address
        ray.init(**kwargs)
    try:
        slots = workers or max(int(ray.cluster_resources().get("CPU", 1)), 1)
        task = ray.remote(num_cpus=1, max_retries=0)(execute_run)
        pending = list(reversed(todo))
        in_flight: dict[Any, tuple[RunConfig, float]] = {}
        try:
            while pending or in_flight:
                while pending and len(in_flight) < slots:
                    cfg = pending.pop()
                    in_flight[task.remote(cfg.as_dict(), meta)] = (cfg, time.monotonic())
                ready, _ = ray.wait(list(in_flight), num_returns=1, timeout=0.5)
                for ref in ready:
                    cfg, _t0 = in_flight.pop(ref)
                    state.finish(_collect(ray, ref, cfg, meta), len(in_flight))
                now = time.monotonic()
                for ref, (cfg, t0) in list(in_flight.items()):
                    if limit_s is not None and now - t0 > limit_s:
                        ray.cancel(ref, force=True)
                        del in_flight[ref]
                        row = _row(cfg, "timeout", f"timed out after {limit_s:g} s", {}, now - t0, meta)
                        state.finish(row, len(in_flight))
        finally:
            for ref in in_flight:
                ray.cancel(ref, force=True)
    finally:
        if started_here:
            ray.shutdown()


def _collect(ray, ref, cfg: RunConfig, meta: dict) -> dict:
    """The task's row, or an error row when the task itself died (worker crash, cancelled)."""
    try:
        return ray.get(ref)
    except Exception as exc:  # noqa: BLE001 (RayTaskError, WorkerCrashedError, ...)
        return _row(cfg, "crashed", f"{type(exc).__name__}: {exc}", {}, float("nan"), meta)


def _row(cfg: RunConfig, status: str, error: str | None, metrics: dict, wall_s: float, meta: dict) -> dict:
    row: dict = {
        "run_id": cfg.run_id,
        "config_id": cfg.config_id,
        "status": status,
        "error": error,
        "seed": cfg.seed,
    }
    row.update({f"config/{k}": v for k, v in cfg.as_dict().items() if k != "seed"})
    row.update({k: v for k, v in metrics.items() if k not in row})
    row.update(
        {
            "wall_s": wall_s,
            "host": socket.gethostname(),
            "pid": os.getpid(),
            **meta,
            "finished_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        }
    )
    return row


def _meta() -> dict:
    """Package version and git commit of the driver's checkout (None outside a git checkout)."""
    import viotb

    commit = None
    try:
        root = Path(viotb.__file__).resolve().parent.parent
        out = subprocess.run(
            ["git", "-C", str(root), "rev-parse", "HEAD"],
            capture_output=True,
            text=True,
            timeout=10,
            check=True,
        )
        dirty = subprocess.run(
            ["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
            capture_output=True,
            text=True,
            timeout=10,
            check=True,
        ).stdout.strip()
        commit = out.stdout.strip() + ("-dirty" if dirty else "")
    except (OSError, subprocess.SubprocessError):
        pass
    return {"version": viotb.__version__, "git_commit": commit}


def _prepare_out_dir(out: Path, spec: SweepSpec, overwrite: bool) -> Path:
    """Create or resume the sweep folder (checked before any work)."""
    if out.exists() and not out.is_dir():
        raise FileExistsError(f"--out {out} exists and is not a folder")
    if out.is_dir() and any(out.iterdir()):
        if overwrite:
            shutil.rmtree(out)
        elif not (out / MARKER).is_file():
            raise FileExistsError(f"--out {out} is not empty and not a sweep folder (use --overwrite)")
    (out / SHARDS).mkdir(parents=True, exist_ok=True)
    import yaml

    now = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
    marker = json.loads((out / MARKER).read_text()) if (out / MARKER).is_file() else {"created_utc": now}
    marker.update({"name": spec.name, "spec": spec.as_dict(), "last_start_utc": now})
    _write_json_atomic(out / MARKER, marker)
    tmp = out / "spec.yaml.tmp"
    tmp.write_text(yaml.safe_dump(spec.as_dict(), sort_keys=False))
    os.replace(tmp, out / "spec.yaml")
    return out


def _read_shards(folder: Path) -> dict[str, dict]:
    rows = {}
    for p in sorted(folder.glob("*.json")):
        try:
            row = json.loads(p.read_text())
        except (OSError, json.JSONDecodeError):
            continue  # a torn shard is recomputed
        rows[row["run_id"]] = row
    return rows


def _write_json_atomic(path: Path, data: dict) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(data, default=_json_default))
    os.replace(tmp, path)


def _json_default(value: Any) -> Any:
    if hasattr(value, "item"):
        return value.item()
    if hasattr(value, "tolist"):
        return value.tolist()
    return str(value)


def write_results(out: Path, runs: list[RunConfig], rows: dict[str, dict]) -> Path:
    """Write ``out/results.parquet``: the rows of ``runs`` that exist, in spec order (atomic replace).

    Columns: :data:`META_COLUMNS`, then ``config/*``, the metrics (sorted), and :data:`RUN_COLUMNS`. A
    column whose values Arrow cannot hold in one type is stored as JSON strings.
    """
    import pyarrow as pa
    import pyarrow.parquet as pq

    mine = [rows[c.run_id] for c in runs if c.run_id in rows]
    keys = {k for r in mine for k in r}
    config = sorted(k for k in keys if k.startswith("config/"))
    metrics = sorted(keys - set(config) - set(META_COLUMNS) - set(RUN_COLUMNS))
    columns = [*META_COLUMNS, *config, *metrics, *RUN_COLUMNS]
    arrays = {}
    for name in columns:
        values = [r.get(name) for r in mine]
        try:
            arrays[name] = pa.array(values)
        except (pa.ArrowInvalid, pa.ArrowTypeError, TypeError, OverflowError):
            arrays[name] = pa.array([None if v is None else json.dumps(v, default=str) for v in values])
    table = pa.table(arrays)
    tmp = out / (RESULTS + ".tmp")
    pq.write_table(table, tmp)
    os.replace(tmp, out / RESULTS)
    return out / RESULTS
