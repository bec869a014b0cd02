"""examples/custom_memory.py runs as a user runs it: `python examples/custom_memory.py`, in a fresh process."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_custom_memory_example_checks_its_cell_and_runs_the_tmaze_gap(tmp_path):
    script = ROOT / "examples" / "custom_memory.py"
    assert len(script.read_text().splitlines()) < 60
    proc = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, cwd=tmp_path, timeout=300,
                          env={"JAX_PLATFORMS": "cpu", "PATH": "", "POBAX_EXAMPLE_TINY": "1",
                               "POBAX_EXAMPLE_OUT": str(tmp_path / "out")})
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "DecayingTrace satisfies the memory contract" in proc.stdout
    assert "Memory-improvability gap on tmaze_5" in proc.stdout
    gap = tmp_path / "out" / "custom_memory-gap"
    report = json.loads((gap / "gap.json").read_text())
    assert [a["name"] for a in report["agents"]] == ["floor", "custom_memory:DecayingTrace", "ceiling"]
    run = gap / "custom_memory:DecayingTrace"
    config = json.loads((run / "config.json").read_text())["config"]
    assert config["memory"] == "custom_memory:DecayingTrace" and config["total_steps"] == 192
    assert (run / "model.eqx").stat().st_size > 0
