"""The notebook-style examples (examples/NN_*.py) run, at their tiny size (`POBAX_EXAMPLE_TINY=1`), as a user would
run them. (Other scripts in examples/ have their own tests.)"""

import os
import subprocess
import sys
from pathlib import Path

import pytest

EXAMPLES = sorted((Path(__file__).resolve().parents[1] / "examples").glob("[0-9][0-9]_*.py"))


def test_there_are_examples():
    assert [p.name for p in EXAMPLES] == ["01_environments.py", "02_train_and_plot.py", "03_evaluate_and_render.py"]


@pytest.mark.parametrize("script", EXAMPLES, ids=[p.name for p in EXAMPLES])
def test_example_runs(script, tmp_path):
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "POBAX_EXAMPLE_TINY": "1", "POBAX_EXAMPLE_OUT": str(tmp_path / "out")}
    proc = subprocess.run([sys.executable, str(script)], cwd=tmp_path, env=env, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    written = list((tmp_path / "out").rglob("*"))
    assert written, "the example wrote nothing"
    assert not (tmp_path / "runs").exists()  # everything went where POBAX_EXAMPLE_OUT said
    for gif in [p for p in written if p.suffix == ".gif"]:
        assert gif.with_suffix(".png").exists() and gif.stat().st_size > 1000
