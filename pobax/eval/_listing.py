"""`pobax results`: the run directories under a directory, with their state."""

import math
import os
from pathlib import Path

from ._results import CheckpointError, RunDir, _is_run_config


def list_runs(root: str | os.PathLike) -> list[dict]:
    """Every run directory under `root` (a directory with config.json and metrics): its environment, agent, number of
    hyperparameter sets and seeds, state (finished / diverged: every seed / resumable / incomplete / damaged: a summary
    or checkpoint that does not read back) and, when finished, the final discounted return of its best set by AUC
    (mean and 95% CI over seeds; None where no episode ended in the final updates)."""
    rows = []
    for cfg_path in sorted(Path(root).rglob("config.json")):
        rd = RunDir(cfg_path.parent)
        if not _is_run_config(cfg_path):  # another program's config.json, or a damaged one
            continue
        record = rd.read_config()
        cfg = record["config"]
        row = {"path": str(rd.path), "env": cfg.get("env", "?"), "observability": cfg.get("observability", "?"),
               "agent": cfg.get("memory", "?") + ("+ld" if cfg.get("double_critic") else ""),
               "sets": len(record.get("hyperparameter_sets", [])), "seeds": int(cfg.get("num_seeds", 0)),
               "disc_return": None, "ci_low": None, "ci_high": None}
        if (rd.path / "summary.json").exists():
            try:
                s = rd.read_summary()
                best_set = s["sets"][s["best_by_auc"]]
                best, diverged = best_set["disc_return"], int(best_set.get("diverged", 0))
            except (CheckpointError, KeyError, IndexError, TypeError, ValueError):
                row["state"] = "damaged"  # summary.json unreadable: listed, not fatal for the other runs
            else:
                if isinstance(best["mean"], (int, float)) and math.isfinite(best["mean"]):
                    row.update(state="finished", disc_return=best["mean"], ci_low=best["ci_low"],
                               ci_high=best["ci_high"])
                elif diverged >= row["seeds"] > 0:  # every seed of its best set (so of every set) diverged
                    row["state"] = "diverged"
                else:  # finished, but no episode ended in the final updates (too few steps): no return to show
                    row["state"] = "finished"
        elif (rd.path / "checkpoint.json").exists():
            try:
                rd.checkpoint_bytes()  # what a resume checks first: the state's and the chunks' hashes
            except (CheckpointError, OSError):
                row["state"] = "damaged"
            else:
                row["state"] = "resumable"
        else:
            row["state"] = "incomplete"
        rows.append(row)
    return rows
