"""benchmarks/bench_memory.py's parameter counts: the networks the benchmark trains, with `--set` overrides applied.
The deviation table's Transformer-XL embedding row rests on them."""

import importlib.util
from pathlib import Path

import pytest

_spec = importlib.util.spec_from_file_location(
    "bench_memory", Path(__file__).parent.parent / "benchmarks" / "bench_memory.py")
bench_memory = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(bench_memory)


def params(env: str, agent: str, **overrides) -> dict:
    return bench_memory.measure(env, agent, "reduced", overrides=overrides or None, params_only=True)


def test_counts_follow_the_configuration():
    gru, trxl = params("rocksample_11_11", "gru"), params("rocksample_11_11", "trxl")
    assert (gru["memory"], gru["hidden_size"], trxl["memory"], trxl["embed_size"]) == ("gru", 256, "trxl", 96)
    assert 0 < gru["memory_parameters"] < gru["parameters"]
    wider = params("rocksample_11_11", "trxl", embed_size=256)
    assert wider["embed_size"] == 256 and wider["parameters"] > 4 * trxl["parameters"]
    assert "argument_bytes" not in trxl  # --params-only compiles nothing


@pytest.mark.parametrize("env, size, matched", [("rocksample_11_11", 96, 0.02), ("rocksample_15_15", 220, 0.05)])
def test_registry_embedding_matches_the_gru_on_rocksample(env, size, matched):
    """The paper's rule ("to match the total number of parameters in recurrent PPO") holds for RockSample's sizes."""
    gru, trxl = params(env, "gru"), params(env, "trxl")
    assert trxl["embed_size"] == size
    assert abs(trxl["parameters"] / gru["parameters"] - 1) < matched


def test_battleship_embedding_256_matches_the_gru_better_than_220():
    gru = params("battleship_10", "gru")["parameters"]
    at_220, at_256 = params("battleship_10", "trxl")["parameters"], params("battleship_10", "trxl", embed_size=256)[
        "parameters"]
    assert abs(at_256 / gru - 1) < 0.05 < abs(at_220 / gru - 1)
    assert set(params("battleship_10", "gru")["observation"]) == {"obs", "action_mask"}  # a dictionary space
