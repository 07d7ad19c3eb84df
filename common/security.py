"""Who may do what on the bus: each role's manifest, zenoh's access-control rules generated
from it, and the mutual-TLS settings of a role's session.

One place: the manifests are derived from the topic table in `common.bus` (TOPICS names
what each service publishes, INPUTS what it reads) and its key builders, never restated.
A certificate's common name (or a username) is a role or `role-instance`; the roles are
the four services, the tools and a router.

- `manifest(role, vehicle)`: the keys the role puts, subscribes to, queries, answers
  queries on (queryables), and declares liveliness tokens on.
- `access_control(vehicle, roles, users, names)`: zenoh's `access_control` block, deny
  by default: one rule per (role, kind of message), a subject of the role's certificate
  common names (`accepted_names`: issued, not revoked) and one of its users, one policy
  joining them. A router enforces it on every client's messages, both ways: what a
  client sends (ingress) and what reaches it (egress).
- `tls(certs, role, listen)`: the `transport/link/tls` block of a session (mTLS).
- `read_credentials(path)`: user/password authentication instead, where TLS is not wanted
  (the users are roles; the router's dictionary and each client's own line).

Zenoh matches verbatim chunks (`@adv`, used by zenoh-ext's advanced publishers and
subscribers for the cached topics) only by name, never by `*` or `**`, so those keys are
listed explicitly.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from common.topics import (
    CACHED,
    INPUTS,
    PREFIX,
    SERVICES,
    TOPICS,
    admin_key,
    alive_key,
    heartbeat_key,
    launcher_key,
    topic_key,
)

TOOLS = ("recorder", "viewer", "operator")   # read-only, read-only, swaps and launcher requests
ROLES = (*SERVICES, *TOOLS, "router")        # a router: another site's, forwarding everything


@dataclass(frozen=True)
class Manifest:
    """What one role does on the bus, as key expressions."""
    role: str
    put: tuple[str, ...] = ()
    subscribe: tuple[str, ...] = ()
    query: tuple[str, ...] = ()
    queryable: tuple[str, ...] = ()
    hears: tuple[str, ...] = ()                # the queries routed to its queryables
    token: tuple[str, ...] = ()
    watch_tokens: tuple[str, ...] = ()        # liveliness subscribers and queries


def _adv(keys: list[str]) -> list[str]:
    """zenoh-ext's keys beside a cached topic's (its publisher's cache and liveliness)."""
    return [f"{k}/@adv/**" for k in keys]


def manifest(role: str, vehicle: str) -> Manifest:
    """The keys `role` uses on the bus of `vehicle` (module docstring)."""
    if role not in ROLES:
        raise ValueError(f"unknown role {role!r}; one of {', '.join(ROLES)}")
    everything = f"{PREFIX}/{vehicle}/**"
    admin_all = f"{PREFIX}/{vehicle}/admin/**"
    cached = [topic_key(vehicle, t) for t in CACHED]
    if role in SERVICES:
        outs = [topic_key(vehicle, t) for t, (owner, _) in TOPICS.items() if owner == role]
        ins = [topic_key(vehicle, t) for t in INPUTS[role]]
        mine_cached = [topic_key(vehicle, t) for t, owner in CACHED.items() if owner == role]
        return Manifest(
            role,
            put=(*outs, heartbeat_key(vehicle, role)),
            # every service watches the heartbeats (the plant: its planners'); its inputs;
            # the cached topics' late samples come as query replies
            subscribe=(*ins, heartbeat_key(vehicle), *_adv(ins)),
            query=(admin_all, *_adv(ins)),
            queryable=(admin_key(vehicle, role, "*", "**"), *_adv(mine_cached)),
            # a query names what it asks for with wildcards (`admin/*/*/latest/cmd`: any
            # instance holding one), which zenoh lets out only under a key that includes
            # it; the queryable answers its own keys alone (its replies are checked)
            hears=(admin_all, *_adv(mine_cached)),
            token=(alive_key(vehicle, role, "*"), *_adv(mine_cached)),
            watch_tokens=(alive_key(vehicle), *_adv(ins)))
    if role == "router":                # all of it, both ways, and zenoh-ext's keys
        every = (everything, *_adv(cached))
        return Manifest(role, put=every, subscribe=every, query=every, queryable=every,
                        hears=every, token=every, watch_tokens=every)
    if role == "operator":              # vamppi swap: a handover, a launcher request
        return Manifest(role, put=(topic_key(vehicle, "handover"), launcher_key(vehicle)),
                        subscribe=(everything,), query=(admin_all,),
                        watch_tokens=(f"{PREFIX}/{vehicle}/alive/**",))
    # recorder and viewer: read everything, write nothing
    return Manifest(role, subscribe=(everything, *_adv(cached)),
                    query=(admin_all, *_adv(cached)),
                    watch_tokens=(f"{PREFIX}/{vehicle}/alive/**", *_adv(cached)))


# (manifest field, the client's messages the router lets in, the messages it lets out to it)
_FLOWS = (
    ("put", ("put",), ()),
    ("subscribe", ("declare_subscriber",), ("put",)),
    ("query", ("query",), ("reply",)),
    ("queryable", ("declare_queryable", "reply"), ()),
    ("hears", (), ("query",)),
    ("token", ("liveliness_token",), ()),
    ("watch_tokens", ("declare_liveliness_subscriber", "liveliness_query"),
     ("liveliness_token",)),
)


def access_control(vehicle: str, roles: tuple[str, ...] = ROLES,
                   users: tuple[str, ...] = (), names: tuple[str, ...] = ROLES
                   ) -> dict[str, Any]:
    """Zenoh's `access_control` block for a router serving `vehicle`: deny by default, each
    role allowed exactly its manifest. A role's subjects are the certificate common names
    `names` of it (`role` or `role-instance`: those issued and not revoked,
    `accepted_names`) and, for user/password authentication, the `users` of it (zenoh
    matches a subject only if all its attributes do: hence one subject each). A role with
    neither has no policy: everything it would do is denied."""
    # A declared publisher sends only where it knows of a subscriber, a querier asks only
    # where it knows of a queryable: every client hears of those (their key expressions,
    # often wider than the keys it may use, such as a recorder's `vamppi/<vehicle>/**`)
    rules = [{"id": "declarations", "permission": "allow", "flows": ["egress"],
              "messages": ["declare_subscriber", "declare_queryable"],
              "key_exprs": ["**", f"{PREFIX}/*/*/*/@adv/**"]}]
    subjects, policies = [], []
    for role in roles:
        certs = [n for n in names if role_of(n) == role]
        mine = [u for u in users if role_of(u) == role]
        ids = [f"{role}-certs"] * bool(certs) + [f"{role}-users"] * bool(mine)
        if not ids:                    # an empty list of names would match any client
            continue
        if certs:
            subjects.append({"id": f"{role}-certs", "cert_common_names": certs})
        if mine:
            subjects.append({"id": f"{role}-users", "usernames": mine})
        m = manifest(role, vehicle)
        rule_ids = ["declarations"]
        for name, ingress, egress in _FLOWS:
            keys = list(getattr(m, name))
            if not keys:
                continue
            for flow, messages in (("ingress", ingress), ("egress", egress)):
                if messages:
                    rid = f"{role}-{name}-{flow}"
                    rules.append({"id": rid, "permission": "allow", "flows": [flow],
                                  "messages": list(messages), "key_exprs": keys})
                    rule_ids.append(rid)
        policies.append({"id": role, "rules": rule_ids, "subjects": ids})
    return {"enabled": True, "default_permission": "deny", "rules": rules,
            "subjects": subjects, "policies": policies}


REVOKED = "revoked.txt"          # in a certificates directory: one revoked name a line


def accepted_names(certs: str | Path) -> tuple[str, ...]:
    """The certificate names a router with the directory `certs` accepts: every `NAME.pem`
    `vamppi certs` issued there (a role or `role-instance`; not the CA), less those
    `vamppi certs --revoke` listed in `revoked.txt`."""
    d = Path(certs).expanduser()
    revoked = revoked_names(d)
    return tuple(sorted(p.stem for p in d.glob("*.pem") if p.stem != "ca"
                        and role_of(p.stem) in ROLES and p.stem not in revoked))


def revoked_names(certs: str | Path) -> set[str]:
    """The names `revoked.txt` in the directory `certs` lists (none if there is none)."""
    f = Path(certs).expanduser() / REVOKED
    return set(f.read_text().split()) if f.exists() else set()


def role_of(name: str) -> str:
    """The role of a certificate or user name: `role` or `role-instance`."""
    return name.partition("-")[0]


def default_certs() -> Path:
    """Where `vamppi up` keeps the certificates it makes on first use, and where a client
    of a `tls/` endpoint looks when bus.certs is "": `$XDG_CONFIG_HOME/vamppi/certs`."""
    base = os.environ.get("XDG_CONFIG_HOME") or str(Path.home() / ".config")
    return Path(base) / "vamppi" / "certs"


def read_credentials(path: str | Path) -> dict[str, str]:
    """A user/password file, one `user:password` per line (zenoh's dictionary format);
    a user is a role or `role-instance`."""
    out = {}
    for n, line in enumerate(Path(path).expanduser().read_text().splitlines(), 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        user, sep, password = line.strip().partition(":")
        if not sep or not user or not password or role_of(user) not in ROLES:
            raise ValueError(f"{path}:{n}: not `role[-instance]:password`")
        out[user] = password
    return out


def identity(certs: str | Path, role: str, instance: str = "0",
             credentials: str | Path = "") -> str:
    """The certificate (or user) a process of `role` presents: `role-instance` where `vamppi
    certs` made one (or the credentials name one), else the role's."""
    name = f"{role}-{instance}"
    if certs and (Path(certs).expanduser() / f"{name}.pem").exists():
        return name
    if credentials and name in read_credentials(credentials):
        return name
    return role


def with_identity(cfg: Any, role: str, instance: str = "0") -> Any:
    """`cfg` (a Config) presenting `role`'s certificate or user unless bus.identity names
    one; a client of a `tls/` endpoint with bus.certs "" uses `default_certs()`."""
    b = cfg.bus
    if not b.certs and any(e.startswith("tls/") for e in (*b.connect, *b.listen)):
        cfg = cfg.replace(**{"bus.certs": str(default_certs())})
        b = cfg.bus
    if not (b.certs or b.credentials) or b.identity:
        return cfg
    return cfg.replace(**{"bus.identity": identity(b.certs, role, instance, b.credentials)})


def tls(certs: str | Path, name: str, listen: bool = False) -> dict[str, Any]:
    """The `transport/link/tls` block of a session with the certificate `name` (a role, or
    `role-instance`) from the directory `vamppi certs` wrote: mutual TLS, the peer checked
    against the local CA."""
    d = Path(certs).expanduser().resolve()
    own = {"listen_private_key" if listen else "connect_private_key": str(d / f"{name}.key"),
           "listen_certificate" if listen else "connect_certificate": str(d / f"{name}.pem")}
    return {"root_ca_certificate": str(d / "ca.pem"), "enable_mtls": True, **own}
