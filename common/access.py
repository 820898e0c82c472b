"""Who may do what on a locked-down cluster: the Zenoh access-control block of the router.

Every process but the router connects as a client over mutual TLS, so every message of a
run crosses one of the router's links, and the router knows each link's peer by the
common name (CN) of the certificate it presented. `acl_config` turns the role lists of
TransportConfig (`acl_learners`, `acl_actors`, `acl_replays`, `acl_observers`: CNs) into
Zenoh's ``access_control`` block, deny by default:

- only a learner publishes weights and exploration state, and serves ``weights/latest`` and
  ``weights/pieces`` (the download of actor.weights_download);
- only an actor publishes episodes;
- only a replay answers trace-batch queries (``replay/sample``) and publishes the replay's
  stats, rate and episode acknowledgements; when the replay is the router itself (the cluster set-up), its own session
  is not behind a link, so no peer may do either;
- only a learner may draw trace batches (a batch drawn counts against the rate limiter);
- an observer (the flight recorder, a monitor) reads everything and writes only its own
  metrics and liveliness token;
- a peer whose CN is in no list may do nothing at all.

The router applies a rule on the way in (ingress: what a peer sends) and on the way out
(egress: what it forwards to a peer). A role that publishes a key must also learn of the
subscribers on it (Zenoh sends a publication only where a subscriber is declared), so every
role may receive declarations of subscribers, queryables and liveliness tokens: they carry
no data.
"""

from __future__ import annotations

from dataclasses import dataclass

ROLES = ("learner", "actor", "replay", "observer")


@dataclass(frozen=True)
class Grants:
    """What a role may do, as key expressions relative to ``<namespace>/<any run>/``."""

    publish: tuple[str, ...] = ()  # put
    subscribe: tuple[str, ...] = ()  # declare a subscriber and receive the puts
    serve: tuple[str, ...] = ()  # declare a queryable, receive the queries, reply
    query: tuple[str, ...] = ()  # send queries and receive the replies
    token: tuple[str, ...] = ()  # declare liveliness tokens


GRANTS: dict[str, Grants] = {
    "learner": Grants(
        publish=("weights/broadcast", "exploration", "metrics/learner/**"),
        subscribe=("replay/stats", "replay/rate"),
        serve=("weights/latest", "weights/pieces"),
        query=("replay/sample",),
        token=("alive/learner/**",)),
    "actor": Grants(
        publish=("episodes", "metrics/actor/**", "metrics/actor_stats/**"),
        subscribe=("weights/broadcast", "exploration", "replay/rate", "replay/acks/**"),
        query=("weights/latest", "weights/pieces"),
        token=("alive/actor/**",)),
    "replay": Grants(  # a replay that is not the router
        publish=("replay/stats", "replay/rate", "replay/acks/**", "metrics/replay/**"),
        subscribe=("episodes", "exploration"),
        serve=("replay/sample",),
        token=("alive/replay/**",)),
    "observer": Grants(
        publish=("metrics/recorder/**",),
        subscribe=("**",),
        query=("weights/latest",),  # `evaluate` against a live learner
        token=("alive/recorder/**",)),
}


def _rules_of(role: str, grants: Grants, run: str) -> list[dict]:
    """Allow rules for one role; ``run`` is ``<namespace>/*``."""
    keys = lambda names: [f"{run}/{name}" for name in names]  # noqa: E731
    rules: list[tuple[str, list[str], list[str], tuple[str, ...]]] = [
        ("publish", ["ingress"], ["put"], grants.publish),
        ("subscribe", ["ingress"], ["declare_subscriber"], grants.subscribe),
        ("receive", ["egress"], ["put"], grants.subscribe),
        ("serve", ["ingress"], ["declare_queryable", "reply"], grants.serve),
        ("be-asked", ["egress"], ["query"], grants.serve),
        ("ask", ["ingress"], ["query"], grants.query),
        ("hear", ["egress"], ["reply"], grants.query),
        ("token", ["ingress"], ["liveliness_token"], grants.token),
    ]
    return [{"id": f"{role}-{name}", "permission": "allow", "flows": flows, "messages": messages,
             "key_exprs": keys(names)}
            for name, flows, messages, names in rules if names]


def acl_config(namespace: str, common_names: dict[str, list[str]]) -> dict:
    """Zenoh's ``access_control`` block: the GRANTS of each role, for the peers whose certificate
    common name is in ``common_names[role]``; everything else is denied."""
    unknown = set(common_names) - set(ROLES)
    if unknown:
        raise ValueError(f"unknown roles {sorted(unknown)}; roles are {', '.join(ROLES)}")
    run = f"{namespace}/*"
    shared = [  # every known peer: declarations (no data) and watching liveliness
        {"id": "any-declarations", "permission": "allow", "flows": ["egress"],
         "messages": ["declare_subscriber", "declare_queryable", "liveliness_token"],
         "key_exprs": [f"{namespace}/**"]},
        {"id": "any-liveliness", "permission": "allow", "flows": ["ingress"],
         "messages": ["declare_liveliness_subscriber", "liveliness_query"],
         "key_exprs": [f"{run}/alive/**"]},
    ]
    rules, subjects, policies = list(shared), [], []
    for role in ROLES:
        names = [name for name in common_names.get(role, ()) if name]
        if not names:
            continue
        own = _rules_of(role, GRANTS[role], run)
        rules.extend(own)
        subjects.append({"id": role, "cert_common_names": names})
        policies.append({"id": role, "subjects": [role], "rules": [rule["id"] for rule in shared + own]})
    if not subjects:  # Zenoh refuses empty lists; with no role at all, deny everything
        subjects = [{"id": "nobody", "cert_common_names": ["-"]}]
        policies = [{"id": "nobody", "subjects": ["nobody"], "rules": [shared[0]["id"]]}]
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}
