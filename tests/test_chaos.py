"""The chaos run, short: a small stack trains for a minute while its actor, learner, recorder and replay are
SIGKILLed in turn every 8-12 s (deploy/labs/chaos.py --cycle). Afterwards every process runs again, each killed
replay restored what its snapshot promised, the closed run's ratio is within the buffer, and every flight-log
segment reads to its end. The long version (30 minutes, random kills 1-3 minutes apart) is the benchmark
`deploy/labs/chaos.py --minutes 30`."""

import json
import subprocess
import sys
from pathlib import Path

from tests.stack_run import SMALL

CHAOS = Path(__file__).resolve().parents[1] / "deploy" / "labs" / "chaos.py"


def test_a_stack_whose_processes_are_killed_in_turn_keeps_its_promises(tmp_path):
    flags = ["--minutes", "1", "--kill-every", "8", "12", "--cycle", "--settle-s", "60", "--soak-every", "5",
             "--close-timeout-s", "180", *SMALL, "--replay.snapshot_period_s", "2", "--learner.checkpoint_every", "20",
             "--run.runs_dir", str(tmp_path / "runs"), "--run.name", "chaos", "--actors", "1"]
    chaos = subprocess.Popen([sys.executable, str(CHAOS), *flags], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                             text=True)
    try:
        out, err = chaos.communicate(timeout=480)
    finally:
        if chaos.poll() is None:  # SIGTERM: it stops the stack it started, then exits
            chaos.terminate()
            chaos.communicate(timeout=150)
    report_path = tmp_path / "runs" / "chaos" / "chaos" / "report.json"
    assert report_path.exists(), out[-3000:] + err[-3000:]
    report = json.loads(report_path.read_text())
    print(json.dumps(report, indent=1))
    assert report["checks"] == {"alive": True, "snapshot": True, "closed": True, "ratio": True, "log": True}, report
    assert chaos.returncode == 0
    killed = {kill["process"] for kill in report["kills"]}
    assert {"actor-0", "learner", "recorder", "replay"} <= killed
    assert all(kill["replaced_after_s"] is not None for kill in report["kills"])
    assert len(report["facts"]["log_segments"]) >= 2  # the killed recorder's segment and its successor's
    assert (tmp_path / "runs" / "chaos" / "soak" / "soak.png").exists()
