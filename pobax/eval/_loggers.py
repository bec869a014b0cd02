"""Optional experiment trackers: TensorBoard and Weights & Biases, one logical run per (hyperparameter set,
seed), fed at chunk boundaries from the same tidy metrics the run directory gets.

`make_loggers(("tensorboard", "wandb"), run_dir, cfg)` returns loggers with `log(df)` and `close()`. A tracker
that is not installed is a clear error naming the package to install; pobax never requires either.
"""

from pathlib import Path

import pandas as pd

SCALARS = ("return", "disc_return", "ep_length", "pg_loss", "v_loss", "entropy", "approx_kl", "clip_frac",
           "lr_now", "value_mean", "lambda_discrepancy", "steps_per_s")


#: Tracker name → (modules, any of which provides it; what to install when none does).
REQUIREMENTS = {
    "tensorboard": (("tensorboardX", "torch"), "TensorBoard logging needs `pip install tensorboardX` (or PyTorch)."),
    "wandb": (("wandb",), "Weights & Biases logging needs `pip install wandb` (and `wandb login`)."),
}


class TensorBoardLogger:
    """One event directory per run: `<run_dir>/tensorboard/set<h>-seed<s>`, step = env steps."""

    def __init__(self, root: Path):
        try:
            from tensorboardX import SummaryWriter  # noqa: PLC0415
        except ImportError:
            from torch.utils.tensorboard import SummaryWriter  # noqa: PLC0415  (check_available ran first)
        self._writer_cls, self.root, self.writers = SummaryWriter, Path(root), {}

    def log(self, df: pd.DataFrame) -> None:
        for (h, s), g in df.groupby(["hp_index", "seed"]):
            w = self.writers.get((h, s))
            if w is None:
                w = self.writers[(h, s)] = self._writer_cls(str(self.root / f"set{h}-seed{s}"))
            for _, row in g.iterrows():
                for k in SCALARS:
                    if k in row and pd.notna(row[k]):
                        w.add_scalar(k, float(row[k]), int(row["env_step"]))

    def close(self) -> None:
        for w in self.writers.values():
            w.close()


class WandbLogger:
    """One W&B run per (set, seed), grouped by the run directory's name."""

    def __init__(self, run_dir: Path, config: dict):
        import wandb  # noqa: PLC0415  (check_available ran first)

        self.wandb, self.group, self.config, self.runs = wandb, Path(run_dir).name, config, {}

    def log(self, df: pd.DataFrame) -> None:
        for (h, s), g in df.groupby(["hp_index", "seed"]):
            run = self.runs.get((h, s))
            if run is None:
                run = self.runs[(h, s)] = self.wandb.init(
                    group=self.group, name=f"{self.group}-set{h}-seed{s}", reinit="create_new",
                    config={**self.config, "hp_index": int(h), "seed_index": int(s)})
            for _, row in g.iterrows():
                run.log({k: float(row[k]) for k in SCALARS if k in row and pd.notna(row[k])},
                        step=int(row["env_step"]))

    def close(self) -> None:
        for run in self.runs.values():
            run.finish()


def check_available(names) -> None:
    """Fail before anything is written if a requested tracker is unknown or not installed."""
    import importlib.util  # noqa: PLC0415

    for name in names:
        if name not in REQUIREMENTS:
            raise ValueError(f"Unknown logger {name!r}: choose {' or '.join(REQUIREMENTS)}.")
        modules, message = REQUIREMENTS[name]
        if not any(importlib.util.find_spec(m) for m in modules):
            raise ImportError(message)


def make_loggers(names, run_dir: Path | None, config: dict) -> list:
    check_available(names)
    if "tensorboard" in names and run_dir is None:
        raise ValueError("TensorBoard logging writes into the run directory: it needs save=True.")
    make = {"tensorboard": lambda: TensorBoardLogger(Path(run_dir) / "tensorboard"),
            "wandb": lambda: WandbLogger(run_dir or Path("pobax"), config)}
    return [make[name]() for name in names]
