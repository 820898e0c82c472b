"""The config's sections that every process shares and the method does not: the run's name and folder
(run), how it talks (transport: Zenoh, TLS, access control), what the flight recorder keeps
(record) and how an actor process runs (actor). They are sections of the one Config (common/config.py), declared the same way.
"""

from __future__ import annotations

from dataclasses import dataclass

from common.schema.fields import check, check_positive, option


TRANSPORT_MODES = ("peer", "client", "router")
INFERENCE_PRECISIONS = ("float32", "bfloat16", "auto")  # actor.inference


@dataclass
class TransportConfig:
    """The Zenoh session: mode, endpoints, key namespace, TLS and access control."""

    mode: str = option("peer", "Zenoh session mode", choices=TRANSPORT_MODES)
    listen: list[str] = option([], "endpoints to listen on, e.g. tcp/0.0.0.0:7447")
    connect: list[str] = option([], "endpoints to connect to, e.g. tcp/127.0.0.1:7447")
    multicast_scouting: bool = option(False, "find peers by UDP multicast on the local network")
    shared_memory: bool = option(
        False, "Zenoh shared memory between the processes of one host (transport/shared_memory/enabled): the learner "
              "puts its weights broadcasts from a shared-memory buffer that local subscribers map instead of each "
              "receiving a copy over a socket (remote ones get them over the network as before). Where Zenoh has "
              "none, the weights go over the network, with one log line. Off by default: with it on, what a process "
              "publishes just before it exits can be lost (d3rqn-log play lost every episode it played)")
    namespace: str = option("d3rqn", "first chunk of every key: <namespace>/<run.name>/...")
    connect_timeout_s: float = option(10.0, "client mode: how long opening a session retries its connect endpoints",
                                      "s")
    # TLS on tls/<host>:<port> endpoints (docs/security.md; d3rqn-certs makes the files).
    tls_ca: str = option("", "PEM file of the run's CA: listeners' certificates (and with tls_mtls, peers') must "
                             "be signed by it; relative paths start from the working directory")
    tls_certificate: str = option("", "PEM file of this host's certificate, shown when listening (and with "
                                      "tls_mtls, connecting)")
    tls_key: str = option("", "PEM file of this host's private key")
    tls_mtls: bool = option(False, "mutual TLS: listeners admit only peers with a certificate signed by tls_ca")
    tls_verify_name: bool = option(True, "a connecting process checks that the listener's certificate names the "
                                         "address dialled")
    # Deny by default; common/access.py lists what each role may do.
    acl: bool = option(False, "access control on this session's links (the router's), by the common name of each "
                              "peer's certificate; needs tls_mtls")
    acl_learners: list[str] = option(["learner"], "certificate common names admitted as learners")
    acl_actors: list[str] = option(["actor"], "certificate common names admitted as actors")
    acl_replays: list[str] = option(["replay"], "certificate common names admitted as a replay that is not the "
                                                "router")
    acl_observers: list[str] = option(["recorder"], "certificate common names admitted as observers: they read "
                                                    "everything and write nothing")

    def validate(self) -> None:
        check(self.mode in TRANSPORT_MODES, "mode", "must be 'peer', 'client' or 'router'")
        check_positive(self, "connect_timeout_s")
        for key in ("listen", "connect"):
            for endpoint in getattr(self, key):
                check("/" in endpoint, key, f"endpoint {endpoint!r} must look like 'tcp/127.0.0.1:7447'")
        check(_is_key_chunk(self.namespace), "namespace", "must be a non-empty key chunk without '/', '*', '$', '?' or '#'")
        self._validate_security()

    def _validate_security(self) -> None:
        check(bool(self.tls_certificate) == bool(self.tls_key), "tls_key",
              "tls_certificate and tls_key go together: give both or neither")
        if any(endpoint.startswith("tls/") for endpoint in self.listen):
            check(bool(self.tls_certificate), "tls_certificate", "a tls/ listener needs a certificate and key")
        if any(endpoint.startswith("tls/") for endpoint in self.listen + self.connect):
            check(bool(self.tls_ca), "tls_ca", "tls/ endpoints need the run's CA certificate")
        if self.tls_mtls:
            check(bool(self.tls_certificate and self.tls_ca), "tls_mtls", "needs tls_ca, tls_certificate and tls_key")
            for key in ("listen", "connect"):
                for endpoint in getattr(self, key):
                    check(endpoint.startswith("tls/"), key,
                          f"endpoint {endpoint!r}: with tls_mtls every endpoint must be tls/ (another would admit peers without a certificate)")
        if self.acl:
            check(self.tls_mtls, "acl", "needs tls_mtls: the access rules tell peers apart by their certificates")
        for key in ("acl_learners", "acl_actors", "acl_replays", "acl_observers"):
            for name in getattr(self, key):
                check(bool(name.strip()), key, "common names must not be empty")


@dataclass
class RunConfig:
    """Which run a process belongs to and where its folder is."""

    name: str = option("default", "the run's name: its folder <runs_dir>/<name>/ and its keys "
                                  "<transport.namespace>/<name>/...")
    seed: int = option(0, "root of the actors' seeds (each derived with its actor.actor_id)")
    runs_dir: str = option("runs", "folder that holds the run folders")

    def validate(self) -> None:
        check(_is_key_chunk(self.name), "name", "must be a non-empty key chunk without '/', '*', '$', '?' or '#'")


IMAGE_FORMATS = ("png", "jpeg")


@dataclass
class RecorderConfig:
    """The flight recorder (replay/recorder): what it keeps of a run's messages and how it writes the MCAP file."""

    enabled: bool = option(True, "the local stack starts a recorder writing <runs_dir>/<run>/traffic.mcap")
    # A paper run has ~250,000 weight versions of 48 MB each.
    weights_every_versions: int = option(50_000, "keep a Weights message when its version is this far past the "
                                                 "last kept one (the first and the last of a run are always kept)",
                                         "versions")
    flush_period_s: float = option(5.0, "closes the open chunk this often: a killed recorder loses at most this "
                                        "span", "s")
    chunk_mb: float = option(4.0, "a chunk also closes at this size", "MB")
    queue_messages: int = option(10_000, "hand-off from Zenoh's threads to the writer; beyond it messages are "
                                         "dropped and counted, never waited for", "messages")
    queue_mb: float = option(512.0, "the same hand-off's cap in size; beyond it messages are dropped and counted",
                             "MB")
    views: bool = option(True, "also write JSON copies of metrics, stats and exploration state that Foxglove reads "
                               "without plugins")
    images: bool = option(False, "also write camera frames as foxglove.CompressedImage while recording (CPU, size); "
                                 "see `d3rqn-log export --images`")
    image_format: str = option("png", "format of those frames: png (lossless) or jpeg", choices=IMAGE_FORMATS)
    stats_period_s: float = option(5.0, "how often the recorder publishes its own counters on metrics/recorder/0",
                                   "s")

    def validate(self) -> None:
        check_positive(self, "weights_every_versions", "flush_period_s", "chunk_mb", "queue_messages", "queue_mb",
                       "stats_period_s")
        check(self.image_format in IMAGE_FORMATS, "image_format", "must be 'png' or 'jpeg'")


def _is_key_chunk(text: str) -> bool:
    return bool(text) and not any(char in text for char in "/*$?# ")


@dataclass
class ActorConfig:
    """An actor process: which one it is, how many simulators it steps, how often it logs, its queue while
    no replay listens, and what it does when the hub's word stops coming."""

    num_actors: int = option(0, "actors the local stack starts; 0 means one per spare core", "actors")
    actor_id: int = option(0, "this actor's number: its keys and, with run.seed, its seed")
    log_period_s: float = option(10.0, "how often the actor logs a status line", "s")
    envs_per_actor: int = option(1, "simulators one actor steps in lockstep, with one batched forward pass of the "
                                    "network per step; each has its own seed, LSTM state, exploration draws and "
                                    "episodes", "simulators")
    inference: str = option(
        "float32", "number format of the actor's forward pass: float32; bfloat16 (the convolutions and the LSTM's "
                   "input projection, with float32 state and head: 2.6-3.2x faster on a CPU with AMX, greedy actions "
                   "as float32's within the tolerance docs/architecture.md states); or auto (bfloat16 where a timing of both at start "
                   "finds it at least 1.2x faster). The evaluation always acts in float32",
        choices=INFERENCE_PRECISIONS)
    # Finished episodes wait in a queue while no replay listens (a replay restart).
    queue_episodes: int = option(32, "the actor holds its next episode while this many finished episodes wait "
                                     "for a replay", "episodes")
    queue_mb: float = option(256.0, "the actor holds its next episode while this much of finished episodes waits "
                                    "for a replay", "MB")
    # Sent episodes stay until the replay says it keeps them (actor/delivery.py).
    resend_after_s: float = option(5.0, "an episode sent this long ago whose receipt the replay has not "
                                        "acknowledged is sent again (the replay takes none twice); one received but "
                                        "not yet kept in a snapshot, after twice replay.snapshot_period_s more", "s")
    in_flight_mb: float = option(256.0, "sent episodes the replay has not yet said it keeps are held, to be sent "
                                        "again after a partition or a replay restart, up to this size; past it "
                                        "the oldest is given up (counted as released)", "MB")
    weights_download: bool = option(
        False, "beyond the paper, for an actor on a slow link: instead of receiving the learner's broadcasts, "
               "download its latest weights piece by piece at the link's pace, every weights_download_period_s. "
               "A broadcast that a slow link cannot carry in its period backs the hub's router up into the "
               "learner's link and slows the learner (docs/reliability.md); a download blocks no queue")
    weights_download_period_s: float = option(
        10.0, "actor.weights_download: how long after one download the next begins", "s")
    # The replay announces its rate word at least every replay.stats_period_s (common/hub_link.py).
    silence_hold_s: float = option(
        30.0, "hold the next episode once the replay's word on replay/rate has not come for this long: this actor "
              "may no longer hear the hub, and driving on would outrun the rate limiter", "s")
    silence_reopen_s: float = option(
        60.0, "reopen the Zenoh session once the replay's word has not come for this long, and again after each "
              "further span: a session can stay half-alive, its publications arriving while nothing reaches it", "s")

    def validate(self) -> None:
        check(self.num_actors >= 0, "num_actors", "must be >= 0")
        check(self.actor_id >= 0, "actor_id", "must be >= 0")
        check_positive(self, "log_period_s", "envs_per_actor", "queue_episodes", "queue_mb", "resend_after_s",
                       "in_flight_mb", "weights_download_period_s", "silence_hold_s", "silence_reopen_s")
        check(self.silence_reopen_s >= self.silence_hold_s, "silence_reopen_s", "must be >= silence_hold_s")
        check(self.inference in INFERENCE_PRECISIONS, "inference",
              f"must be one of {', '.join(INFERENCE_PRECISIONS)}")
