"""Who is alive: heartbeats and their deadlines, as pure functions on frozen dataclasses.

Every service instance beats a `vamppi.Heartbeat` every `supervision.heartbeat_period_s`
from a thread that beats `ready` only while the service's main loop makes progress
(common.bus.Node). A watcher (`Watch`) keeps the last beat of each instance; an
instance is alive while its last beat is younger than the deadline the beat states and
says neither `stalled` nor `stopping`. Liveliness tokens alone miss a wedged process:
zenoh's own threads keep its session, and so its token, up while Python is stuck.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

from common.messages import Heartbeat

FAILED = ("stalled", "stopping", "retired")   # a retired planner was replaced by a swap
RETIRED_EXIT = 3      # the exit status of a planner replaced by a swap (vamppi up lets it go)
REFUSED_EXIT = 4      # ... of a service that found the plant running another scenario


@dataclass(frozen=True)
class Beat:
    """The last beat of one instance, as received."""
    source: str                 # "<service>/<instance>"
    boot: int
    status: str
    role: str
    deadline_s: float
    stamp: float
    episode: int
    wall: float                 # receive wall time
    world: str = ""             # the digest of the scenario it runs ("" unknown)

    @property
    def service(self) -> str:
        return self.source.split("/")[0]


@dataclass(frozen=True)
class Watch:
    """The newest beat of every instance (and process: source, boot) heard from."""
    beats: Mapping[tuple[str, int], Beat] = field(default_factory=dict)


def on_beat(w: Watch, hb: Heartbeat, wall: float) -> Watch:
    h = hb.header
    beat = Beat(h.source, h.boot, hb.status, hb.role, hb.deadline_s, h.stamp, h.episode, wall,
                hb.world)
    return Watch({**w.beats, (h.source, h.boot): beat})


def is_alive(b: Beat, wall: float) -> bool:
    return b.status not in FAILED and wall - b.wall <= b.deadline_s


def alive(w: Watch, source: str, wall: float, boot: int | None = None) -> bool:
    """Whether some process of `source` (that one, with `boot`) beats in time."""
    return any(is_alive(b, wall) for (s, bt), b in w.beats.items()
               if s == source and (boot is None or bt == boot))


def newest(w: Watch, source: str) -> Beat | None:
    """The beat of the newest process of `source` heard from."""
    found = [b for (s, _), b in w.beats.items() if s == source]
    return max(found, key=lambda b: b.boot) if found else None


def failed(w: Watch, wall: float) -> list[Beat]:
    """The newest process of each instance whose beat is overdue or says it failed."""
    sources = {s for s, _ in w.beats}
    out = []
    for s in sorted(sources):
        b = newest(w, s)
        if b is not None and not is_alive(b, wall):
            out.append(b)
    return out


def other_world(b: Beat | None, world: str) -> bool:
    """Whether the beat states a scenario digest that differs from `world` (either
    unknown: no)."""
    return b is not None and bool(b.world) and bool(world) and b.world != world


def missing(w: Watch, services: tuple[str, ...], wall: float) -> list[str]:
    """The named services of which no instance beats in time."""
    up = {b.service for b in w.beats.values() if is_alive(b, wall)}
    return [s for s in services if s not in up]
