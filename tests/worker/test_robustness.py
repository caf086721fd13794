"""A small run of bench/robustness.py in CI (issue 14, build 5): two instrument variants at a
tiny size, each reconstructed by the default and the plain chain in a child process
(`python -m worker.reconstruct`), as the bench does.

Asserted: both chains complete (exit 0) and write no height outside the range the ground
truth allows, the true heights' range on the tablet widened by 50 µm (`evaluate`'s
`height_out_of_range`, over every output pixel, not only the core). The variants: the
paper-like rig (projector pixels and defocus, light inside the clay, 10-bit) and a broken
tablet (chips, the cliffs where the default's wall refinement wrote centimetre needles).
Random draws with a V-block or cloth support are left to the bench: both chains take part
of the support for tablet at 96×72, whose true heights the ground truth does not give.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

_BENCH = Path(__file__).resolve().parents[2] / "bench" / "robustness.py"


@pytest.fixture(scope="module")
def robustness():
    spec = importlib.util.spec_from_file_location("bench_robustness", _BENCH)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up there
    try:
        spec.loader.exec_module(module)
        yield module
    finally:
        sys.modules.pop(spec.name, None)


VARIANTS = [
    ("paper-like", ("--physics", "paper-like", "--size", "96x72", "--seed", "2")),
    ("broken", ("--physics", "broken", "--size", "96x72", "--seed", "4")),
]


@pytest.mark.parametrize(("name", "args"), VARIANTS, ids=[v[0] for v in VARIANTS])
def test_both_chains_complete_without_heights_out_of_range(robustness, tmp_path, name, args):
    scan = robustness.Scan(f"ci-{name}", "native", args)
    result = robustness.run_scan(scan, tmp_path, ["default", "plain"], sys.executable)
    assert result.error is None
    for chain in ("default", "plain"):
        entry = result.chains[chain]
        assert entry["exit"] == 0, (chain, entry.get("message"))
        assert entry["height_out_of_range"] == 0, chain
        assert entry["coverage"] > 0.5, chain  # a model of the tablet, not a speck
    summ = robustness.summary([result], ["default", "plain"])
    assert summ["chains"]["plain"]["completed"] == 1
    assert set(summ["default_worse_than_plain"]) == set(robustness.COMPARED)
    table = robustness.scan_table([result], ["default", "plain"])
    assert table.count(f"ci-{name}") == 1 and "| plain |" in table


def test_bench_lists_enough_scans(robustness):
    scans = robustness.SCANS
    assert len(scans) >= 24 and len({s.name for s in scans}) == len(scans)
    assert sum(s.quick for s in scans) == 6
    assert {s.instrument for s in scans} == {"native", "mitsuba"}
    assert any("paper-like" in s.args and "paper" in s.args for s in scans)


def test_summary_counts_the_scans_where_the_default_is_worse(robustness):
    def result(name, default, plain):
        r = robustness.Result(robustness.Scan(name, "native", ()))
        r.chains = {"default": {"exit": 0, **default}, "plain": {"exit": 0, **plain}}
        return r

    results = [
        # 5 % worse: within the slack; coverage 0.80 vs 0.95: worse.
        result(
            "a", {"height_mae_um": 1.05, "coverage": 0.80}, {"height_mae_um": 1.0, "coverage": 0.95}
        ),
        # 20 % worse on MAE.
        result(
            "b", {"height_mae_um": 1.2, "coverage": 1.0}, {"height_mae_um": 1.0, "coverage": 1.0}
        ),
        # A default that fails where plain completes is worse on every metric.
        result("c", {}, {"height_mae_um": 1.0}),
    ]
    results[2].chains["default"]["exit"] = 2
    summ = robustness.summary(results, ["default", "plain"])
    worse = summ["default_worse_than_plain"]
    assert worse["height_mae_um"] == ["b", "c"]
    assert worse["coverage"] == ["a", "c"]
    assert summ["chains"]["default"]["completed"] == 2
    assert summ["chains"]["plain"]["height_mae_um"] == {"median": 1.0, "worst": 1.0}
    assert summ["chains"]["default"]["coverage"]["worst"] == 0.80
