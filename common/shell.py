"""The shell of every process of a run that holds a Zenoh session: actor, learner, replay, recorder.

Each of them starts the same way and ends the same way; only the middle is its own:

    shell = Shell("replay", config)      # log lines, stop on SIGINT/SIGTERM, the run's keys
    ...                                      # the role's own set-up, which may take a while
    with shell.session() as session:       # the session, and the token <run>/alive/replay/0
        episodes = subscribe(session, shell.keys.episodes, on_episode)
        shell.on_close(episodes.undeclare)
        while not shell.stop.wait(1.0):
            ...
    # however the block was left: stop set, on_close callbacks run, the token undeclared, session closed

The token is declared only once the role is set up, so that its peers, which watch it, see
the role alive when it is ready. One process holds a token at a time: a second learner or replay
of a run, or a second actor of one id, is refused (a line in the log, exit code 1), as two would
split the run between them. A killed holder's token lingers until Zenoh's lease ends, so the
newcomer waits that long for it to go before it gives up. Two that find the token free at the same
moment each declare a claim, <token>/claim/<zid>, for a second; the lower zid goes on, the other
waits. A role with state in the run folder calls claim() first, which opens the session and waits
then, so that it reads the checkpoint or snapshot a stopping holder wrote last:

    shell = Shell("learner", config)
    shell.claim()                          # the session, once no other learner holds the token
    ...                                      # read the checkpoint
    with shell.session() as session:       # the same session, now with the token

A session that cannot open (a bad endpoint, a port in use, no router, a missing TLS file) is
one line in the log and exit code 1, not a traceback. A role's module ends with run_main(main), which
ends the process without the interpreter's finalization, where Zenoh's threads could abort it.
"""

from __future__ import annotations

import argparse
import atexit
import contextlib
import logging
import os
import re
import signal
import sys
import threading
import time
from typing import Callable, Iterator

import zenoh

from common.config import Config
from common.config_cli import add_config_arguments, parse_config_or_exit, print_config
from common.disk_space import DISK_FULL_EXIT, is_disk_full
from common.malloc_trim import keep_releasing_free_heap
from common.log_streams import tolerate_full_disk
from common.logs import setup_logging
from common.liveliness import alive_keys, declare_liveliness
from common.transport import Declared, open_session
from common.keys import Keys

log = logging.getLogger(__name__)

_RUST_SOURCE = re.compile(r" at \S+\.rs:\d+\.?")  # where in Zenoh's code an error arose: noise to a user


def parse_service_args(parser: argparse.ArgumentParser, argv: list[str] | None = None
                       ) -> tuple[argparse.Namespace, Config]:
    """A role's command line: its own flags (on parser) and the config's; the resolved config goes
    to stderr first, so that every log starts with what the process ran with."""
    add_config_arguments(parser)
    args, config = parse_config_or_exit(parser, argv)
    print_config(parser.prog, config)
    return args, config


SOLE_WAIT_S = 15.0  # Zenoh's lease (10 s) and a margin: a token whose holder was killed is gone by then
CLAIM_SETTLE_S = 1.0  # how long a claim takes to reach every peer, with a wide margin (a router hop: ms)
PARENT_ENV = "D3RQN_STOP_WITH_PARENT"  # a parent's pid (the stack's for its roles, the main job's for its stack)
PARENT_POLL_S = 1.0


def run_main(main: Callable[[], int | str | None]) -> None:
    """Runs the main() of a process that held a Zenoh session (a role, the stack, an evaluation following a
    run), then ends the process as soon as its exit handlers have run, skipping the
    interpreter's finalization. Zenoh's threads may still be letting go of a callback then, which takes
    the GIL; a finalizing interpreter answers with a thread exit that unwinds through Rust, and the
    process aborts ("FATAL: exception not rethrown", exit code -6 instead of 0): seen in about one stop
    in twenty of an actor that had reopened its session. Its log lines cannot end it on a full disk
    (common/log_streams.py), and an exception of a full disk ends it with DISK_FULL_EXIT, which the stack
    answers by waiting for space; any other uncaught exception ends it the usual way."""
    tolerate_full_disk()
    try:
        returned = main()
    except SystemExit as exit_:
        returned = exit_.code
    except Exception as error:  # noqa: BLE001 - only a full disk's is answered here
        if not is_disk_full(error):
            raise
        log.error("stopping: the disk is full (%s)", error, exc_info=True)
        returned = DISK_FULL_EXIT
    if isinstance(returned, str):
        print(returned, file=sys.stderr)
    code = returned if isinstance(returned, int) else 0 if returned is None else 1
    threading._shutdown()  # as the interpreter does first: ends idle executors, joins the non-daemon threads
    atexit._run_exitfuncs()  # logging's flush and our own handlers, while threads may still take the GIL
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    os._exit(code)


def env_stopping_with_this() -> dict[str, str]:
    """The environment for a child that is to stop once this process is gone (stop_with_parent)."""
    return {**os.environ, PARENT_ENV: str(os.getpid())}


def stop_with_parent(stop: threading.Event, expected: int | None = None,
                     then: Callable[[], None] | None = None) -> threading.Thread | None:
    """Sets `stop` (with a log line), then calls `then`, once the process that started this one is gone, when
    that process asked for it (PARENT_ENV holds its pid): a stack killed or crashed leaves no role running on
    its own, a grid runner killed no stack or evaluation."""
    if expected is None:
        value = os.environ.get(PARENT_ENV, "")
        expected = int(value) if value.isdigit() else None
    if expected is None:
        return None

    def watch() -> None:
        while not stop.wait(PARENT_POLL_S):
            if os.getppid() != expected:
                log.warning("the process that started this one (pid %d) is gone: stopping", expected)
                stop.set()
                if then is not None:
                    then()

    thread = threading.Thread(target=watch, name="parent-watch", daemon=True)
    thread.start()
    return thread


def interrupt_main() -> None:
    """From any thread: interrupts the main thread as a Ctrl-C would (a real SIGINT to it, which ends a wait at
    once), or, where this process ignores SIGINT (the background job of a script), exits at once. For a
    process with no stop event to set (evaluate, the soak) whose parent is gone (stop_with_parent)."""
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        signal.pthread_kill(threading.main_thread().ident, signal.SIGINT)
        return
    with contextlib.suppress(OSError):  # its stderr may have been a pipe to the process now gone
        print("the process that started this one is gone; stopping", file=sys.stderr, flush=True)
    os._exit(1)


def on_stop_signals(handler) -> dict:
    """Sets handler on SIGINT, SIGTERM and SIGHUP (a closed terminal), each a request to stop cleanly, and
    returns the handlers it replaced. A SIGHUP ignored at the start stays ignored: `nohup` asked for it."""
    hangup_ignored = signal.getsignal(signal.SIGHUP) == signal.SIG_IGN
    return {signum: signal.signal(signum, handler) for signum in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
            if not (signum == signal.SIGHUP and hangup_ignored)}


def stop_on_signals() -> threading.Event:
    """An event that the stop signals set (on_stop_signals): the process finishes what it does and stops
    cleanly."""
    stop = threading.Event()
    on_stop_signals(lambda *_: stop.set())
    return stop


class Shell:
    """One process of a run: its log, its stop event, its keys and, within session(), its session.

    The process's log lines say `role` (`role-<process_id>` when an id is given, as actors have);
    its liveliness token is <run>/alive/<role>/<process_id or 0>, which only one process holds unless
    `sole` is False (recorders: several may listen).
    """

    def __init__(self, role: str, config: Config, process_id: int | str | None = None, sole: bool = True) -> None:
        self.role = role
        self.sole = sole
        self.config = config
        self.process_id = "0" if process_id is None else str(process_id)
        setup_logging(role if process_id is None else f"{role}-{process_id}")
        self.stop = stop_on_signals()
        stop_with_parent(self.stop)
        keep_releasing_free_heap(self.stop)  # a role holds its peak for good otherwise (common/malloc_trim.py)
        self.keys = Keys(config.transport.namespace, config.run.name)
        self._closing: contextlib.ExitStack | None = None
        self._held: tuple[zenoh.Session, Declared] | None = None  # the open session and its token
        self._held_lock = threading.Lock()
        self._claimed: zenoh.Session | None = None  # opened by claim(), for session() to go on with
        self._claim_token: Declared | None = None  # <token>/claim/<zid>, from the check until the token is up

    def claim(self) -> None:
        """Opens the session now and, unless `sole` is False, waits until no other process holds this
        process's token (exit code 1 where one keeps it). session() goes on with this session."""
        if self._claimed is None:
            self._claimed = self._connect(SystemExit, self.sole)
            atexit.register(self._drop_claim)  # a role that fails before session() still closes it

    @contextlib.contextmanager
    def session(self) -> Iterator[zenoh.Session]:
        """The open session with the process's liveliness token; on leaving, by any path, sets
        stop, runs the on_close callbacks, undeclares the token and closes the session (the one
        reopen() gave last, if it did)."""
        with contextlib.ExitStack() as closing:
            self._held = opened = self._open(SystemExit, self.sole)
            closing.callback(self._close_held)
            self._closing = closing
            try:
                yield opened[0]
            finally:
                with self._held_lock:
                    self._closing = None
                self.stop.set()  # first: the role's threads stop using the session before it closes

    def reopen(self, declare: Callable[[zenoh.Session], object]) -> bool:
        """A fresh session with the token in place of the one held, for a session that no longer hears its
        peers: declare(fresh) declares on it what was declared on the old one, which closes after that.
        False, with a log line, where none opens now (the old one stays) or the session() block is over."""
        with self._held_lock:
            if self._closing is None:
                return False
            fresh = self._open(None)
            if fresh is None:
                return False
            try:
                declare(fresh[0])
            except Exception:
                _close_quietly(*fresh)
                raise
            stale, self._held = self._held, fresh
        _close_quietly(*stale)
        return True

    def on_close(self, callback: Callable[[], object]) -> None:
        """Has the session's end call callback (an undeclare, or telling threads to finish), before
        the token goes and the session closes; the latest given runs first."""
        if self._closing is None:
            raise RuntimeError("on_close() belongs inside `with shell.session()`")
        self._closing.callback(callback)

    def _close_held(self) -> None:
        with self._held_lock:
            held, self._held = self._held, None
        if held is not None:
            _close_quietly(*held)

    def _drop_claim(self) -> None:
        claimed, self._claimed = self._claimed, None
        if claimed is not None:
            claimed.close()

    def _open(self, failure, sole: bool = False) -> tuple[zenoh.Session, Declared] | None:
        """A session with the token (the claimed one, if any); None where it cannot open (a line in the log),
        or `failure` raised. With `sole`, also where another process holds the token past SOLE_WAIT_S."""
        session, self._claimed = self._claimed, None
        if session is None:
            session = self._connect(failure, sole)
        if session is None:
            return None
        token = declare_liveliness(session, self.keys.liveliness(self.role, self.process_id))
        claim, self._claim_token = self._claim_token, None
        if claim is not None:
            claim.undeclare()  # the token itself now keeps newcomers out
        return session, token

    def _connect(self, failure, sole: bool) -> zenoh.Session | None:
        """An open session without the token, as _open() says."""
        transport = self.config.transport
        try:
            session = open_session(transport)
        except (zenoh.ZError, FileNotFoundError) as error:  # a bad endpoint, a port in use, no router; a TLS file
            log.error("cannot open the Zenoh session (mode %s, listen %s, connect %s): %s", transport.mode,
                      ", ".join(transport.listen) or "none", ", ".join(transport.connect) or "none",
                      _RUST_SOURCE.sub("", str(error)))
            if failure is not None:
                raise failure(1) from None
            return None
        log.info("Zenoh session %s open (Zenoh's own errors name it so)", session.zid())
        if sole and not self._token_free(session, self.keys.liveliness(self.role, self.process_id)):
            session.close()
            if failure is not None:
                raise failure(1)
            return None
        return session

    def _token_free(self, session: zenoh.Session, token: str) -> bool:
        """Whether no other process holds the token, waiting up to SOLE_WAIT_S for one to let it go. Two processes
        that find it free at the same moment each declare <token>/claim/<zid>, and the lower zid goes on."""
        deadline = time.monotonic() + SOLE_WAIT_S
        waited = False
        while _held_elsewhere(session, token) or not self._won_claim(session, token):
            if time.monotonic() >= deadline or self.stop.is_set():
                other = "another --actor.actor_id" if self.role == "actor" else "another --run.name"
                log.error("another process holds %s: one %s per token, or they would split the run between them. "
                          "Stop that one, or start this one with %s", token, self.role, other)
                return False
            if not waited:
                log.warning("another process holds %s; waiting up to %.0f s for it to go (a killed one's token "
                            "lasts until Zenoh's lease ends)", token, SOLE_WAIT_S)
                waited = True
            self.stop.wait(1.0)
        return True

    def _won_claim(self, session: zenoh.Session, token: str) -> bool:
        """Declares this process's claim on a free token, lets it settle and keeps it where no other process
        holds the token or claims it with a lower zid; otherwise withdraws it."""
        claim = declare_liveliness(session, f"{token}/claim/{session.zid()}")
        self.stop.wait(CLAIM_SETTLE_S)
        if _held_elsewhere(session, token, own_claim=claim.key):
            claim.undeclare()
            return False
        self._claim_token = claim
        return True


def _held_elsewhere(session: zenoh.Session, token: str, own_claim: str | None = None) -> bool:
    """Whether another process holds the token or claims it (first_claim); False (a log line) where the session
    cannot say: the check must not stop a role."""
    try:
        alive = alive_keys(session, f"{token}/**", timeout_s=2.0)  # the token and the claims on it
    except zenoh.ZError as error:
        log.warning("cannot ask whether another process holds %s (%s); going on", token, _RUST_SOURCE.sub("", str(error)))
        return False
    return not first_claim(alive, token, own_claim)


def first_claim(alive: list[str], token: str, own_claim: str | None) -> bool:
    """Whether this process may take the token, given the live keys under it: none but its own claim, or other
    claims only, each with a higher zid. Without a claim of its own, any key under the token is another's."""
    others = set(alive) - {own_claim}
    if own_claim is None or token in others:
        return not others
    own = _claim_rank(own_claim)
    return all((rank := _claim_rank(key)) is not None and own is not None and rank > own for key in others)


def _claim_rank(key: str) -> int | None:
    """The zid of a <token>/claim/<zid> key as a number; None for any other key."""
    head, _, zid = key.rpartition("/claim/")
    try:
        return int(zid, 16) if head and zid else None
    except ValueError:
        return None


def _close_quietly(session: zenoh.Session, token: Declared) -> None:
    """Undeclares the token and closes the session; a failure is a log line (a broken session may refuse)."""
    try:
        token.undeclare()
        session.close()
    except Exception as error:  # noqa: BLE001 - closing must not stop the process
        log.warning("closing the Zenoh session: %s", error)
