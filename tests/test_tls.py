"""A locked-down cluster (docs/security.md): TLS on every link, mutual TLS, and the
router's access rules by certificate common name.

The live tests run the deploy/configs/secure-*.toml files as written, from a directory holding
the certs/ that `d3rqn-certs` made, with a free loopback port in place of 7447 and smoke-sized
settings. Every Zenoh session lives in a process of its own (tests/zenoh_peer.py for the
watcher, the rogue and the connection probes).
"""

from __future__ import annotations

import subprocess
import time
from pathlib import Path

import pytest

from common.access import GRANTS, acl_config
from common.certs import main as certs_main
from common.config import TransportConfig
from common.config_values import load_config
from common.schema.fields import ConfigError
from common.transport import zenoh_config
from tests.processes import free_port, start, stop, wait_for
from tests.zenoh_peer import PATH as PEER, read_lines

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "deploy" / "configs"
SMOKE = ["--preset", "smoke", "--network.lstm_units", "16"]
# What the roles publish (actor 0, the learner, the replay): under the access rules each must still reach a subscriber.
PUBLISHED = ("episodes", "metrics/actor/0", "metrics/actor_stats/0", "metrics/learner/0", "weights/broadcast",
             "exploration", "replay/stats", "replay/rate")
FORGED_VERSION = 987_654  # the rogue's weights: no real learner gets near this version in a test
CONTROL_VERSION = 900_000  # the same weights from a holder of the learner's certificate


def make_certs(directory: Path, *flags: str) -> None:
    assert certs_main([str(directory), *flags]) == 0


def subject_of(certificate: Path) -> str:
    return subprocess.run(["openssl", "x509", "-in", str(certificate), "-noout", "-subject", "-ext", "subjectAltName"],
                          capture_output=True, text=True, check=True).stdout


# --- without a network ---------------------------------------------------------------------

def test_certs_command_makes_a_ca_and_role_certificates(tmp_path):
    certs = tmp_path / "certs"
    make_certs(certs, "--address", "hub.example", "--address", "10.9.8.7")
    for name in ("replay", "learner", "actor", "recorder"):
        verified = subprocess.run(["openssl", "verify", "-CAfile", str(certs / "ca.pem"), str(certs / f"{name}.pem")],
                                  capture_output=True, text=True)
        assert verified.returncode == 0, verified.stderr
        text = subject_of(certs / f"{name}.pem")
        assert f"CN = {name}" in text or f"CN={name}" in text
        assert "DNS:hub.example" in text and "IP Address:10.9.8.7" in text and "DNS:localhost" in text
        assert (certs / f"{name}-key.pem").stat().st_mode & 0o077 == 0  # keys: owner only
    assert (certs / "ca-key.pem").stat().st_mode & 0o077 == 0
    ca = (certs / "ca.pem").read_bytes()
    make_certs(certs, "--name", "actor-host7", "--cn", "actor")  # one more host, same CA, an actor's CN
    assert (certs / "ca.pem").read_bytes() == ca
    assert "CN = actor" in subject_of(certs / "actor-host7.pem") or "CN=actor" in subject_of(certs / "actor-host7.pem")
    assert certs_main([str(certs), "--name", "actor-host7"]) == 1  # never overwrites


def test_tls_options_are_checked():
    def transport(**values) -> TransportConfig:
        overrides = {f"transport.{key}": value for key, value in values.items()}
        return load_config("paper", overrides=overrides).transport

    with pytest.raises(ConfigError, match="tls_certificate"):
        transport(mode="router", listen=["tls/0.0.0.0:7447"], tls_ca="ca.pem")
    with pytest.raises(ConfigError, match="tls_ca"):
        transport(mode="client", connect=["tls/hub:7447"])
    with pytest.raises(ConfigError, match="tls_key"):
        transport(tls_certificate="a.pem")
    with pytest.raises(ConfigError, match="every endpoint must be tls/"):
        transport(mode="router", listen=["tls/0.0.0.0:7447", "tcp/0.0.0.0:7448"], tls_ca="ca.pem",
                  tls_certificate="r.pem", tls_key="r-key.pem", tls_mtls=True)
    with pytest.raises(ConfigError, match="acl: needs tls_mtls"):
        transport(acl=True)
    for name in ("secure-hub-replay.toml", "secure-hub-learner.toml", "secure-remote-actor.toml"):
        config = load_config("paper", CONFIGS / name)
        assert config.run.name == "cluster" and config.transport.tls_mtls
        assert all(endpoint.startswith("tls/") for endpoint in config.transport.listen + config.transport.connect)
    assert load_config("paper", CONFIGS / "secure-hub-replay.toml").transport.acl


def test_a_missing_certificate_file_is_named(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # the secure configs' certs/ paths start from the working directory
    config = load_config("paper", CONFIGS / "secure-hub-learner.toml").transport
    with pytest.raises(FileNotFoundError, match="transport.tls_ca: no file 'certs/ca.pem'"):
        zenoh_config(config)


def test_access_rules_grant_each_role_only_its_own_keys():
    acl = acl_config("d3rqn", {"learner": ["learner"], "actor": ["actor", "actor-b"], "replay": ["replay"],
                               "observer": ["recorder"]})
    assert acl["default_permission"] == "deny" and acl["enabled"]
    rules = {rule["id"]: rule for rule in acl["rules"]}
    subjects = {subject["id"]: subject["cert_common_names"] for subject in acl["subjects"]}
    assert subjects["actor"] == ["actor", "actor-b"]

    def allowed(role: str, flow: str, message: str) -> set[str]:
        policy = next(policy for policy in acl["policies"] if policy["subjects"] == [role])
        return {key for rule_id in policy["rules"] for key in rules[rule_id]["key_exprs"]
                if rules[rule_id]["permission"] == "allow" and flow in rules[rule_id]["flows"]
                and message in rules[rule_id]["messages"]}

    published = {role: allowed(role, "ingress", "put") for role in ("learner", "actor", "replay", "observer")}
    assert "d3rqn/*/weights/broadcast" in published["learner"] and "d3rqn/*/exploration" in published["learner"]
    assert "d3rqn/*/episodes" in published["actor"]
    for role in ("actor", "replay", "observer"):
        assert not {"d3rqn/*/weights/broadcast", "d3rqn/*/exploration"} & published[role]
    for role in ("learner", "replay", "observer"):
        assert "d3rqn/*/episodes" not in published[role]
    servers = {role for role in GRANTS if allowed(role, "ingress", "reply") & {"d3rqn/*/replay/sample"}}
    assert servers == {"replay"}
    assert {role for role in GRANTS if "d3rqn/*/replay/sample" in allowed(role, "ingress", "query")} == {"learner"}
    assert {role for role in GRANTS if "d3rqn/*/weights/latest" in allowed(role, "ingress", "reply")} == {"learner"}


# --- live -----------------------------------------------------------------------------------

class Cluster:
    """Processes of a secure cluster on a loopback port, run from a directory holding certs/."""

    def __init__(self, directory: Path) -> None:
        self.directory = directory
        self.port = free_port()
        self.processes: list[subprocess.Popen] = []
        self.logs: list[Path] = []

    def endpoint(self, host: str = "localhost") -> str:
        return f"tls/{host}:{self.port}"

    def start(self, name: str, module: str, config: str, *flags: str) -> subprocess.Popen:
        log = self.directory / f"{name}.log"
        self.logs.append(log)
        args = [str(PEER)] if module == "peer" else ["-m", module]  # tests/ is not installed: the peer by path
        if config:
            args += ["--config", str(CONFIGS / config)]
        process = start([*args, *flags], log, cwd=self.directory)
        self.processes.append(process)
        return process

    def hub(self, *flags: str) -> None:
        self.start("replay", "replay.main", "secure-hub-replay.toml", "--transport.listen",
                   self.endpoint("127.0.0.1"), *SMOKE, "--run.runs_dir", "runs", *flags)

    def client(self, name: str, module: str, config: str, *flags: str) -> subprocess.Popen:
        return self.start(name, module, config, "--transport.connect", self.endpoint(), *flags)

    def watcher(self) -> Path:
        out = self.directory / "watch.jsonl"
        self.client("watch", "peer", "secure-remote-actor.toml", "watch", str(out),
                    "--transport.tls_certificate", "certs/recorder.pem", "--transport.tls_key", "certs/recorder-key.pem")
        wait_for(lambda: any(line["kind"] == "up" for line in read_lines(out)), "the watcher's session", 30, self.logs)
        return out

    def alive(self) -> None:
        dead = [log.name for process, log in zip(self.processes, self.logs) if process.poll() is not None]
        assert not dead, f"exited: {dead}\n" + self.tails()

    def tails(self) -> str:
        return "\n".join(f"--- {log.name}\n{log.read_text(errors='replace')[-2500:]}" for log in self.logs if log.exists())

    def stop(self) -> None:
        stop(*reversed(self.processes))


@pytest.fixture
def cluster(tmp_path):
    make_certs(tmp_path / "certs")
    cluster = Cluster(tmp_path)
    try:
        yield cluster
    finally:
        cluster.stop()


def test_a_locked_down_stack_trains_and_a_rogue_actor_cannot_feed_weights(cluster):
    """TLS + mTLS + access rules: the stack trains; a peer holding an actor's certificate forges weights,
    exploration state and the replay's keys, and serves trace batches and weights/latest: the actor
    never loads its weights, nothing of it reaches a subscriber but its episodes, no query reaches it.
    Control: the same weights from a holder of the learner's certificate are loaded."""
    cluster.hub()
    watch = cluster.watcher()
    rogue_out = cluster.directory / "rogue.jsonl"
    cluster.client("rogue", "peer", "secure-remote-actor.toml", "rogue", str(rogue_out),
                   "--weights-version", str(FORGED_VERSION), *SMOKE)
    wait_for(lambda: any(line["kind"] == "counts" for line in read_lines(rogue_out)), "the rogue's session", 40,
             cluster.logs)
    cluster.client("learner", "learner.main", "secure-hub-learner.toml", *SMOKE, "--run.runs_dir", "runs")
    cluster.client("actor", "actor.main", "secure-remote-actor.toml", "--actor.actor_id", "0", *SMOKE)

    def trained() -> bool:
        cluster.alive()
        lines = read_lines(watch)
        updates = max((line["updates"] or 0 for line in lines if line["kind"] == "learner"), default=0)
        acted = [line for line in lines if line["kind"] == "record" and line["weights_version"] >= 1]
        return updates >= 5 and len(acted) >= 3

    wait_for(trained, "5 updates and 3 episodes acted with the learner's weights", 75, cluster.logs)

    def missing() -> set[str]:
        seen = {line["key"].rsplit("cluster/", 1)[1] for line in read_lines(watch) if line["kind"] == "key"}
        return set(PUBLISHED) - seen

    deadline = time.monotonic() + 15
    while missing() and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not missing(), f"denied by the access rules or never published: {sorted(missing())}"

    def rogue_counts() -> dict:
        return [line for line in read_lines(rogue_out) if line["kind"] == "counts"][-1]

    # it kept forging all along: 10 rounds of 0.5 s at least, however fast the stack trained meanwhile
    wait_for(lambda: rogue_counts()["weights_sent"] >= 10, "10 rounds of forgeries", 30, cluster.logs)
    lines = read_lines(watch)
    counts = rogue_counts()
    acted_with = {version for line in lines if line["kind"] == "episode" for version in line["versions"]}
    assert FORGED_VERSION not in acted_with and max(acted_with) >= 1, acted_with  # no step acted with the rogue's
    markers = {line["key"].rsplit("cluster/", 1)[1] for line in lines if line["kind"] == "marker"}
    assert markers == {"episodes"}, markers  # an actor's certificate may publish episodes, nothing else it forged
    assert counts["replay_sample_queries"] == 0 and counts["weights_latest_queries"] == 0, counts

    control_out = cluster.directory / "control.jsonl"
    cluster.client("control", "peer", "secure-hub-learner.toml", "rogue", str(control_out),
                   "--weights-version", str(CONTROL_VERSION), *SMOKE)
    wait_for(lambda: any(line["kind"] == "episode" and CONTROL_VERSION in line["versions"]
                         for line in read_lines(watch)),
             "the actor to load weights from the learner's certificate (the control)", 40, cluster.logs)

    def markers() -> set[str]:
        return {line["key"].rsplit("cluster/", 1)[1] for line in read_lines(watch) if line["kind"] == "marker"}

    wait_for(lambda: "exploration" in markers() and 4 <= max(
        (line["weights_sent"] for line in read_lines(control_out) if line["kind"] == "counts"), default=0),
             "the control's exploration state to pass, over 4 rounds", 20, cluster.logs)
    assert not {"replay/stats", "replay/rate"} & markers()  # only the replay (the router itself) publishes those
    cluster.alive()
    # the access rules let a role ask who holds its token: a second learner of the run is refused
    second = cluster.client("learner2", "learner.main", "secure-hub-learner.toml", *SMOKE, "--run.runs_dir", "runs2")
    assert second.wait(60) == 1
    assert "another process holds d3rqn/cluster/alive/learner/0" in (cluster.directory / "learner2.log").read_text()


def test_peers_without_a_valid_certificate_cannot_connect(cluster, tmp_path):
    """Against the secure hub: no certificate, a certificate of another CA (with the learner's CN), plain
    TCP on the TLS port, and a server whose certificate another CA signed all fail; a valid one connects."""
    make_certs(tmp_path / "other", "--name", "learner")
    cluster.hub()
    fast = ["--transport.connect_timeout_s", "3"]
    probes = {
        "valid": ["--transport.connect", cluster.endpoint()],
        "no-certificate": ["--transport.connect", cluster.endpoint(), "--transport.tls_mtls", "false",
                           "--transport.tls_certificate", "", "--transport.tls_key", ""],
        "other-ca": ["--transport.connect", cluster.endpoint(), "--transport.tls_certificate", "other/learner.pem",
                     "--transport.tls_key", "other/learner-key.pem"],
        "plain-tcp": ["--transport.connect", f"tcp/127.0.0.1:{cluster.port}", "--transport.tls_mtls", "false"],
    }
    rogue_port = free_port()
    cluster.start("rogue-hub", "peer", "secure-hub-replay.toml", "watch", str(tmp_path / "rogue-hub.jsonl"),
                  "--transport.listen", f"tls/127.0.0.1:{rogue_port}", "--transport.tls_ca", "other/ca.pem",
                  "--transport.tls_certificate", "other/learner.pem", "--transport.tls_key", "other/learner-key.pem")
    probes["rogue-server"] = ["--transport.connect", f"tls/localhost:{rogue_port}"]
    wait_for(lambda: any(line["kind"] == "up" for line in read_lines(tmp_path / "rogue-hub.jsonl")),
             "the rogue hub", 30, cluster.logs)
    running = {name: cluster.start(f"probe-{name}", "peer", "secure-hub-learner.toml", "probe", *flags, *fast)
               for name, flags in probes.items()}
    codes = {name: process.wait(60) for name, process in running.items()}
    assert codes == {"valid": 0, "no-certificate": 3, "other-ca": 3, "plain-tcp": 3, "rogue-server": 3}, \
        cluster.tails()
    assert "connected" in (tmp_path / "probe-valid.log").read_text()
