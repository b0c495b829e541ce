"""One run's files on disk (CSV, JSON, YAML, a heatmap PNG) and the summary printed at the end.

Comparisons across methods and seeds are `harness/report/`, rebuilt from MLflow."""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path

import numpy as np
import yaml

from harness.common.atomic import write_text
from harness.config.benchmark import BenchConfig
from harness.track import figures


def success_matrix_csv(tasks: list[str], stage_tasks: list[str], R: np.ndarray) -> str:
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(["stage", "trained_on", *tasks])
    for i, row in enumerate(R):
        writer.writerow([i, stage_tasks[i], *[f"{v:.4f}" for v in row]])
    return buf.getvalue()


def rows_csv(rows: list[dict]) -> str:
    buf = io.StringIO()
    if rows:
        writer = csv.DictWriter(buf, fieldnames=list(rows[0]), lineterminator="\n")
        writer.writeheader()
        writer.writerows(rows)
    return buf.getvalue()


def sparsity_progress_csv(stages) -> str:
    """The paper's Eq. 8 per layer during training (its figure 1): one row per stage, step done
    in that stage and layer; header only when no stage measured it (stage 0 never does)."""
    rows = [{"stage": s.stage, "step": step, "layer": layer, "eq8": f"{values[i]:.6g}"}
            for s in stages for i, step in enumerate(s.sparsity_steps)
            for layer, values in s.sparsity_layers.items()]
    return rows_csv(rows) or "stage,step,layer,eq8\n"


def write_run_outputs(cfg: BenchConfig, result, provenance: dict) -> dict[str, Path]:
    """Write a run's files atomically; returns name -> path."""
    out = result.run_dir
    R = result.success_matrix()
    stage_tasks = [s.task for s in result.stages]
    paths = {
        "success_matrix": out / "success_matrix.csv",
        "metrics": out / "metrics.json",
        "config": out / "config.yaml",
        "heatmap": out / "success_matrix.png",
        "heldout_loss": out / "heldout_loss.csv",
        "updates_per_layer": out / "updates_per_layer.csv",
        "sparsity_progress": out / "sparsity_progress.csv",
    }
    write_text(paths["success_matrix"], success_matrix_csv(result.tasks, stage_tasks, R))
    write_text(paths["heldout_loss"], success_matrix_csv(result.tasks, stage_tasks,
                                                         result.heldout_matrix()))
    write_text(paths["updates_per_layer"], rows_csv(result.layer_rows))
    write_text(paths["sparsity_progress"], sparsity_progress_csv(result.stages))
    S, spatial_path = result.spatial_success_matrix(), out / "spatial_success_matrix.csv"
    if S is not None:  # the spatial probe's, when it is on
        paths["spatial_success_matrix"] = spatial_path
        write_text(spatial_path, success_matrix_csv(result.tasks, stage_tasks, S))
    else:  # an earlier run's with the probe on would not describe this one
        spatial_path.unlink(missing_ok=True)
    stages = [{"stage": s.stage, "trained_on": s.task, "train_loss": s.train_loss,
               "updates": s.updates, "updates_stage_over_stage": s.updates_stage,
               "curve_steps": s.curve_steps, "curve": s.curve, "steps_used": s.steps_used,
               "check_steps": s.check_steps, "check_success": s.check_success,
               "sparsity_steps": s.sparsity_steps, "sparsity": s.sparsity} for s in result.stages]
    write_text(paths["metrics"], json.dumps({"method": result.method, "seed": result.seed,
                                              "metrics": result.metrics, "stages": stages},
                                             indent=2, sort_keys=True, default=float) + "\n")
    write_text(paths["config"], yaml.safe_dump({**provenance, "config": cfg.as_dict()}, sort_keys=True))
    figures.success_matrix(paths["heatmap"], R, result.tasks, stage_tasks, len(cfg.foundation_tasks),
                           f"{cfg.name}: {result.method}, seed {result.seed}")
    return paths


HEADLINE = ["foundation_success_stage0", "retention", "retention_drop", "plasticity",
            "stream_final_success", "forgetting", "bwt", "heldout_loss_ratio",
            "update_frac_changed_rho0.01", "update_relative_l2"]

SPATIAL_HEADLINE = ["spatial_foundation_success_stage0", "spatial_retention", "spatial_plasticity"]


def summary_table(results) -> str:
    """Markdown table: one row per (method, seed), the headline metrics as columns."""
    columns = HEADLINE + [k for k in SPATIAL_HEADLINE if any(k in r.metrics for r in results)]
    header = "| method | seed | " + " | ".join(columns) + " |"
    lines = [header, "|" + "---|" * (len(columns) + 2)]
    for r in results:
        cells = [f"{r.metrics.get(k, float('nan')):.3f}" for k in columns]
        lines.append(f"| {r.method} | {r.seed} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"
