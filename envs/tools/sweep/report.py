"""Report of a sweep folder (``viotb sweep-report``): distribution plots and a table of percentiles.

A *configuration* is the set of runs that differ only by seed (``config_id``); its label names the axes
that vary across the sweep (``estimator=msckf imu=bmi088``). Written into ``DIR/report/``:

- ``ate.png``, ``drift.png``: ATE (4-DOF aligned) and drift per configuration over seeds (box + points);
- ``nees.png``: position NEES averaged over the N seeds of each configuration against its chi-square 95 %
  band: each run's ``nees_pos_mean`` is a position NEES of dof 3, so N of them averaged lie, for a consistent
  estimator, in ``[chi2.ppf(0.025, 3N), chi2.ppf(0.975, 3N)] / N``;
- ``timing.png``: ms per frame (median of each run) and wall time per run;
- ``summary.csv`` and ``summary.md``: per configuration and metric, n, mean, median, p5, p25, p75, p95.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

METRICS = (
    "ate_posyaw_m",
    "drift_pct",
    "nees_pos_mean",
    "rpe_1m_pct",
    "scale_error_pct",
    "hover_rms_m",
    "max_err_m",
    "ms_per_frame_median",
    "ms_per_frame_p99",
    "wall_s",
)
"""Metrics summarized when the table has them (record-eval and fly runs have different ones)."""
PERCENTILES = (5, 25, 50, 75, 95)


def sweep_report(sweep_dir: Path | str, report_dir: Path | str | None = None) -> dict:
    """Write the plots and tables of a sweep folder and return the summary.

    Args:
        sweep_dir: A sweep folder (holding ``results.parquet``).
        report_dir: Where to write (default ``sweep_dir/report``).

    Returns:
        Strict-JSON dict: ``results``, ``rows``, ``failed``, ``configs`` (per configuration: label,
        ``runs``, ``failed``, per-metric stats, NEES band and whether the mean lies in it), ``plots``,
        ``tables``.

    Raises:
        FileNotFoundError: No ``results.parquet`` in ``sweep_dir``.
    """
    import matplotlib

    matplotlib.use("Agg")
    import pandas as pd

    src = Path(sweep_dir) / "results.parquet"
    if not src.is_file():
        raise FileNotFoundError(f"{src} not found (run `viotb sweep SPEC --out {sweep_dir}` first)")
    df = pd.read_parquet(src)
    out = Path(report_dir) if report_dir is not None else Path(sweep_dir) / "report"
    out.mkdir(parents=True, exist_ok=True)
    df["label"] = _labels(df)
    ok = df[df["status"] == "ok"]
    metrics = [m for m in METRICS if m in ok.columns and pd.api.types.is_numeric_dtype(ok[m])]
    configs = []
    for label, group in df.groupby("label", sort=False):
        good = group[group["status"] == "ok"]
        entry: dict[str, Any] = {
            "label": label,
            "config_id": str(group["config_id"].iloc[0]),
            "runs": int(len(group)),
            "failed": int((group["status"] != "ok").sum()),
        }
        entry["stats"] = {m: _stats(good[m]) for m in metrics}
        if "nees_pos_mean" in metrics:
            entry["nees"] = nees_band(good["nees_pos_mean"].to_numpy(dtype=float))
        configs.append(entry)
    plots = _plots(ok, metrics, configs, out)
    tables = _tables(configs, metrics, out)
    return _strict(
        {
            "results": str(src),
            "rows": int(len(df)),
            "failed": int((df["status"] != "ok").sum()),
            "configs": configs,
            "plots": [str(p) for p in plots],
            "tables": [str(p) for p in tables],
        }
    )


def nees_band(nees_per_run) -> dict:
    """Mean position NEES over N runs and the chi-square 95 % band of that mean (dof 3 per run).

    Args:
        nees_per_run: Position NEES (dof 3) of each run; NaNs are left out.

    Returns:
        ``{"n", "anees", "low", "high", "inside"}`` (None where there is no finite value).
    """
    import numpy as np
    from scipy.stats import chi2

    x = np.asarray(nees_per_run, dtype=float)
    x = x[np.isfinite(x)]
    n = int(x.size)
    if n == 0:
        return {"n": 0, "anees": None, "low": None, "high": None, "inside": None}
    low, high = (float(chi2.ppf(q, 3 * n) / n) for q in (0.025, 0.975))
    anees = float(x.mean())
    return {"n": n, "anees": anees, "low": low, "high": high, "inside": bool(low <= anees <= high)}


def _labels(df) -> list[str]:
    """Label per row from the ``config/*`` columns that vary (the configuration id when none varies)."""
    cols = [c for c in df.columns if c.startswith("config/")]
    varying = [c for c in cols if df[c].astype(str).nunique() > 1]
    if not varying:
        return [
            str(df["config/scenario"].iloc[i]) if "config/scenario" in df else "all" for i in range(len(df))
        ]
    return [" ".join(f"{c[len('config/') :]}={df[c].iloc[i]}" for c in varying) for i in range(len(df))]


def _stats(series) -> dict:
    import numpy as np

    x = series.to_numpy(dtype=float)
    x = x[np.isfinite(x)]
    if x.size == 0:
        return {"n": 0}
    out = {"n": int(x.size), "mean": float(x.mean())}
    out.update({f"p{q}": float(np.percentile(x, q)) for q in PERCENTILES})
    return out


def _plots(ok, metrics: list[str], configs: list[dict], out: Path) -> list[Path]:
    import matplotlib.pyplot as plt
    import numpy as np

    labels = [c["label"] for c in configs]
    written = []

    def box(ax, metric: str, title: str) -> None:
        data = [ok.loc[ok["label"] == lab, metric].to_numpy(dtype=float) for lab in labels]
        data = [d[np.isfinite(d)] for d in data]
        ax.boxplot([d if d.size else [np.nan] for d in data], showfliers=False)
        for i, d in enumerate(data, start=1):
            ax.plot(np.full(d.size, i) + np.linspace(-0.1, 0.1, d.size), d, ".", alpha=0.5, color="C1")
        ax.set_xticks(range(1, len(labels) + 1), labels, rotation=30, ha="right", fontsize=8)
        ax.set_title(title)
        ax.grid(alpha=0.3)

    for metric, name, title in (
        ("ate_posyaw_m", "ate.png", "ATE (4-DOF aligned) [m] over seeds"),
        ("drift_pct", "drift.png", "drift [% of path] over seeds"),
    ):
        if metric in metrics:
            fig, ax = plt.subplots(figsize=(max(6, 1.2 * len(labels)), 4.5), constrained_layout=True)
            box(ax, metric, title)
            written.append(_save(fig, out / name))
    if "nees_pos_mean" in metrics:
        fig, ax = plt.subplots(figsize=(max(6, 1.2 * len(labels)), 4.5), constrained_layout=True)
        for i, c in enumerate(configs, start=1):
            band = c.get("nees", {})
            if band.get("n"):
                ax.fill_between(
                    [i - 0.3, i + 0.3],
                    band["low"],
                    band["high"],
                    color="C2",
                    alpha=0.3,
                    label="chi2 95 % band of the mean" if i == 1 else None,
                )
                ax.plot(i, band["anees"], "o", color="C0" if band["inside"] else "C3")
            runs = ok.loc[ok["label"] == c["label"], "nees_pos_mean"].to_numpy(dtype=float)
            ax.plot(
                np.full(runs.size, i) + np.linspace(-0.2, 0.2, runs.size), runs, ".", color="0.5", alpha=0.4
            )
        ax.axhline(3.0, color="k", lw=0.8, ls="--", label="expected (dof 3)")
        ax.set_xticks(range(1, len(labels) + 1), labels, rotation=30, ha="right", fontsize=8)
        ax.set_yscale("log")
        ax.set_title("position NEES: runs (grey), mean over seeds (dot), 95 % band")
        ax.legend(fontsize=8)
        written.append(_save(fig, out / "nees.png"))
    timing = [m for m in ("ms_per_frame_median", "wall_s") if m in metrics]
    if timing:
        fig, axes = plt.subplots(
            1,
            len(timing),
            figsize=(max(6, 1.2 * len(labels)) * len(timing), 4.5),
            constrained_layout=True,
            squeeze=False,
        )
        for ax, metric in zip(axes[0], timing, strict=True):
            box(
                ax,
                metric,
                {"ms_per_frame_median": "ms per frame (median of a run)", "wall_s": "wall time per run [s]"}[
                    metric
                ],
            )
        written.append(_save(fig, out / "timing.png"))
    return written


def _save(fig, path: Path) -> Path:
    import matplotlib.pyplot as plt

    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _tables(configs: list[dict], metrics: list[str], out: Path) -> list[Path]:
    head = ["config", "metric", "n", "mean", *(f"p{q}" for q in PERCENTILES)]
    lines = [",".join(head)]
    md = ["| " + " | ".join(head) + " |", "|" + " --- |" * len(head)]
    for c in configs:
        for m in metrics:
            s = c["stats"][m]
            vals = [s.get(k) for k in ("mean", *(f"p{q}" for q in PERCENTILES))]
            cells = [c["label"], m, str(s["n"]), *("" if v is None else f"{v:.6g}" for v in vals)]
            lines.append(",".join(json.dumps(x) if "," in x or '"' in x else x for x in cells))
            md.append("| " + " | ".join(cells) + " |")
        if c.get("nees", {}).get("n"):
            b = c["nees"]
            md.append(
                f"| {c['label']} | ANEES over {b['n']} seeds: {b['anees']:.3g} in [{b['low']:.3g}, "
                f"{b['high']:.3g}]: {'yes' if b['inside'] else 'NO'} |" + " |" * (len(head) - 2)
            )
    (out / "summary.csv").write_text("\n".join(lines) + "\n")
    (out / "summary.md").write_text("\n".join(md) + "\n")
    return [out / "summary.csv", out / "summary.md"]


def _strict(value: Any) -> Any:
    """NaN and infinities to None, recursively (strict JSON)."""
    if isinstance(value, dict):
        return {k: _strict(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_strict(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value
