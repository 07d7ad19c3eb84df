"""The protocol rules every service shares: pure functions on frozen dataclasses.

A service's protocol core (`services/<name>/protocol.py`) is a set of functions

    on_<input>(params, state, message, wall) -> (state, verdict, outputs)

with no bus in them: the shell (`node.py`) decodes, calls the core, publishes the
`Out`s; the in-process runner (`deploy/sim/runner.py`) calls the same functions with
messages it builds itself (`Stamper`). What they share lives here:

- **Input acceptance** (`check`, `accept`): every input is checked before it
  changes any state. It must come from the service that owns its topic
  (common.bus.TOPICS), and within an episode from the one instance of it that fed
  the first accepted message (a restart keeps the instance's name). Per source
  (`header.source`) and publisher process (`header.boot`): a seq no greater than the
  last accepted one is a duplicate, a boot older than the last accepted one a message
  of a dead incarnation, a stamp older than the last accepted one stale, a stamp
  further ahead than the protocol allows from the future: in lockstep `ahead_s` past
  the last accepted stamp; in realtime `ahead_s` (and some slack) past the source's
  clock, the largest stamp less receive time seen (a message delivered late never
  raises it). `FUTURE_RUN` such messages in a row from one process are taken as its
  clock having moved and accepted, so that no judgement stalls a consumer for good.
  A rejected message changes nothing but that count; the verdict names the reason,
  which the shell counts in health. A message with the stamp of the
  last accepted one (and a new seq) is a `REPEAT`: the plant re-offering a tick, or a
  service answering one again; lockstep answers it from the output it cached. So is a
  newer boot's message less than `back_s` older than the last accepted one: a
  restarted plant resumes from the newest whole tick held on the bus, behind the states
  within that tick its dead incarnation had sent (judged stale, its re-offer would be
  refused for good); the consumers of states pass the tick.
- **Episodes** (`Episodes`): the plant names each episode it starts
  (`header.episode`), and every message computed from it carries that name on.
  Each service keeps its state per episode, for the two most recent: a message of
  another episode is judged and answered in its own context, so that a new
  episode starts afresh and a stray one disturbs nothing.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from typing import Any, Generic, TypeVar

from common.messages import Header, InputRef, Message

EPS = 1e-6                 # stamps are sums of the plant's period: equal within this
REALTIME_SLACK_S = 0.5     # realtime: how far a stamp may run ahead of the source's clock
                           # (the jitter of the most prompt delivery seen)
FUTURE_RUN = 3             # consecutive "future" messages of one process that are its clock

NEW = "new"                # verdicts that accept
REPEAT = "repeat"
ACCEPTED = (NEW, REPEAT)


@dataclass(frozen=True)
class Out:
    """One message a core asks its shell to publish."""
    topic: str
    stamp: float
    fields: Mapping[str, Any]
    inputs: tuple[InputRef, ...] = ()
    episode: int = 0


@dataclass(frozen=True)
class Seen:
    """The last message accepted from one source, and its clock."""
    boot: int
    seq: int
    stamp: float
    wall: float
    offset: float                 # the largest stamp - receive wall time seen
    futures: int = 0              # "future" messages since, in a row
    future_seq: int = -1


@dataclass(frozen=True)
class Order:
    """What has been accepted on one input, by source, and the source it is bound to.
    Treated as immutable: `accept` returns a new one."""
    seen: Mapping[str, Seen] = field(default_factory=dict)
    bound: str = ""

    def last(self, source: str) -> Seen | None:
        return self.seen.get(source)

    def newest_stamp(self) -> float | None:
        return max((s.stamp for s in self.seen.values()), default=None)


def check(order: Order, h: Header, wall: float, ahead_s: float, realtime: bool,
          owner: str = "", back_s: float = 0.0) -> str:
    """The verdict on a message with header `h` received at `wall`: NEW, REPEAT or the
    reason it is rejected (not the owner's, another instance, duplicate, superseded
    boot, stale, future). `owner`: the service whose topic it is ('' for any); `back_s`:
    how far behind the last accepted stamp a newer boot may resume."""
    if owner and h.source.split("/")[0] != owner:
        return f"not from the {owner}"
    if owner and order.bound and h.source != order.bound:
        return f"not this episode's {owner} ({order.bound})"
    last = order.last(h.source)
    if last is None:
        return NEW
    if h.boot < last.boot:
        return "superseded boot"
    if h.boot == last.boot and h.seq <= last.seq:
        return "duplicate"
    if h.stamp < last.stamp - EPS:
        resumed = h.boot > last.boot and last.stamp - h.stamp < back_s - EPS
        return REPEAT if resumed else "stale"
    if realtime:
        beyond = h.stamp - wall > last.offset + ahead_s + REALTIME_SLACK_S
    else:
        beyond = h.stamp > last.stamp + ahead_s + EPS
    if beyond:
        moved = last.futures >= FUTURE_RUN - 1 and h.seq > last.future_seq
        return NEW if moved else "future"
    return REPEAT if abs(h.stamp - last.stamp) <= EPS else NEW


def accept(order: Order, h: Header, wall: float) -> Order:
    """`order` with `h` accepted (bound to its source if it was the first)."""
    last = order.last(h.source)
    offset = h.stamp - wall
    if last is not None and h.boot == last.boot:
        offset = max(offset, last.offset)
    return Order({**order.seen, h.source: Seen(h.boot, h.seq, h.stamp, wall, offset)},
                 order.bound or h.source)


def judge(order: Order, h: Header, wall: float, ahead_s: float, realtime: bool,
          owner: str = "", back_s: float = 0.0) -> tuple[Order, str]:
    """`check` and its consequence: the order with the message accepted, or with a
    "future" one counted (FUTURE_RUN), or unchanged."""
    verdict = check(order, h, wall, ahead_s, realtime, owner, back_s)
    if verdict in ACCEPTED:
        return accept(order, h, wall), verdict
    last = order.last(h.source)
    if verdict == "future" and last is not None and h.boot >= last.boot:
        run = last.futures + 1 if h.seq > last.future_seq else 1
        return Order({**order.seen, h.source: replace(last, futures=run, future_seq=h.seq)},
                     order.bound), verdict
    return order, verdict


T = TypeVar("T")


@dataclass(frozen=True)
class Episodes(Generic[T]):
    """A service's state per episode, the two most recently used kept (last: the newest)."""
    items: tuple[tuple[int, T], ...] = ()
    keep: int = 2

    def get(self, episode: int) -> T | None:
        for e, ctx in self.items:
            if e == episode:
                return ctx
        return None

    def put(self, episode: int, ctx: T) -> Episodes[T]:
        rest = tuple((e, c) for e, c in self.items if e != episode)
        return replace(self, items=(*rest, (episode, ctx))[-self.keep:])

    def current(self) -> tuple[int, T] | None:
        return self.items[-1] if self.items else None


def context(episodes: Episodes[T], episode: int, fresh: Callable[[], T]) -> T:
    """The context of `episode`, or a fresh one."""
    ctx = episodes.get(episode)
    return fresh() if ctx is None else ctx


R = TypeVar("R")


def after_rejection(run: R, episode: int, ctx: Any, counted: bool) -> R:
    """A service's run after it rejected a message of `episode`: unchanged, or where the
    rejection was `counted` (a "future" run, `judge`) with that context put back."""
    return replace(run, episodes=run.episodes.put(episode, ctx)) if counted else run


class Stamper:
    """Builds the messages a publisher would send (header: gap-free seq, boot, source) without
    a bus: what the in-process runner hands from one core to the next, and what the shell's
    publishers use (common.bus)."""

    def __init__(self, source: str, boot: int | None = None,
                 wall: Callable[[], float] = time.time):
        self.source = source
        self.boot = time.time_ns() if boot is None else boot
        self.seq = 0
        self._wall = wall

    def make(self, cls: type[Message], out: Out) -> Message:
        msg = cls(header=Header(self.seq, float(out.stamp), self._wall(), self.source,
                                tuple(out.inputs), self.boot, out.episode), **out.fields)
        self.seq += 1
        return msg


def newer(held: Message | None, msg: Message) -> bool:
    """Whether `msg` is at least as new as `held` (episode, then stamp): what a service keeps
    to answer a restarted one."""
    return held is None or (msg.header.episode, msg.header.stamp) >= (held.header.episode,
                                                                       held.header.stamp)


def on_tick(stamp: float, tick_s: float) -> bool:
    """Whether a stamp falls on a control tick boundary."""
    k = round(stamp / tick_s)
    return abs(stamp - k * tick_s) <= EPS


def ref(key: str, msg: Message) -> InputRef:
    """The InputRef naming `msg` as received on `key`."""
    return InputRef(key, msg.header.seq, msg.header.stamp)


@dataclass
class SeqTrack:
    """The seqs of one publisher (one source and boot) on one key, as they arrive: which never
    came (`gaps`, exact inclusive ranges), which came late (filling a gap) and which twice.
    Mutable bookkeeping, fed in arrival order."""
    count: int = 0
    first: int = -1
    last: int = -1                                  # the highest seen
    gaps: list[list[int]] = field(default_factory=list)   # [from, to], sorted, disjoint
    late: int = 0
    duplicates: int = 0

    MAX_GAPS = 10_000

    def see(self, seq: int) -> None:
        if not self.count:
            self.first = self.last = seq
        elif seq > self.last:
            if seq > self.last + 1 and len(self.gaps) < self.MAX_GAPS:
                self.gaps.append([self.last + 1, seq - 1])
            self.last = seq
        elif not self._fill(seq):
            self.duplicates += 1
            return
        self.count += 1

    def _fill(self, seq: int) -> bool:
        for i, (a, b) in enumerate(self.gaps):
            if a <= seq <= b:
                pieces = [p for p in ([a, seq - 1], [seq + 1, b]) if p[0] <= p[1]]
                self.gaps[i:i + 1] = pieces
                self.late += 1
                return True
        if seq < self.first:              # older than the first seen (recovered history)
            if seq + 1 <= self.first - 1:
                self.gaps.insert(0, [seq + 1, self.first - 1])
            self.first = seq
            self.late += 1
            return True
        return False

    def has(self, seq: int) -> bool:
        """Whether `seq` has arrived."""
        return (self.count > 0 and self.first <= seq <= self.last
                and not any(a <= seq <= b for a, b in self.gaps))

    @property
    def missing(self) -> int:
        return sum(b - a + 1 for a, b in self.gaps)

    def summary(self) -> dict[str, Any]:
        return {"count": self.count, "first": self.first, "last": self.last,
                "missing": self.missing, "gaps": [list(g) for g in self.gaps[:50]],
                "late": self.late, "duplicates": self.duplicates}
