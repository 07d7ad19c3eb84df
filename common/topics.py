"""The bus's key space: the one table of topics, who writes and reads each, and one key
builder per kind of key.

    vamppi/<vehicle>/<service>/<topic>                        data (TOPICS)
    vamppi/<vehicle>/<service>/heartbeat                      every instance's beat
    vamppi/<vehicle>/alive/<service>/<instance>               liveliness token
    vamppi/<vehicle>/admin/<service>/<instance>/health        queryable (JSON counters)
    vamppi/<vehicle>/admin/<service>/<instance>/config        queryable (JSON config)
    vamppi/<vehicle>/admin/<service>/<instance>/clock         queryable: its wall clock
    vamppi/<vehicle>/admin/<service>/<instance>/latest/<topic>  queryable: the newest
                                                              message of a topic it holds

Pure data and string functions: the bus (common.bus) and the access-control rules
(common.security) both derive from it.
"""

from __future__ import annotations

PREFIX = "vamppi"

# topic name -> (owning service, message schema name); the one table of topics
TOPICS: dict[str, tuple[str, str]] = {
    "state": ("plant", "vamppi.State"),
    "events": ("plant", "vamppi.Event"),
    "clock": ("plant", "vamppi.Clock"),
    "depth": ("sensor", "vamppi.Depth"),
    "map": ("mapper", "vamppi.Map"),
    "cmd": ("planner", "vamppi.Cmd"),
    "plan": ("planner", "vamppi.Plan"),
    "stats": ("planner", "vamppi.Stats"),
    "shadow": ("planner", "vamppi.Plan"),           # a candidate's plans before it drives
    "handover": ("planner", "vamppi.Handover"),
}
SERVICES = ("plant", "sensor", "mapper", "planner")
# what each service reads (TOPICS names what it writes)
INPUTS: dict[str, tuple[str, ...]] = {"plant": ("cmd", "handover"), "sensor": ("state",),
                                      "mapper": ("depth",),
                                      "planner": ("state", "map", "cmd", "handover")}
HEARTBEAT = "heartbeat"
REPLAY_SOURCE = "replay"     # `vamppi replay` beats as this service (heartbeat_key)
# topics whose publisher keeps what it sent for `RECOVERY_S` (zenoh-ext advanced publishers):
# a subscriber that missed samples of them (a cut link) fetches them late
CACHED: dict[str, str] = {"state": "plant", "clock": "plant", "events": "plant"}
RECOVERY_S = 30.0


def topic_key(vehicle: str, topic: str) -> str:
    service, _ = TOPICS[topic]
    return f"{PREFIX}/{vehicle}/{service}/{topic}"


def heartbeat_key(vehicle: str, service: str = "*") -> str:
    return f"{PREFIX}/{vehicle}/{service}/{HEARTBEAT}"


def alive_key(vehicle: str, service: str = "*", instance: str = "*") -> str:
    return f"{PREFIX}/{vehicle}/alive/{service}/{instance}"


def admin_key(vehicle: str, service: str, instance: str, what: str) -> str:
    return f"{PREFIX}/{vehicle}/admin/{service}/{instance}/{what}"


def latest_key(vehicle: str, service: str, instance: str, topic: str) -> str:
    return admin_key(vehicle, service, instance, f"latest/{topic}")


def launcher_key(vehicle: str) -> str:
    """Requests to `vamppi up`'s launcher (JSON: spawn or stop a service instance)."""
    return f"{PREFIX}/{vehicle}/admin/launcher/0/requests"


def topic_of(key: str) -> str:
    """`vamppi/<vehicle>/<service>/<topic>` -> topic ('' for other keys)."""
    parts = key.split("/")
    return parts[3] if len(parts) == 4 and parts[0] == PREFIX and parts[3] in TOPICS else ""


def key_matches(pattern: str, key: str) -> bool:
    """Whether a concrete `key` matches a key expression with `*` (one chunk) and `**` (any
    number of chunks), as zenoh matches them."""
    def match(p: list[str], k: list[str]) -> bool:
        if not p:
            return not k
        if p[0] == "**":
            return any(match(p[1:], k[i:]) for i in range(len(k) + 1))
        return bool(k) and (p[0] == "*" or p[0] == k[0]) and match(p[1:], k[1:])
    return match(pattern.split("/"), key.split("/"))


# ----------------------------------------------------------------------------- transports
