"""The README's benchmark figures are the shipped records' (`results/benchmark.csv`, `results/protocol/benchmark.csv`),
as rounded for the page: a record retrained or merged without the README following fails here."""

import csv
import math
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
COLUMNS = ("floor", "gru", "ld", "trxl", "ceiling")  # the README table's agent columns, in order


def _records(path: Path) -> dict[tuple[str, str], dict]:
    with open(path, newline="") as f:
        return {(r["env"], r["agent"]): r for r in csv.DictReader(f)}


def _close(shown: str, value: float) -> bool:
    """`shown` is `value` rounded as the README rounds: to the decimals shown, or to three significant digits
    (1630 for 1629.4): within half a unit of the finer of the two."""
    decimals = len(shown.split(".")[1]) if "." in shown else 0
    third_digit = 10.0 ** (math.floor(math.log10(abs(value))) - 2) if value else 0.0
    return abs(float(shown) - value) <= max(0.5 * 10.0 ** -decimals, 0.5 * third_digit) + 1e-9


def _steps(text: str) -> int:
    number, unit = re.fullmatch(r"([\d.]+)([MK]?)", text).groups()
    return round(float(number) * {"M": 1e6, "K": 1e3, "": 1}[unit])


def _table() -> list[list[str]]:
    rows = [line.strip("|").split("|") for line in (ROOT / "README.md").read_text().splitlines()
            if line.startswith("| ") and " × " in line]
    return [[c.strip() for c in row] for row in rows if row[0].strip() != "environment"]


def test_the_readme_table_is_the_registry_records():
    records, rows = _records(ROOT / "results" / "benchmark.csv"), _table()
    assert len(rows) >= 14  # every environment of the suite
    for env, metric, budget, *values, verdict in rows:
        steps, seeds = budget.split(" × ")
        key = {"discounted": "disc_mean", "undiscounted": "undisc_mean"}[metric]
        for agent, shown in zip(COLUMNS, values, strict=True):
            r = records[(env, agent)]
            assert _close(shown, float(r[key])), (env, agent, shown, r[key])
            assert int(r["total_steps"]) == _steps(steps) and int(r["num_seeds"]) == int(seeds), (env, agent)
        if int(seeds) < 5:
            assert verdict.startswith("not judged"), env


def test_the_readme_protocol_figures_are_the_protocol_records():
    """Every protocol record of T-Maze 10 and RockSample 11 (discounted) and Battleship 10 (undiscounted) is shown in
    the README's protocol paragraph, in its environment's sentence, with its record's value and its interval where
    one is printed."""
    records = _records(ROOT / "results" / "protocol" / "benchmark.csv")
    text = " ".join((ROOT / "README.md").read_text().split())
    start = text.index("**The paper's protocol**")
    para = text[start:text.index("```", start)]
    markers = {"tmaze_10": ("T-Maze 10", "disc"), "battleship_10": ("Battleship:", "undisc"),
               "rocksample_11_11": ("RockSample 11:", "disc")}
    starts = sorted((para.index(marker), env) for env, (marker, _) in markers.items())
    names = {"floor": "floor", "gru": "GRU", "ld": r"λ-disc\.", "trxl": "Transformer-XL",
             "ceiling": r"(?<!`perfect_memory` )ceiling",
             "ceiling_pobax": r"pobax's memoryless `perfect_memory` ceiling"}
    for i, (at, env) in enumerate(starts):
        segment = para[at:starts[i + 1][0] if i + 1 < len(starts) else None]
        metric = markers[env][1]
        shown = [agent for (e, agent) in records if e == env]
        assert (env != "tmaze_10" or len(shown) == 5) and shown, (env, shown)
        for agent in shown:
            r = records[(env, agent)]
            with_ci = re.search(names[agent] + r" ([\d.]+) \[([\d.]+), ([\d.]+)\]", segment)
            if with_ci:
                mean, low, high = with_ci.groups()
                assert all(_close(v, float(r[f"{metric}_{k}"])) for v, k in ((mean, "mean"), (low, "ci_low"),
                                                                            (high, "ci_high"))), (env, agent, mean)
            else:
                value = re.search(names[agent] + r" ([\d.]+)", segment)
                assert value and _close(value.group(1), float(r[f"{metric}_mean"])), (env, agent, "not shown")


@pytest.mark.parametrize("shown,value,ok", [("1.50", 1.49779, True), ("-0.80", -0.796924, True),
                                            ("1630", 1629.4, True), ("1.52", 1.49779, False),
                                            ("0.072", 0.081, False), ("7.48", 7.47233, False),
                                            ("7.47", 7.47233, True), ("1640", 1629.4, False)])
def test_the_rounding_rule_accepts_rounding_alone(shown, value, ok):
    assert _close(shown, value) is ok
