import itertools
import json
import logging
import os
import queue
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import zenoh

from common.config import TransportConfig
from common.liveliness import alive_keys, declare_liveliness, watch_liveliness
from common.transport import open_session, publisher, request, serve, subscribe, zenoh_config
from common.logs import ThrottledLog
from common.keys import Keys
from common.wire.envelope import encode
from common.wire.messages import Stats, TraceBatchRequest, Weights
from tests.processes import loopback_endpoint
from wire_examples import assert_messages_equal, example_messages

WAIT_S = 5.0  # bound of every wait for discovery or delivery
BIG_WEIGHTS_BYTES = 50_000_000


def wait_until(predicate, timeout_s: float = WAIT_S) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.01)
    return bool(predicate())


def big_weights() -> Weights:
    """About 50 MB of float32, the size of the D3RQN's parameters."""
    rng = np.random.default_rng(0)
    count = BIG_WEIGHTS_BYTES // 4
    return Weights(version=9, created=time.time(), tensors={
        "lstm.weight_ih": rng.standard_normal(count - 1000, dtype=np.float32),
        "head.weight": rng.standard_normal((5, 200), dtype=np.float32),
    })


@pytest.fixture(scope="module")
def sessions():
    """Two peers on loopback: one listens on a free port, the other only connects."""
    endpoint = loopback_endpoint()
    listener = open_session(TransportConfig(listen=[endpoint]))
    try:
        connector = open_session(TransportConfig(connect=[endpoint]))
        try:
            assert wait_until(lambda: connector.info.peers_zid() and listener.info.peers_zid())
            yield listener, connector
        finally:
            connector.close()
    finally:
        listener.close()


_runs = itertools.count()


@pytest.fixture
def keys():
    """Keys of a fresh run, so tests sharing the sessions never see each other's messages."""
    return Keys("d3rqn-test", f"run{next(_runs)}")


def collect(session, key, **options):
    """A subscription whose messages land in a queue."""
    inbox: queue.Queue = queue.Queue()
    subscription = subscribe(session, key, lambda message, sample_key: inbox.put((message, sample_key)), **options)
    return subscription, inbox


# --- configuration and keys -------------------------------------------------------------------

def test_zenoh_config_holds_mode_endpoints_and_scouting():
    config = TransportConfig(mode="client", connect=["tcp/127.0.0.1:7000"], connect_timeout_s=2.5)
    zconfig = zenoh_config(config)
    assert json.loads(zconfig.get_json("mode")) == "client"
    assert json.loads(zconfig.get_json("connect/endpoints")) == ["tcp/127.0.0.1:7000"]
    assert json.loads(zconfig.get_json("listen/endpoints")) == []
    assert json.loads(zconfig.get_json("scouting/multicast/enabled")) is False
    assert json.loads(zconfig.get_json("connect/timeout_ms")) == 2500


def test_keys_place_every_name_under_namespace_and_run():
    keys = Keys("d3rqn", "paper1")
    assert keys.episodes == "d3rqn/paper1/episodes"
    assert keys.replay_sample == "d3rqn/paper1/replay/sample"
    assert keys.replay_stats == "d3rqn/paper1/replay/stats"
    assert keys.weights == "d3rqn/paper1/weights/broadcast"
    assert keys.weights_latest == "d3rqn/paper1/weights/latest"
    assert keys.exploration == "d3rqn/paper1/exploration"
    assert keys.metrics_source("actor", 3) == "d3rqn/paper1/metrics/actor/3"
    assert keys.metrics_source("learner") == "d3rqn/paper1/metrics/learner"
    assert keys.liveliness("actor", "a-1") == "d3rqn/paper1/alive/actor/a-1"
    assert keys.all == "d3rqn/paper1/**"


def test_wildcard_keys_cover_their_family_and_nothing_else():
    keys = Keys("d3rqn", "paper1")
    assert zenoh.KeyExpr(keys.metrics_all).includes(keys.metrics_source("actor", 3))
    assert zenoh.KeyExpr(keys.metrics_all).includes(keys.metrics_source("learner"))
    assert not zenoh.KeyExpr(keys.metrics_all).includes(keys.replay_stats)
    assert zenoh.KeyExpr(keys.liveliness_all).includes(keys.liveliness("learner", 0))
    assert not zenoh.KeyExpr(keys.weights).includes(keys.weights_latest)
    assert all(zenoh.KeyExpr(keys.all).includes(key) for key in (keys.episodes, keys.weights_latest, keys.metrics_all))


@pytest.mark.parametrize("namespace, run", [("", "r"), ("a/b", "r"), ("d3rqn", "run*"), ("d3rqn", "x y")])
def test_keys_refuse_chunks_that_would_change_the_key_structure(namespace, run):
    with pytest.raises(ValueError, match="key chunk"):
        Keys(namespace, run)


def test_metrics_source_refuses_a_wildcard_role():
    with pytest.raises(ValueError, match="role"):
        Keys("d3rqn", "r").metrics_source("**")


# --- publish / subscribe -------------------------------------------------------------------------

def test_every_message_type_passes_through_publish_subscribe(sessions, keys):
    listener, connector = sessions
    subscription, inbox = collect(listener, keys.episodes)
    with subscription, publisher(connector, keys.episodes) as out:
        assert wait_until(lambda: out.matched)
        sent = example_messages()
        for message in sent:
            out.put(message)
        for message in sent:
            received, sample_key = inbox.get(timeout=WAIT_S)
            assert sample_key == keys.episodes
            assert_messages_equal(message, received)
    assert (subscription.received, subscription.rejected, subscription.failed) == (len(sent), 0, 0)


def test_fifty_megabyte_weights_pass_through_publish_subscribe(sessions, keys):
    listener, connector = sessions
    weights = big_weights()
    subscription, inbox = collect(connector, keys.weights, expected=Weights)
    with subscription, publisher(listener, keys.weights) as out:
        assert wait_until(lambda: out.matched)
        assert out.put(weights) > BIG_WEIGHTS_BYTES
        received, _ = inbox.get(timeout=WAIT_S * 2)
    assert_messages_equal(weights, received)


def small(seq: int) -> Stats:
    """A small message numbered seq."""
    return Stats(source="r", time=0.0, values={"seq": seq})


def test_malformed_sample_is_counted_and_the_next_good_one_arrives(sessions, keys):
    listener, connector = sessions
    subscription, inbox = collect(listener, keys.exploration)
    with subscription, publisher(connector, keys.exploration) as out:
        assert wait_until(lambda: out.matched)
        connector.put(keys.exploration, b"\x93not a message")
        good = small(1)
        out.put(good)
        received, _ = inbox.get(timeout=WAIT_S)
        assert_messages_equal(good, received)
        assert wait_until(lambda: subscription.rejected == 1)
        assert inbox.empty() and subscription.received == 1


def test_wrong_type_and_oversized_samples_are_rejected(sessions, keys):
    listener, connector = sessions
    subscription, inbox = collect(listener, keys.episodes, expected=Stats, max_bytes=200)
    with subscription, publisher(connector, keys.episodes) as out:
        assert wait_until(lambda: out.matched)
        out.put(TraceBatchRequest(request_id=0, batch_size=1, trace_length=1))  # wrong type
        out.put(Stats(source="r" * 300, time=0.0, values={"seq": 0}))  # too long
        out.put(small(3))
        received, _ = inbox.get(timeout=WAIT_S)
        assert received.values["seq"] == 3
        assert wait_until(lambda: subscription.rejected == 2)


def test_a_failing_callback_is_counted_and_the_subscription_goes_on(sessions, keys):
    listener, connector = sessions
    seen = []

    def fussy(message, sample_key):
        if message.values["seq"] == 0:
            raise RuntimeError("first one fails")
        seen.append(message.values["seq"])

    with subscribe(listener, keys.episodes, fussy) as subscription, publisher(connector, keys.episodes) as out:
        assert wait_until(lambda: out.matched)
        for seq in range(2):
            out.put(small(seq))
        assert wait_until(lambda: seen == [1])
        assert (subscription.received, subscription.failed) == (2, 1)


# --- request / reply -----------------------------------------------------------------------------

def wait_for_service(session, key, message=None):
    reply = []
    assert wait_until(lambda: reply.append(request(session, key, message, 1.0)) or reply[-1] is not None)
    return reply[-1]


def test_every_message_type_passes_through_request_reply(sessions, keys):
    listener, connector = sessions
    with serve(listener, keys.replay_sample, lambda message: message) as service:  # an echo service
        wait_for_service(connector, keys.replay_sample, small(0))
        for message in example_messages():
            reply = request(connector, keys.replay_sample, message, WAIT_S)
            assert_messages_equal(message, reply)
    assert service.rejected == 0 and service.failed == 0


def test_fifty_megabyte_weights_pass_through_request_and_reply(sessions, keys):
    listener, connector = sessions
    weights = big_weights()
    with serve(listener, keys.weights_latest, lambda message: weights if message is None else message):
        latest = wait_for_service(connector, keys.weights_latest)
        assert_messages_equal(weights, latest)
        echoed = request(connector, keys.weights_latest, weights, WAIT_S * 2, expected=Weights)
        assert_messages_equal(weights, echoed)


def test_a_query_without_payload_reaches_the_handler_as_none(sessions, keys):
    listener, connector = sessions
    requests = []
    reply_message = small(1)
    with serve(listener, keys.weights_latest, lambda message: requests.append(message) or reply_message):
        assert_messages_equal(reply_message, wait_for_service(connector, keys.weights_latest))
    assert set(requests) == {None}


def test_handler_errors_are_answered_with_an_error_and_the_service_goes_on(sessions, keys, caplog):
    listener, connector = sessions
    good = TraceBatchRequest(request_id=1, batch_size=1, trace_length=1)

    def handler(message):
        if message.request_id == 0:
            raise KeyError("no episodes")
        return message

    with serve(listener, keys.replay_sample, handler) as service:
        wait_for_service(connector, keys.replay_sample, good)
        with caplog.at_level(logging.WARNING, logger="common.transport"):
            assert request(connector, keys.replay_sample, TraceBatchRequest(0, 1, 1), WAIT_S) is None
        assert service.failed == 1
        assert any("handler failed: KeyError" in record.getMessage() for record in caplog.records)
        assert request(connector, keys.replay_sample, good, WAIT_S).request_id == 1


def test_a_malformed_request_gets_an_error_reply(sessions, keys):
    listener, connector = sessions
    with serve(listener, keys.replay_sample, lambda message: message) as service:
        wait_for_service(connector, keys.replay_sample, small(0))
        replies = list(connector.get(keys.replay_sample, payload=b"\xc1junk", timeout=WAIT_S))
    assert len(replies) == 1 and replies[0].ok is None
    assert replies[0].err.payload.to_string().startswith("bad request: not a msgpack message")
    assert service.rejected == 1


def test_a_malformed_or_unexpected_reply_gives_none(sessions, keys):
    listener, connector = sessions
    answers = iter([b"garbage", encode(small(0))])

    def raw_queryable(query):
        with query:
            query.reply(keys.replay_sample, next(answers, b""))

    queryable = listener.declare_queryable(keys.replay_sample, raw_queryable)
    querier = connector.declare_querier(keys.replay_sample)
    try:
        assert wait_until(lambda: querier.matching_status.matching)
        assert request(connector, keys.replay_sample, None, WAIT_S) is None  # garbage
        assert request(connector, keys.replay_sample, None, WAIT_S, expected=Weights) is None  # a Stats
    finally:
        querier.undeclare()
        queryable.undeclare()


def test_a_request_without_any_service_returns_none_at_once(sessions, keys):
    _, connector = sessions
    start = time.monotonic()
    assert request(connector, keys.replay_sample, TraceBatchRequest(0, 1, 1), WAIT_S) is None
    assert time.monotonic() - start < WAIT_S


# --- liveliness ------------------------------------------------------------------------------------

def test_a_liveliness_token_is_seen_by_the_other_session_until_undeclared(sessions, keys):
    listener, connector = sessions
    changes: queue.Queue = queue.Queue()
    token_key = keys.liveliness("actor", 3)
    with watch_liveliness(connector, keys.liveliness_all, lambda key, alive: changes.put((key, alive))):
        token = declare_liveliness(listener, token_key)
        assert changes.get(timeout=WAIT_S) == (token_key, True)
        assert wait_until(lambda: alive_keys(connector, keys.liveliness_all, 1.0) == [token_key])
        token.undeclare()
        assert changes.get(timeout=WAIT_S) == (token_key, False)
        assert wait_until(lambda: alive_keys(connector, keys.liveliness_all, 1.0) == [])


# --- opening sessions ---------------------------------------------------------------------------------

def test_a_client_waits_for_a_router_that_starts_late():
    endpoint = loopback_endpoint()
    routers = []
    starter = threading.Timer(0.3, lambda: routers.append(open_session(TransportConfig(mode="router", listen=[endpoint]))))
    starter.start()
    try:
        with open_session(TransportConfig(mode="client", connect=[endpoint], connect_timeout_s=WAIT_S)) as client:
            assert client.info.routers_zid()
    finally:
        starter.join()
        for router in routers:
            router.close()


def test_undeclaring_twice_or_after_the_session_closed_is_harmless():
    session = open_session(TransportConfig())
    declared = [subscribe(session, "d3rqn-test/a", lambda message, key: None), publisher(session, "d3rqn-test/a"),
                serve(session, "d3rqn-test/b", lambda message: None), declare_liveliness(session, "d3rqn-test/c")]
    declared[0].undeclare()
    session.close()
    for entity in declared:
        entity.undeclare()


# --- throttled logging -----------------------------------------------------------------------------

def test_a_throttled_log_reports_what_it_suppressed_on_the_logger_it_was_given(caplog):
    now = [0.0]
    warn = ThrottledLog(period_s=10.0, clock=lambda: now[0], logger=logging.getLogger("replay"))
    with caplog.at_level(logging.WARNING, logger="replay"):
        warn.warning("bad sample %d", 1)
        warn.warning("bad sample %d", 2)
        warn.warning("bad sample %d", 3)
        now[0] = 10.0
        warn.warning("bad sample %d", 4)
    assert [record.getMessage() for record in caplog.records] == ["bad sample 1", "bad sample 4 (2 similar suppressed)"]
    assert {record.name for record in caplog.records} == {"replay"}


def test_zenohs_own_log_lines_reach_the_process_output_plain(tmp_path):
    # Zenoh's errors (a transport closed as unresponsive) would be silent otherwise; RUST_LOG=info here
    # so that opening a session is enough to see its lines
    script = ("import sys; from common.config import TransportConfig; from common.transport import open_session; "
              "open_session(TransportConfig(mode='peer', multicast_scouting=False)).close()")
    env = {key: value for key, value in os.environ.items() if key != "NO_COLOR"}
    done = subprocess.run([sys.executable, "-c", script], env={**env, "RUST_LOG": "info"}, capture_output=True,
                          text=True, timeout=60, cwd=Path(__file__).parent.parent)
    assert done.returncode == 0, done.stderr
    lines = [line for line in done.stdout.splitlines() if " INFO " in line and "zenoh" in line]
    assert lines and not any("\x1b[" in line for line in lines), done.stdout[:500]
