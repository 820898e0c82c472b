"""The actor process: drive the simulators with the newest policy and publish whole episodes (the acting
itself, simulators, network and strategy, is actor/acting.py; here its session, threads and loop).

An actor steps actor.envs_per_actor simulators in lockstep on the acting core
(actor/lockstep.py, which the evaluation and the reference loop use too): one batched forward
pass of the network per step (actor/batched_q.py, shared with the evaluation),
each simulator with its own seed, LSTM state (zeroed when its episode starts),
exploration draws and episodes. Weights and exploration state arrive on Zenoh
callbacks, which only park the newest message in a mailbox; the stepping loop
picks it up between steps, so a slow or absent learner never blocks driving.

The learner is the authority on exploration: the actor builds no strategy of its
own; it acts uniformly at random until the learner's exploration state comes, then
follows the strategy that state describes (one log line when it changes). Between episodes the actor obeys the replay's rate limiter: a simulator
whose episode has ended starts no other while the replay says the learner is
behind (``replay/rate``); see EpisodeGate. Once the replay says updates have
started, an actor that has not yet had the learner's weights and exploration
state (a run resumed, an actor restarted) starts no episode either: it would
act at random and fill the replay with episodes no policy of the run drove.
So an actor begins its first episode only once it has heard the replay's word.

Nothing that arrives is taken on trust: weights must be in an encoding this build
reads (float32, or compact float16 or bfloat16, widened to float32 on arrival) and
name the network's tensors with their shapes (and finite values, checked again
when loaded), an exploration state must describe a strategy completely, a rate
message must be the replay's typed RateState counting no more env steps than the run can. What is
refused is counted by kind and logged at a bounded rate; the counts go out on
``metrics/actor_stats/<id>``. The newest acceptable weights win, whatever their version: a learner
resumed from an older checkpoint counts its versions from there. An actor on a slow link
(actor.weights_download) takes no broadcasts: it downloads the latest weights piece by piece at its
link's pace (actor/weights_download.py), so that its link never backs the hub up into the learner's.

Finished episodes go to an outbox that one thread sends from, in order, while a
replay is alive (its liveliness token) and subscribed. While none is (a replay
restart) they wait there, and no simulator begins an episode until a replay's rate
message comes again: no rate limiter counts the steps meanwhile. When the outbox
holds actor.queue_episodes episodes or actor.queue_mb MB, all of the actor's
simulators wait for room. Episodes still waiting when
the actor stops are counted as dropped. Each episode carries this process's
random incarnation, so the replay never stores one twice and counts the ones that
never arrived. A sent episode stays in the outbox until the replay says it keeps
it, and is sent again after a loss, a partition or a replay restart (actor/delivery.py).
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Callable

import numpy as np
import torch
import zenoh

from actor.acting import Actor
from actor.delivery import REPLAY_WAIT_LOG_S, Outbox
from actor.gate import HOLD_LOG_S, EpisodeGate, HoldLog
from common.hub_link import Declare, HubLink, keep_hearing
from actor.mailbox import Mailbox
from actor.weights_download import download_weights
from common.config import Config
from common.logs import Every
from common.shell import Shell
from common.liveliness import watch_liveliness
from common.transport import publisher, request, subscribe
from common.keys import Keys
from common.wire.errors import WireError
from common.wire.messages import EpisodeAck, WeightsPiece, WeightsPieceAsk
from common.wire.metrics import ActorStats

MEGABYTE = 1 << 20

log = logging.getLogger("actor")

LATEST_WEIGHTS_TIMEOUT_S = 30.0
LATEST_WEIGHTS_RETRY_S = 5.0  # asked again while no weights have come: a resuming learner answers late
STALE_BROADCASTS = 4  # weights this many broadcasts old are reported: the broadcasts are not getting through


class ReplayWatch:
    """Whether the run's replay is alive, from its liveliness token (gone when it dies, back when it returns);
    calls on_gone when the last one goes."""

    def __init__(self, on_gone: Callable[[], None] = lambda: None) -> None:
        self._alive: set[str] = set()
        self._lock = threading.Lock()
        self.on_gone = on_gone

    def on_change(self, key: str, alive: bool) -> None:
        with self._lock:
            (self._alive.add if alive else self._alive.discard)(key)
            gone = not self._alive
        if gone:
            self.on_gone()

    def forget(self) -> None:
        """Knows of no replay until a watcher tells again (a fresh session's, after a reopen)."""
        with self._lock:
            self._alive.clear()

    @property
    def alive(self) -> bool:
        with self._lock:
            return bool(self._alive)


def _declaring(config: Config, keys: Keys, actor: Actor, outbox: Outbox, replay: ReplayWatch) -> Declare:
    """What the actor declares on a session (again on each fresh one): receivers and publishers by name."""
    def declare(session) -> tuple[dict, dict]:
        replay.forget()  # the new session's watcher tells again which replay is alive
        mailbox = actor.mailbox
        # no expected type: a message of another type reaches the mailbox, which counts it
        weights = {} if config.actor.weights_download else {  # a slow link: no broadcasts, downloads at its pace
            "weights": subscribe(session, keys.weights, mailbox.offer_weights)}
        receivers = {**weights, "exploration": subscribe(session, keys.exploration, mailbox.offer_exploration),
                     "rate": subscribe(session, keys.replay_rate, mailbox.offer_rate),
                     "acks": subscribe(session, keys.episode_acks(actor.actor_id), outbox.on_ack, expected=EpisodeAck),
                     "liveliness": watch_liveliness(session, keys.liveliness("replay", "0"), replay.on_change)}
        publishers = {"episodes": publisher(session, keys.episodes),
                      "records": publisher(session, keys.metrics_source("actor", str(actor.actor_id))),
                      "stats": publisher(session, keys.metrics_source("actor_stats", str(actor.actor_id)))}
        return receivers, publishers
    return declare


def run_actor(config: Config, max_episodes: int | None = None) -> None:
    """Runs episodes until stopped (SIGINT/SIGTERM) or after max_episodes (then waits until they are sent)."""
    actor_id = config.actor.actor_id
    shell = Shell("actor", config, actor_id)
    stop = shell.stop
    torch.set_num_threads(1)  # one core per actor; the learner owns the rest
    actor = Actor(config, actor_id)
    log.info("actor %d (seed %d, incarnation %x), %d simulator(s), acting uniformly until the learner's "
             "exploration state comes", actor_id, actor.seed, actor.incarnation, len(actor.slots))
    keys = shell.keys
    outbox = Outbox(config.actor.queue_episodes, int(config.actor.queue_mb * MEGABYTE),
                    incarnation=actor.incarnation, actor_id=actor_id, resend_after_s=config.actor.resend_after_s,
                    keep_within_s=config.actor.resend_after_s + 2 * config.replay.snapshot_period_s,
                    max_in_flight_bytes=int(config.actor.in_flight_mb * MEGABYTE))
    replay = ReplayWatch(actor.mailbox.replay_gone)  # a restarted replay's rate limiter must see every step
    sending = threading.Event()  # the sender and the stats thread stop once driving is over
    with shell.session() as session:
        shell.on_close(sending.set)
        link = HubLink(shell, session, _declaring(config, keys, actor, outbox, replay))
        shell.on_close(link.close)
        threads = [
            threading.Thread(target=_download_weights if config.actor.weights_download else _fetch_latest_weights,
                             args=(link, keys, actor, stop), daemon=True),
            threading.Thread(target=keep_hearing, args=(link, actor.mailbox.silent_s, config.actor.silence_reopen_s,
                                                        sending), name="hearing", daemon=True),
            threading.Thread(target=outbox.run, args=(lambda episode: link.put("episodes", episode),
                                                      lambda: replay.alive and link.matched("episodes"), sending),
                             name="outbox", daemon=True),
            threading.Thread(target=_report_stats, args=(actor, outbox, link, sending), name="stats", daemon=True)]
        for thread in threads:
            thread.start()
        if max_episodes != 0 and _await_replays_word(actor.mailbox, stop):  # 0: nothing to drive, no word needed
            _drive(actor, stop, max_episodes, outbox, link)
        outbox.drain(stop)
        sending.set()
        for thread in threads[1:]:
            thread.join(timeout=5.0)
        unsent = outbox.drop_rest()
        if unsent:
            log.warning("stopping with %d finished episodes unsent: dropped", unsent)
        link.put("stats", _stats(actor, outbox, link))
    counts = outbox.values()
    log.info("actor %d stopped after %d episodes: %d sent (%d sent again), %d kept by the replay, %d in flight, "
             "%d dropped, %d released", actor_id, actor.episode_index, counts["episodes_sent"],
             counts["episodes_resent"], counts["episodes_kept"], counts["episodes_in_flight"],
             counts["episodes_dropped"], counts["episodes_released"])


def _stats(actor: Actor, outbox: Outbox, link: HubLink) -> ActorStats:
    behind = actor.mailbox.weights_behind(actor.weights_version)
    actor.weights_behind_max = max(actor.weights_behind_max, behind)
    return ActorStats(time=time.time(), episodes=actor.episode_index, **outbox.values(),
                      weights_version=actor.weights_version, weights_behind=behind,
                      weights_behind_max=actor.weights_behind_max, weights_superseded=actor.mailbox.superseded,
                      weights_downloads=actor.weights_downloads, weights_download_s=actor.weights_download_s,
                      sessions_reopened=link.reopened, hub_silent_s=round(actor.mailbox.silent_s(), 1),
                      rejected={**actor.rejections.values(),
                                **{f"malformed_{door}": rejected for door, rejected in link.rejected().items()}})


def _report_stats(actor: Actor, outbox: Outbox, link: HubLink, stop: threading.Event) -> None:
    stale = STALE_BROADCASTS * actor.config.learner.weights_every
    while not stop.wait(actor.config.actor.log_period_s):
        try:
            stats = _stats(actor, outbox, link)
            link.put("stats", stats)
        except Exception:  # the stats must never stop the actor
            log.warning("could not publish the actor's stats", exc_info=True)
            continue
        if _stale(actor, stats.weights_behind > stale):
            how = (f"downloads every {actor.config.actor.weights_download_period_s:g} s after the last: none has "
                   "finished for three periods" if actor.config.actor.weights_download else
                   f"broadcasts every {actor.config.learner.weights_every}: no newer broadcast has come through")
            log.warning("acting on weights v%d, %d updates behind the learner (%s; a slow or broken link?); acting "
                        "on these meanwhile", actor.weights_version, stats.weights_behind, how)


def _stale(actor: Actor, behind_broadcasts: bool) -> bool:
    """Whether the actor's weights are late: four broadcasts behind, or (actor.weights_download) no download
    finished for three periods plus the last one's own length."""
    if not actor.config.actor.weights_download:
        return behind_broadcasts
    late_after = 3 * actor.config.actor.weights_download_period_s + actor.weights_download_s
    return time.monotonic() - actor.weights_downloaded_at > late_after


def _await_replays_word(mailbox: Mailbox, stop: threading.Event) -> bool:
    """Waits for the replay's first rate message, which says whether updates have started: until then
    an actor cannot tell a fresh run (act at random) from a resumed one (wait for the policy). False if
    stopped first."""
    waiting = Every(REPLAY_WAIT_LOG_S)
    while not mailbox.heard_rate.wait(timeout=0.1):
        if stop.is_set():
            return False
        if waiting.due():
            log.info("waiting for the replay's word on replay/rate before the first episode")
    return True


def _fetch_latest_weights(link: HubLink, keys: Keys, actor: Actor, stop: threading.Event) -> None:
    """Asks the learner for its latest weights, and again while none have come by any way."""
    mailbox = actor.mailbox
    while not stop.is_set() and not mailbox.had_weights.is_set():
        reply = request(link.session, keys.weights_latest, None, LATEST_WEIGHTS_TIMEOUT_S)
        if reply is not None:
            mailbox.offer_latest(reply)
        stop.wait(LATEST_WEIGHTS_RETRY_S)


def _download_weights(link: HubLink, keys: Keys, actor: Actor, stop: threading.Event) -> None:
    """actor.weights_download: the learner's latest weights, piece by piece, every period (sooner while
    none have come)."""
    def ask(message: WeightsPieceAsk) -> WeightsPiece | None:
        return request(link.session, keys.weights_pieces, message, LATEST_WEIGHTS_TIMEOUT_S, expected=WeightsPiece)

    while not stop.is_set():
        began = time.monotonic()
        try:
            weights = download_weights(ask, stop)
        except WireError as error:
            actor.rejections.reject("weights_download", f"downloaded weights: {error}")
            weights = None
        if weights is not None:
            actor.mailbox.offer_weights(weights)
            actor.weights_downloaded_at = time.monotonic()
            actor.weights_download_s = actor.weights_downloaded_at - began
            actor.weights_downloads += 1
        stop.wait(actor.config.actor.weights_download_period_s if weights is not None else LATEST_WEIGHTS_RETRY_S)


def _drive(actor: Actor, stop: threading.Event, max_episodes: int | None, outbox: Outbox, link: HubLink) -> None:
    report = Every(actor.config.actor.log_period_s)
    may_start = EpisodeGate(actor.mailbox, HoldLog(HOLD_LOG_S),
                            lambda: max_episodes is None or actor.episodes_started < max_episodes,
                            actor.uses_network)
    steps = 0
    returns: list[float] = []
    while not stop.is_set() and (max_episodes is None or actor.episode_index < max_episodes):
        ended = actor.step(may_start)
        if not ended and not actor.running:
            stop.wait(0.01)  # every simulator is held
        for episode, record in ended:
            # A full outbox holds every simulator here: the replay is gone, not just behind.
            if not outbox.offer(episode, stop):
                return
            try:
                link.put("records", record)
            except zenoh.ZError:  # a session reopened meanwhile: one record lost, driving goes on
                log.debug("an episode record was not published", exc_info=True)
            steps += record.length
            returns.append(record.episode_return)
            if report.due():
                log.info("episodes %d, steps %d, mean return %.2f, weights v%d, epsilon %.3f; %d sent, %d waiting, "
                         "%d rejected messages", actor.episode_index, steps, float(np.mean(returns)),
                         actor.weights_version, record.epsilon, outbox.sent, len(outbox), actor.rejections.total)
                returns.clear()
