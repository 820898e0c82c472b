"""deploy/tools/failure_sites.py: an evaluation's failures pooled by what they hit, read from its episodes.csv, or
replayed for an older one and checked against its recorded actions."""

from __future__ import annotations

import csv

from actor.evaluation.command import main as evaluate
from common.analysis.stats import SITE_FIELDS
from common.analysis.tables import EPISODES_CSV
from deploy.tools import failure_sites
from tests.test_evaluation import make_checkpoint


def rewrite(path, change):
    with path.open(newline="") as handle:
        rows = list(csv.DictReader(handle))
    rows = [change(dict(row)) for row in rows]
    with path.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


def test_sites_are_read_from_an_evaluation_or_replayed_for_an_older_one(tmp_path, capsys):
    run_dir = make_checkpoint(tmp_path / "runs")  # an untrained network: its greedy episodes fail within 60 steps
    evaluate(["--checkpoint", str(run_dir)])
    evaluation = run_dir / "evaluation"
    capsys.readouterr()
    assert failure_sites.main([str(evaluation)]) == 0
    table = capsys.readouterr().out
    assert table.startswith("What the greedy policy hit") and "| Where |" in table

    rewrite(evaluation / EPISODES_CSV, lambda row: {key: value for key, value in row.items()
                                                    if key not in SITE_FIELDS})  # as an older evaluate wrote it
    assert failure_sites.main([str(evaluation)]) == 1
    assert "no end poses" in capsys.readouterr().err
    assert failure_sites.main([str(evaluation), "--policy", str(run_dir), "--write", "--start-set", "test"]) == 0
    assert failure_sites.main([str(evaluation), "--policy", str(run_dir), "--write", "--start-set", "train"]) == 0
    capsys.readouterr()
    assert failure_sites.main([str(evaluation)]) == 0  # --write kept both sets' places: no policy needed now
    assert capsys.readouterr().out == table  # and the replays found the places the evaluation recorded
    rewrite(evaluation / EPISODES_CSV, lambda row: {key: value for key, value in row.items()
                                                    if key not in SITE_FIELDS})

    first_failed = {}

    def damage(row):  # another action sequence recorded for the first failed greedy episode
        if row["policy"] == "greedy" and row["end"] != "cap" and not first_failed:
            first_failed.update(row)
            row["actions_digest"] = "0" * 16
        return row

    rewrite(evaluation / EPISODES_CSV, damage)
    assert failure_sites.main([str(evaluation), "--policy", str(run_dir)]) == 1
    assert "the replay took other actions" in capsys.readouterr().err
