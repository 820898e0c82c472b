"""The replay's admission of a trace-batch request: what refuses one (its type, its size, the updates it
states), and the log lines of what the updates a request states changed in the rate limiter's counts."""

from __future__ import annotations

import logging

from common.wire.messages import TraceBatchRequest

log = logging.getLogger("replay")


def request_fault(request, trace_length: int, max_batch: int, max_updates: int) -> tuple[str, str] | None:
    """(kind, text) of the fault that refuses the request, or None: it asks for what the replay serves and
    states no more updates than the run's budget pays for (common/pacing.updates_ceiling)."""
    if not isinstance(request, TraceBatchRequest):
        return "request_wrong_type", f"a {type(request).__name__} on replay/sample, not a TraceBatchRequest"
    if request.trace_length != trace_length or not 0 < request.batch_size <= max_batch:
        return "request_size", (f"a request for {request.batch_size} traces of {request.trace_length} steps "
                                f"(serving up to {max_batch} traces of {trace_length} steps)")
    if request.learner_updates > max_updates:
        return "request_updates", (f"a request stating {request.learner_updates} learner updates, more than the "
                                   f"run's budget pays for ({max_updates})")
    return None


def log_recounted(updates: int, lost: int, gained: int, unreceived: int, stock: int) -> None:
    """One line for each count a learner's stated updates changed (RateLimiter.on_learner_start and
    on_learner_updates): batches owed again, or counted served."""
    if lost:
        log.info("a learner starts from %d updates: the %d batches served beyond them were lost with "
                 "the learner that died, and are owed again", updates, lost)
    if gained:
        log.info("the learner has made %d updates, %d more than this replay counted served (lost with its "
                 "counters when it died): counted served", updates, gained)
    if unreceived:
        log.warning("the learner has made %d updates and can hold %d batches more, but %d more were served: "
                    "their replies never reached it; owed again", updates, stock, unreceived)
