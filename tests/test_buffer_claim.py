"""The buffer claim on seed-paired runs and each run's buffer fill (deploy/studies/buffer_claim.py), on exported
runs made by hand."""

from __future__ import annotations

import pytest

from deploy.studies import buffer_claim, grid_claims, grid_report
from tests.test_grid_report import exported_run

BOOTSTRAP = grid_report.Bootstrap(replicates=200)
NEVER = {1000: 200, 2000: 300, 6000: 900}  # a curve that never reaches 1,000 steps


def cap_share(share_in_eighths: int) -> list[int]:
    """Eight test starts, this many reaching the cap (100): a chosen test CFR of share/8."""
    return [100] * share_in_eighths + [50] * (8 - share_in_eighths)


def paired_grid(top, small: dict, large: dict) -> list:
    """Runs at both buffers: (strategy, seed) -> eighths reaching the cap."""
    for capacity, shares in ((1000, small), (2000, large)):
        for (strategy, seed), share in shares.items():
            exported_run(top, strategy, seed, cap_share(share), capacity=capacity)
    return grid_report.read_runs([top])


def test_pairs_join_the_same_strategy_and_seed_across_the_buffers(tmp_path):
    runs = paired_grid(tmp_path, {("bmc", 0): 8, ("bmc", 1): 6, ("softmax", 0): 4},
                       {("bmc", 0): 4, ("bmc", 1): 5})  # softmax seed 0 has no 2,000 run
    pairs = buffer_claim.buffer_pairs(runs, buffer_claim.chosen_test_cfr)
    assert [(p.strategy, p.seed, p.small, p.large) for p in pairs] == [("bmc", 0, 1.0, 0.5), ("bmc", 1, 0.75, 0.625)]


def test_the_claim_and_its_exception_by_the_rule(tmp_path):
    small = {("bmc", 0): 8, ("bmc", 1): 7, ("bmc", 2): 6, ("softmax", 0): 8, ("softmax", 1): 8, ("softmax", 2): 8,
             ("vdbe", 0): 2, ("vdbe", 1): 3, ("vdbe", 2): 4}
    large = {("bmc", 0): 7, ("bmc", 1): 5, ("bmc", 2): 3, ("softmax", 0): 4, ("softmax", 1): 3, ("softmax", 2): 2,
             ("vdbe", 0): 5, ("vdbe", 1): 5, ("vdbe", 2): 5}
    runs = paired_grid(tmp_path, small, large)
    cfr = buffer_claim.buffer_pairs(runs, buffer_claim.chosen_test_cfr)
    drive = buffer_claim.buffer_pairs(runs, grid_report.updates_to_drive)
    main, exception, everything, drives = buffer_claim.claim_readings(cfr, drive, BOOTSTRAP, past=6051)
    # six pairs all 1,000 ahead, differences 1..6 eighths, all ranks positive: W+ = 21, exact p = 1/2^6
    assert (main.pairs, main.p_value, main.improvement, main.low) == (6, pytest.approx(1 / 64), 1.0, 1.0)
    assert main.reading == "supported"
    # VDBE 2,000 ahead in all three (differences 3, 2, 1 eighths): p = 1/8 at best, so a lean at most
    assert (exception.pairs, exception.p_value, exception.improvement) == (3, pytest.approx(1 / 8), 1.0)
    assert exception.reading == "a lean"
    # all nine: 1,000 ahead in six; ranks of |d| 1,2,3 tie across VDBE and BMC: W+ = 45 - 6 of VDBE's ranks
    assert everything.pairs == 9 and everything.improvement == pytest.approx(6 / 9)
    # every run drove at 2,000 updates: all ties, no evidence either way
    assert (drives.p_value, drives.improvement, drives.reading) == (1.0, 0.5, "can't tell")


def test_a_run_that_never_drove_ranks_past_every_budget(tmp_path):
    exported_run(tmp_path, "bmc", 0, cap_share(8), capacity=1000)
    exported_run(tmp_path, "bmc", 0, cap_share(8), capacity=2000, curve=NEVER)
    exported_run(tmp_path, "bmc", 1, cap_share(8), capacity=1000)
    exported_run(tmp_path, "bmc", 1, cap_share(8), capacity=2000, curve=NEVER)
    exported_run(tmp_path, "bmc", 2, cap_share(8), capacity=1000, curve=NEVER)
    exported_run(tmp_path, "bmc", 2, cap_share(8), capacity=2000)
    runs = grid_report.read_runs([tmp_path])
    drive = buffer_claim.buffer_pairs(runs, grid_report.updates_to_drive)
    assert [(p.small, p.large) for p in drive] == [(2000, None), (2000, None), (None, 2000)]
    reading = buffer_claim.paired_reading(drive, "drive", BOOTSTRAP, larger_better=False, past=6051)
    # 1,000 sooner in two pairs, later in one, all by 4,051 (tied ranks of 2): W+ = 4, P(W+ >= 4) = 4/8
    assert (reading.improvement, reading.p_value) == (pytest.approx(2 / 3), pytest.approx(0.5))
    lines = buffer_claim.buffer_lines(runs, grid_report.updates_to_drive, BOOTSTRAP)
    assert "| bmc | 0 | 100.0% | 100.0% | 2,000 | not reached |" in lines
    assert any("never drove, ranked past every budget (6,051 updates): 3." in line for line in lines)


def test_the_fill_of_each_run_from_its_own_counters(tmp_path):
    fill = {"held_random_steps": 10, "sampled_batches": 400, "sampled_steps": 1_000, "sampled_random_steps": 250,
            "full_at_env_steps": 90_000, "full_at_batches": 300, "sampled_steps_after_full": 200,
            "sampled_random_steps_after_full": 10}
    exported_run(tmp_path, "bmc", 0, cap_share(8), summary={"replay_episodes_total": 1_724, "replay_fill": fill})
    exported_run(tmp_path, "bmc", 0, cap_share(8), capacity=2000,
                 summary={"replay_episodes_total": 1_650, "replay_fill": {**fill, "full_at_env_steps": 0}})
    exported_run(tmp_path, "bmc", 1, cap_share(8), summary={"replay_episodes_total": 1_700})  # before the counters
    exported_run(tmp_path, "bmc", 2, cap_share(8), summary={"replay_episodes_total": "x",
                                                             "replay_fill": {**fill, "sampled_steps": "many"}})
    rows = {(r["run"]): r for r in map(buffer_claim.fill_row, grid_report.read_runs([tmp_path]))}
    full = rows["bmc-b1000-s0"]
    assert (full["full_at_env_steps"], full["full_at_batches"]) == (90_000, 300)
    assert (full["served_random_share"], full["served_random_share_after_full"]) == (0.25, 0.05)
    never = rows["bmc-b2000-s0"]
    assert (never["full_at_env_steps"], never["full_at_batches"], never["episodes_total"]) == (None, None, 1_650)
    assert not rows["bmc-b1000-s1"]["counted"]
    assert not rows["bmc-b1000-s2"]["counted"] and rows["bmc-b1000-s2"]["episodes_total"] is None  # malformed
    lines = buffer_claim.fill_lines(grid_report.read_runs([tmp_path]))
    assert "| bmc-b1000-s0 | 1,000 | 1,724 | 90,000; 300 | 25.0% (5.0%) | 400 |" in lines
    assert "| bmc-b2000-s0 | 2,000 | 1,650 | never | 25.0% (–) | 400 |" in lines
    assert any(line.startswith("| bmc-b1000-s1 | 1,000 | 1,700 | not counted") for line in lines)


def test_the_strategy_claims_are_read_per_buffer_and_pooled(tmp_path):
    small = {("bmc", seed): 8 for seed in range(3)} | {("constant", seed): 4 for seed in range(3)}
    large = {("bmc", seed): 4 for seed in range(3)} | {("constant", seed): 8 for seed in range(3)}
    runs = paired_grid(tmp_path, small, large)
    assert [label for label, _ in grid_claims.claim_cells(runs)] == [
        "At buffer 1,000", "At buffer 2,000", "Both buffers pooled (each group's runs at every buffer)"]
    first, _ = grid_claims.claim_readings(runs, BOOTSTRAP, ((2000, "paper"),))
    # at 2,000 BMC caps 4 starts of 8 and constant all 8: per start a tie (one half) or constant ahead
    assert first["improvement"] == pytest.approx((4 * 0.5 + 4 * 0.0) / 8)
    pooled, _ = grid_claims.claim_readings(runs, BOOTSTRAP, ((1000, "paper"), (2000, "paper")))
    # starts 4-7 pooled: BMC 1 in half its runs, constant 1 in the other half: 1/4 ahead + 1/2 tied x 1/2
    assert pooled["runs"] == "6 vs 6" and pooled["improvement"] == pytest.approx((4 * 0.5 + 4 * 0.5) / 8)


def test_the_report_adds_the_buffer_section_and_figures_only_with_runs_at_2000(tmp_path):
    paired_grid(tmp_path / "runs", {("bmc", 0): 8}, {("bmc", 0): 4})
    paths = grid_report.report_on([tmp_path / "runs"], tmp_path / "out", BOOTSTRAP)
    page = (tmp_path / "out" / "grid.md").read_text()
    assert "## The buffer: 1,000 against 2,000" in page and "![buffer pairs](buffer_pairs.png)" in page
    assert (tmp_path / "out" / "buffer_pairs.png") in paths and (tmp_path / "out" / "buffer_pairs.png").is_file()
    exported_run(tmp_path / "alone", "bmc", 0, cap_share(8))
    grid_report.report_on([tmp_path / "alone"], tmp_path / "out1", BOOTSTRAP)
    assert "## The buffer" not in (tmp_path / "out1" / "grid.md").read_text()
