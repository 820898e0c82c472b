"""docs/deployment.md "Across machines" for real: three hosts as Linux network namespaces on one switch.

    hub  10.203.0.1   replay (router) + learner, from deploy/configs/hub-replay.toml and hub-learner.toml
    a1   10.203.0.11  actor 1, from remote-actor.toml with --transport.connect tcp/10.203.0.1:7447
    a2   10.203.0.12  actor 2, the same
    sw                a bridge; each host's eth0 is one end of a veth pair whose other end is a port of it

Each host has only its loopback and its eth0, so an actor reaches the hub over its veth link
and the bridge, as it would over a LAN; the configs' fixed port 7447 is free in every
namespace. The secure variant runs the deploy/configs/secure-*.toml files the same way (TLS,
mutual TLS, access rules), with certificates made for the hub's address 10.203.0.1, which the
actors verify. Training must proceed with both actors' episodes arriving and both acting with
the learner's weights: actor 1's from broadcasts, actor 2's downloaded piece by piece.

Needs root (CI runs as root) and iproute2; elsewhere the tests are skipped with the reason.
Namespaces (named per test run), links and processes are removed at the end, also on failure.
The lab itself is deploy/labs/netns_lab.py; tests/test_network_faults.py puts faults on its links.
"""

from __future__ import annotations

import pytest

from common.certs import main as certs_main
from deploy.labs.netns_lab import HUB, Lab, LabError, config_flags, why_no_lab
from tests.processes import wait_for
from tests.zenoh_peer import PATH as PEER
from tests.zenoh_peer import read_lines

pytestmark = pytest.mark.lab  # run alone, after the rest (deploy/test.sh)

SMOKE = ["--preset", "smoke", "--network.lstm_units", "16"]
DEADLINE_S = 75.0


@pytest.fixture
def lab(tmp_path):
    reason = why_no_lab()
    if reason:
        pytest.skip(reason)
    lab = Lab(tmp_path)
    try:
        try:
            lab.build()
        except LabError as error:
            pytest.skip(f"cannot make network namespaces and veth links here: {error}")
        yield lab
    finally:
        lab.teardown()


@pytest.mark.parametrize("secure", [False, True], ids=["tcp", "tls-mtls-acl"])
def test_actors_on_two_other_hosts_feed_the_hub(lab, secure):
    if secure:
        assert certs_main([str(lab.directory / "certs"), "--address", HUB]) == 0
    runs = ["--run.runs_dir", "runs"]
    lab.start("hub", "replay", ["-m", "replay.main", *config_flags(secure, "replay"), *SMOKE, *runs])
    watch = lab.directory / "watch.jsonl"
    lab.start("hub", "watch", [str(PEER), "watch", str(watch), *config_flags(secure, "watch")])
    wait_for(lambda: any(line["kind"] == "up" for line in read_lines(watch)), "the watcher's session", 30, lab.logs)
    lab.start("hub", "learner", ["-m", "learner.main", *config_flags(secure, "learner"), *SMOKE, *runs])
    # actor 2 downloads the weights in pieces (actor.weights_download) instead of receiving broadcasts
    downloads = ["--actor.weights_download", "true", "--actor.weights_download_period_s", "1"]
    for host, actor_id, extra in (("a1", 1, []), ("a2", 2, downloads)):
        lab.start(host, "actor", ["-m", "actor.main", *config_flags(secure, "actor"), "--actor.actor_id", str(actor_id),
                                  *SMOKE, *extra])

    def trained() -> bool:
        lab.alive()
        lines = read_lines(watch)
        updates = max((line["updates"] or 0 for line in lines if line["kind"] == "learner"), default=0)
        episodes = [line for line in lines if line["kind"] == "episode"]
        arrived = {line["actor"] for line in episodes}
        learned = {line["actor"] for line in episodes if max(line["versions"]) >= 1}
        return updates >= 5 and arrived == learned == {1, 2}

    wait_for(trained, "5 updates, and episodes of actors 1 and 2 acted with the learner's weights", DEADLINE_S,
             lab.logs)
    lines = read_lines(watch)
    replay = [line for line in lines if line["kind"] == "replay"]
    assert replay and replay[-1]["inserted"] >= 2, replay[-1:]
    for host in ("a1", "a2"):  # the actors really were elsewhere: they dialled the hub's address over their link
        log = (lab.directory / f"{host}-actor.log").read_text()
        assert f"{HUB}:7447" in log, log[-2000:]
