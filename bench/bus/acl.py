"""Who may say what on the bus: the Zenoh access-control table, from one place.

Each bench identity (the CN of its certificate, see certs.py) has a `Role`: the topics it
publishes, the topics it subscribes to, and the CAN channels it is attached to. A new topic is
one entry in ROLES. `access_control_config()` turns the table into Zenoh's `access_control`
section, deny by default, which every secure session carries (nodes, the launcher's hub, a
router), so every process enforces the table on each of its links:

- ingress (what a remote identity sends to us): its puts only on its own publications, its
  subscriber declarations only on its own subscriptions, its presence queryable (liveliness,
  readiness and clock: bench/bus/presence.py) only `presence/<cn>`, a liveliness token only the
  launcher's `alive/launcher` and the CAN transport's members;
- egress (what we send to a remote identity): puts only on what it subscribes to, so the
  estimator never receives `truth` unless its role reads it, and a rogue cannot subscribe its way
  to the commands.

Declarations going out (our subscribers, queryables, tokens) and liveliness queries are allowed
towards every identity of the deployment: they say what we listen to, not what we say, and a
router must forward them for the topics to match. A link with no certificate of the deployment's
CA matches no subject and gets the default: deny.

Key expressions are `bench/*/<topic>` so one table serves every run id (a router outlives runs).
Zenoh allows a message when a rule's key expression *includes* the message's (authorization.rs,
`nodes_including`), so a wildcard subscription such as the recorder's `bench/<run>/**` needs a
rule with `**`.
"""
from __future__ import annotations

from dataclasses import dataclass

from bench.bus import keys
from bench.bus.can.config import CanConfig
from bench.bus.presence import PRESENCE

ANY_RUN = "*"
NOT_NODES = ("router", "launcher", "operator")    # identities that publish no stats of their own


@dataclass(frozen=True)
class Role:
    """What one identity may do. Topics are relative to `bench/<run_id>/`."""

    publishes: tuple[str, ...] = ()
    subscribes: tuple[str, ...] = ()
    can_channels: tuple[str, ...] = ()   # CAN frames over Zenoh: bench/<run>/can/<channel>
    # Command channels (queries, bench/bus/fault_command.py): the ones it may ask, the ones it answers.
    asks: tuple[str, ...] = ()
    answers: tuple[str, ...] = ()


_CAN = CanConfig()
# The bench's identities. The nodes are those of bench.runtime.node.NODES; `launcher` is the hub
# session of `bench run` (progress, stats, liveliness); `router` forwards everything it is allowed
# to forward and says nothing itself. Attitude-loop topics join here as they are built.
ROLES: dict[str, Role] = {
    "plant": Role(
        publishes=(keys.TRUTH, "truth/*", "sense/*", keys.COMMAND_APPLIED, keys.EVENT_DEADLINE, keys.STATUS_STEP),
        subscribes=("command/*", keys.ACTUATOR_MTQ),
    ),
    "estimator": Role(
        publishes=("estimate/*",),
        # truth: the estimator's `truth` mode is the seeds' "full state knowledge" case
        # (`truth/attitude` for the attitude loop).
        subscribes=("sense/*", keys.TRUTH, "truth/*", keys.COMMAND_THRUST),
    ),
    "controller": Role(
        publishes=("command/*", keys.EVENT_DEADLINE, keys.EVENT_CAN, keys.CAN_STEP_FLIGHT),
        subscribes=("estimate/*", "plan/*", keys.CAN_STEP_BUS),
        can_channels=(_CAN.flight_channel,),   # the magnetorquer driver lives in the controller
    ),
    # MILQR plans from the attitude estimate; it commands nothing itself.
    "planner": Role(publishes=(keys.PLAN_ATTITUDE,), subscribes=(keys.ESTIMATE_ATTITUDE,)),
    # It takes live hardware faults from canbus's event/fault (bench/bus/can/live_faults.py).
    "mtq": Role(publishes=(keys.ACTUATOR_MTQ,), subscribes=(keys.EVENT_FAULT,), can_channels=(_CAN.board_channel,)),
    # In lock-step with the bus on simulated time the board runs inside canbus (sim_window.py).
    # It answers the live fault-injection channel (the injector is its own) and publishes every fault's window.
    "canbus": Role(publishes=(keys.CAN_STEP_BUS, keys.ACTUATOR_MTQ, keys.EVENT_FAULT), subscribes=(keys.CAN_STEP_FLIGHT,),
                   can_channels=(_CAN.flight_channel, _CAN.board_channel), answers=(keys.CONTROL_FAULT,)),
    "recorder": Role(subscribes=("**",)),
    # `bench run --live` (bench/live/node.py): reads what the recorder reads, and forwards the live
    # view's fault-injection service calls to canbus.
    "live": Role(subscribes=("**",), asks=(keys.CONTROL_FAULT,)),
    # `bench inject` (bench/live/inject_cli.py): an operator's terminal; asks canbus for a fault, nothing else.
    "operator": Role(asks=(keys.CONTROL_FAULT,)),
    "launcher": Role(subscribes=(keys.STATUS_STEP, f"{keys.STATUS_STATS}/*")),
    "router": Role(),
}

# Every message kind Zenoh's ACL knows (DEFAULT_CONFIG.json5 of zenoh 1.10).
_DECLARATIONS = ["declare_subscriber", "declare_queryable", "liveliness_token", "declare_liveliness_subscriber",
                 "liveliness_query"]


def _k(topic: str) -> str:
    return keys.key(ANY_RUN, topic)


def _own_stats(name: str) -> str:
    return f"{keys.STATUS_STATS}/{name}"


def publications(name: str) -> list[str]:
    role = ROLES[name]
    topics = list(role.publishes)
    if name not in NOT_NODES:
        topics.append(_own_stats(name))      # every node publishes its own counters at the end
    topics += [f"can/{ch}" for ch in role.can_channels]
    return topics


def subscriptions(name: str) -> list[str]:
    role = ROLES[name]
    return list(role.subscribes) + [f"can/{ch}" for ch in role.can_channels]


def _own_tokens(name: str) -> list[str]:
    # The launcher's token only hints that it left (nodes on other hosts then ask its presence at
    # once); every other sign of life is a signed presence answer.
    tokens = [f"{keys.ALIVE}/{name}"] if name == "launcher" else []
    return tokens + [f"can/{ch}/member/*" for ch in ROLES[name].can_channels]


def _rule(rule_id: str, flow: str, messages: list[str], topics: list[str]) -> dict:
    return {"id": rule_id, "permission": "allow", "flows": [flow], "messages": messages,
            "key_exprs": sorted({_k(t) for t in topics})}


def _rules_for(name: str) -> list[dict]:
    """Allow-rules for the remote identity `name` (deny is the default)."""
    rules = []
    pubs, subs = publications(name), subscriptions(name)
    presence = f"{PRESENCE}/{name}"
    if pubs:
        rules.append(_rule(f"{name}-sends", "ingress", ["put", "delete"], pubs))
    if subs:
        rules.append(_rule(f"{name}-receives", "egress", ["put", "delete"], subs))
        rules.append(_rule(f"{name}-subscribes", "ingress", ["declare_subscriber"], subs))
    if role_of(name).asks:
        # A command channel (bench/bus/fault_command.py): its queries in, the answers back to it.
        rules.append(_rule(f"{name}-commands", "ingress", ["query"], list(role_of(name).asks)))
        rules.append(_rule(f"{name}-commands-answered", "egress", ["reply"], list(role_of(name).asks)))
    if role_of(name).answers:
        rules.append(_rule(f"{name}-command-queryable", "ingress", ["declare_queryable", "reply"],
                           list(role_of(name).answers)))
        rules.append(_rule(f"{name}-command-asked", "egress", ["query"], list(role_of(name).answers)))
    if name != "router":
        # Every process answers presence queries on its own key only, and may ask the others
        # (the launcher and the plant watch their peers, the recorder pings their clocks, a node
        # on another host watches the launcher). The answers are signed besides (presence.py).
        rules.append(_rule(f"{name}-presence", "ingress", ["declare_queryable", "reply"], [presence]))
        rules.append(_rule(f"{name}-asked", "egress", ["query"], [f"{PRESENCE}/*"]))
        rules.append(_rule(f"{name}-asks", "ingress", ["query"], [f"{PRESENCE}/*"]))
        rules.append(_rule(f"{name}-answered", "egress", ["reply"], [f"{PRESENCE}/*"]))
        if _own_tokens(name):
            rules.append(_rule(f"{name}-tokens", "ingress", ["liveliness_token"], _own_tokens(name)))
        rules.append(_rule(f"{name}-watches", "ingress", ["declare_liveliness_subscriber", "liveliness_query"],
                           [f"{keys.ALIVE}/launcher", "can/*/member/*"]))
    # What we tell this identity about ourselves: declarations and liveliness, never data.
    rules.append(_rule(f"{name}-told", "egress", _DECLARATIONS, ["**"]))
    return rules


def role_of(name: str) -> Role:
    return ROLES[name]


def access_control_config(names: list[str] | None = None) -> dict:
    """Zenoh's `access_control` section: deny by default, each identity its own rules."""
    names = list(names or ROLES)
    unknown = [n for n in names if n not in ROLES]
    if unknown:
        raise ValueError(f"no access-control role for {', '.join(unknown)} (add it to bench.bus.acl.ROLES)")
    rules, subjects, policies = [], [], []
    for name in names:
        own = _rules_for(name)
        rules += own
        subjects.append({"id": f"cn-{name}", "cert_common_names": [name]})
        policies.append({"id": f"policy-{name}", "rules": [r["id"] for r in own], "subjects": [f"cn-{name}"]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}


def identities() -> list[str]:
    return list(ROLES)
