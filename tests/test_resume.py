"""Checkpoint/resume: an interrupted run continues to the same metrics, bit for bit; bad resumes fail clearly."""

import dataclasses

import numpy as np
import pandas as pd
import pytest

from pobax.agent import TrainConfig, train
from pobax.agent._train import CheckpointError

CFG = TrainConfig(env="tmaze_5", memory="gru", hidden_size=8, num_envs=4, num_steps=16, num_minibatches=2,
                  total_steps=4 * 16 * 6, num_seeds=2, lr=(2.5e-3, 2.5e-4), num_chunks=3, normalize_obs=True)


def _comparable(m: pd.DataFrame) -> pd.DataFrame:
    # chunks read back from CSV are float64 holding the float32 values written: compare in float32
    m = m.drop(columns=["steps_per_s"]).reset_index(drop=True)
    return m.astype({c: np.float32 for c in m.columns if m[c].dtype.kind == "f"})


def test_resume_is_bit_exact(tmp_path):
    full = train(CFG, tmp_path / "full", progress=False)
    part = train(CFG, tmp_path / "split", progress=False, max_chunks=1)
    assert not part.summary["finished"]
    assert (tmp_path / "split" / "checkpoint.eqx").exists()
    assert not (tmp_path / "split" / "summary.json").exists()
    part = train(CFG, tmp_path / "split", progress=False, resume=True, max_chunks=1)  # a second interruption
    resumed = train(CFG, tmp_path / "split", progress=False, resume=True)
    assert resumed.summary["finished"]
    pd.testing.assert_frame_equal(_comparable(full.metrics), _comparable(resumed.metrics), check_exact=True)
    for a, b in zip(np.asarray(full.state.model.actor.out.weight), np.asarray(resumed.state.model.actor.out.weight)):
        np.testing.assert_array_equal(a, b)
    # the files on disk are identical, digit for digit (but for the timing column)
    def text(run):
        return pd.read_csv(tmp_path / run / "metrics.csv", dtype=str).drop(columns=["steps_per_s"])
    pd.testing.assert_frame_equal(text("split"), text("full"))
    assert not (tmp_path / "split" / "checkpoint.eqx").exists()  # finished runs keep their results, not the state


def test_bad_resumes_fail_clearly_and_keep_files(tmp_path):
    with pytest.raises(CheckpointError, match="not a run directory"):
        train(CFG, tmp_path / "nothing", progress=False, resume=True)
    train(CFG, tmp_path / "run", progress=False, max_chunks=1)
    before = sorted(p.name for p in (tmp_path / "run").rglob("*"))
    other = dataclasses.replace(CFG, hidden_size=16)
    with pytest.raises(CheckpointError, match="hidden_size"):
        train(other, tmp_path / "run", progress=False, resume=True)
    ckpt = tmp_path / "run" / "checkpoint.eqx"
    data = ckpt.read_bytes()
    ckpt.write_bytes(data[: len(data) // 2])
    with pytest.raises(CheckpointError, match="corrupted"):
        train(CFG, tmp_path / "run", progress=False, resume=True)
    assert sorted(p.name for p in (tmp_path / "run").rglob("*")) == before
    assert ckpt.read_bytes() == data[: len(data) // 2]  # nothing was overwritten
