"""`vamppi`: the command line.

    vamppi up --scenario NAME [--controller C] [--samples K] [--clock lockstep|realtime] [--seed S]
    vamppi service NAME [--connect tcp/HOST:PORT] [--listen EP] [--mode peer|client|router]
    vamppi router --listen tcp/0.0.0.0:7447     a standalone router
    vamppi health --connect tcp/HOST:7447       live instances and their counters
    vamppi view [--connect tcp/HOST:7447]       the bus live in Foxglove (ws://localhost:8765)
    vamppi run ...           one episode in this process, no bus (the lockstep reference)
    vamppi plans --at T ...  the plan at T s of such an episode against the same plan sooner
    vamppi experiment --scenario alleyway,offroad --controllers va,deterministic,prescient \\
        --samples 400,1000,4000 --runs 100 --seed 0 --out DIR
    vamppi tables [NAME...] [--run [--stale] --root DIR]   the tables of record: current?
    vamppi config ...        print the effective configuration as JSON
    vamppi reveal DIR        when each hidden obstacle was first seen, and could it stop
    vamppi collisions DIR... what each collision was on, and how long the map had shown it
    vamppi timeouts DIR...   how each run that timed out ended: standing (since when) or driving
    vamppi near-goal DIR...  runs split by a hidden obstacle near the goal, successes compared

Every command takes `--config FILE` and `--set section.key=value` (repeatable). A bus
command (health, record, replay, view, swap) given no `--connect` connects to the router
of the `vamppi up` running on this machine (deploy/launch/running.py).

Where each command's code is: up (deploy/launch/up.py), swap (launch/swap.py), certs
(launch/certs.py), service, router, health (here, around common.bus); record and recover
(recording/record.py), replay, timing, export-foxglove, view (recording/replay.py,
timing.py, foxglove.py, view.py); run (sim/runner.py), experiment (sim/experiment.py, its
summary analysis/summary.py), tables (sim/tables.py), scenario generate and set
(sim/generate.py); reveal, collisions, timeouts, near-goal, plans (analysis/); bench WHAT
(bench/main.py).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import signal
import sys
import threading
from pathlib import Path
from typing import Any

from common import compile_cache
from common.config import Config, ConfigError, load_config, preset_overrides
from common.memory import PIPELINE_PROCESSES, keep_large_buffers, share_device
from common.process import PARENT_ENV, die_with_parent, exit_now, stop_on_signals, when_orphaned
from common.security import default_certs, with_identity
from common.supervision import REFUSED_EXIT, RETIRED_EXIT


def add_config_args(p: argparse.ArgumentParser, shorthands: bool = True) -> None:
    """--config, --set and --preset; with `shorthands` the flags for the most used
    parameters too (overrides_from_args reads them all)."""
    g = p.add_argument_group("configuration")
    g.add_argument("--config", help="TOML file merged over the defaults")
    g.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                   help="override one parameter (repeatable)")
    g.add_argument("--preset", help="a named set of parameters (common/presets: paper = the "
                                    "paper's method), over --config and under --set")
    if not shorthands:
        return
    g.add_argument("--scenario", help="episode.scenario: a built-in's name or a scenario file")
    g.add_argument("--controller", help="planner.controller")
    g.add_argument("--samples", type=int, help="planner.samples (K)")
    g.add_argument("--clock", choices=("lockstep", "realtime"), help="episode.clock")
    g.add_argument("--seed", type=int, help="episode.seed")
    g.add_argument("--vehicle", help="episode.vehicle")


def add_runner_args(p: argparse.ArgumentParser) -> None:
    """How an experiment's runs are run (deploy/sim/experiment.py), and what it shows."""
    p.add_argument("--jobs", type=_positive_int, default=1,
                   help="worker processes running runs side by side, each pinned to its "
                        "share of the CPUs (default 1: in this process); solve times are "
                        "then measured with the others competing")
    p.add_argument("--cluster", metavar="ADDRESS",
                   help="run the runs as tasks on the Ray cluster at ADDRESS (auto, "
                        "HOST:6379, ray://HOST:10001), or on one started here with --jobs "
                        "CPUs (local); needs the cluster extra")
    p.add_argument("--no-plots", action="store_true")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def add_bus_args(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("bus (zenoh)")
    g.add_argument("--mode", choices=("peer", "client", "router"), help="bus.mode")
    g.add_argument("--connect", action="append", metavar="ENDPOINT", help="bus.connect")
    g.add_argument("--listen", action="append", metavar="ENDPOINT", help="bus.listen")


def add_view_args(p: argparse.ArgumentParser, prefix: str = "") -> None:
    """The live view's server settings (`vamppi view`; `vamppi up --view-...`)."""
    g = p.add_argument_group("live view (Foxglove WebSocket)")
    g.add_argument(f"--{prefix}host", default="127.0.0.1", dest="host",
                   help="address to serve on (0.0.0.0: other machines too)")
    g.add_argument(f"--{prefix}port", type=int, default=8765, dest="port",
                   help="port to serve on (0: a free one)")
    g.add_argument("--map-hz", type=float, default=2.0,
                   help="maps shown per second at most (mean and variance: 1.7 MB of JSON)")
    g.add_argument("--rollouts", type=int, default=30, help="sampled rollouts drawn per plan")


def overrides_from_args(args: argparse.Namespace) -> list[str]:
    """The --preset's parameters, the --set list and the shorthand flags, as
    section.key=value strings (later ones win)."""
    preset = getattr(args, "preset", None)
    out = preset_overrides(preset) if preset else []
    out += list(getattr(args, "set", []))
    for flag, key in (("scenario", "episode.scenario"), ("controller", "planner.controller"),
                      ("samples", "planner.samples"), ("clock", "episode.clock"),
                      ("seed", "episode.seed"), ("vehicle", "episode.vehicle"),
                      ("mode", "bus.mode")):
        v = getattr(args, flag, None)
        if v is not None:
            out.append(f"{key}={json.dumps(v)}")
    for flag in ("connect", "listen"):
        v = getattr(args, flag, None)
        if v:
            out.append(f"bus.{flag}={json.dumps(v)}")
    return out


def config_from_args(args: argparse.Namespace) -> Config:
    """The configuration: --config's TOML over the defaults, then the flags. A router's
    --config may be a zenoh JSON5 file instead (a site's, deploy/configs): bus.zenoh."""
    path, overrides = getattr(args, "config", None), overrides_from_args(args)
    if args.command == "router" and path and path.endswith(".json5"):
        path, overrides = None, [f"bus.zenoh={json.dumps(path)}", *overrides]
    return load_config(path, overrides)


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be 1 or more, not {value}")
    return value


def _setup_logging(verbose: bool) -> None:
    logging.basicConfig(level=logging.DEBUG if verbose else logging.INFO, stream=sys.stderr,
                        format="%(asctime)s %(name)s %(levelname)s %(message)s")
    logging.getLogger("jax._src.xla_bridge").setLevel(logging.WARNING)


def _interrupt_on_sigterm() -> None:
    """SIGTERM unwinds like Ctrl-C (a KeyboardInterrupt): the children or workers stop."""
    def interrupt(*_: object) -> None:
        raise KeyboardInterrupt
    signal.signal(signal.SIGTERM, interrupt)


def _stop_event() -> threading.Event:
    """An event Ctrl-C or SIGTERM sets, for a command that finishes its file on the way out
    (no forced exit after a grace, unlike a service's common.process.stop_on_signals)."""
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    return stop


class NoRouter(RuntimeError):
    """A bus command has no router to connect to."""


def find_bus(cfg: Config) -> Config:
    """`cfg`, or, when its bus names no endpoint (no --connect, --listen or bus.zenoh) and
    is a client's, `cfg` connected to the router of this machine's running `vamppi up`
    (deploy/launch/running.py). NoRouter when there is none."""
    b = cfg.bus
    if b.connect or b.listen or b.zenoh or b.mode != "client":
        return cfg
    from deploy.launch.running import bus_overrides, locate
    found = locate(cfg.episode.vehicle)
    if found is None:
        raise NoRouter(f"no router to connect to: no `vamppi up` of vehicle "
                       f"{cfg.episode.vehicle!r} runs on this machine; give --connect "
                       "ENDPOINT (a router's, e.g. tcp/127.0.0.1:7447)")
    logging.getLogger(__name__).info("connecting to the router of vamppi up (pid %d) at %s",
                                     found.pid, found.endpoint)
    return cfg.replace(**bus_overrides(found))


SERVICE_MAINS = {
    "plant": "services.plant.node",
    "sensor": "services.sensor.node",
    "mapper": "services.mapper.node",
    "planner": "services.planner.node",
}


def cmd_service(args: argparse.Namespace, cfg: Config) -> int:
    """One service until its episode ends (the plant) or a signal: SIGINT or SIGTERM stop
    it within a second whatever it is doing (common.process)."""
    import importlib
    stop = threading.Event()
    stop_on_signals(stop)
    if args.stop_with_parent:
        def parent_gone() -> None:        # as a signal: stopped, and gone after the grace
            logging.getLogger(__name__).warning("parent process gone: stopping")
            os.kill(os.getpid(), signal.SIGTERM)
        die_with_parent()
        when_orphaned(parent_gone)
    os.environ.pop(PARENT_ENV, None)
    cfg = with_identity(cfg, args.name, args.instance)
    from common.bus import WorldMismatch
    module = importlib.import_module(SERVICE_MAINS[args.name])
    role = "standby" if args.standby else args.role
    if args.name != "planner" and role != "active":
        print(f"vamppi service: --role is for planners; {args.name} has none", file=sys.stderr)
        return 2
    try:
        if args.name == "planner":
            ended = module.main(cfg, args.instance, stop, role=role,
                                take_over_after_s=args.take_over_after,
                                retire=not args.keep_old, take_over_at_s=args.take_over_at)
            return exit_now(RETIRED_EXIT if ended == "retired" else 0)
        module.main(cfg, args.instance, stop)
    except WorldMismatch as exc:
        print(f"vamppi service {args.name}: refused: {exc}", file=sys.stderr)
        return exit_now(REFUSED_EXIT)
    return exit_now(0)


def cmd_certs(args: argparse.Namespace, cfg: Config) -> int:
    """A local CA and certificates per role for mutual TLS (deploy/launch/certs.py); --revoke
    lists names the routers must deny."""
    from common.security import ROLES
    from deploy.launch.certs import CertError, make_certs, revoke
    try:
        if args.revoke:
            accepted = []
            for name in args.revoke:
                accepted = revoke(args.dir, name)
            print(json.dumps({"revoked": args.revoke, "accepted": accepted,
                              "apply": "restart every router that uses this directory"}))
            return 0
        made = make_certs(args.dir, tuple(args.name or ROLES), tuple(args.host), args.days)
    except CertError as exc:
        print(f"vamppi certs: {exc}", file=sys.stderr)
        return 1
    print(json.dumps({"ca": str(Path(args.dir) / "ca.pem"), "certificates": list(map(str, made))}))
    return 0


def cmd_swap(args: argparse.Namespace, cfg: Config) -> int:
    """Start a planner instance beside the running one and hand it the authority."""
    from deploy.launch.swap import SwapError, promote, swap
    cfg = with_identity(find_bus(cfg), "operator")
    try:
        if args.to:
            report = promote(cfg, args.to, keep_old=args.keep_old, timeout_s=args.timeout)
        else:
            report = swap(cfg, args.instance, overrides_from_args(args), args.config,
                          shadow_s=args.shadow, timeout_s=args.timeout, keep_old=args.keep_old)
    except SwapError as exc:
        print(f"vamppi swap: {exc}", file=sys.stderr)
        return 1
    print(json.dumps(report), flush=True)
    return 0


def cmd_run(args: argparse.Namespace, cfg: Config) -> int:
    from deploy.sim.runner import run_episode
    result = run_episode(cfg)
    print(json.dumps(result.summary(cfg)), flush=True)
    return 0 if result.outcome == "success" else 1


def cmd_plans(args: argparse.Namespace, cfg: Config) -> int:
    """The planner's plan at one instant of an in-process episode, priced beside the same plan
    carried out sooner (deploy/analysis/plans.py)."""
    from deploy.analysis.plans import plans, table
    try:
        alt = load_config(overrides=args.price_with, base=cfg) if args.price_with else None
        rows = plans(cfg, args.at, steady=args.steady, alt=alt)
    except (ValueError, ConfigError) as exc:
        print(f"vamppi plans: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(rows, indent=1) if args.json else table(rows, args.top))
    return 0


def cmd_scenario(args: argparse.Namespace, cfg: Config) -> int:
    """show: the scenario's start, goal and obstacles as JSON (--plot writes its picture);
    export: its scenario file; generate: a procedural world (deploy/sim/generate.py); set: the
    benchmark set of generated worlds, split into a tuning half and a held-out half."""
    from dataclasses import asdict

    from common.scenarios import ScenarioError, save_spec, scenario_of, spec_of, spec_toml
    from deploy.sim.generate import GenerateError, generate, write_set
    try:
        if args.action == "generate":
            spec = generate(cfg, args.kind or "", 1 if args.seed is None else args.seed,
                            drive=not args.no_drive)
            if args.out:
                print(save_spec(spec, args.out))
            else:
                print(spec_toml(spec), end="")
            return 0
        if args.action == "set":
            for path in write_set(cfg, Path(args.out), args.per_kind, args.kind, jobs=args.jobs):
                print(path, flush=True)
            return 0
        if args.action == "export":
            spec = spec_of(cfg.episode.scenario, cfg.episode.layout)
            if args.out:
                print(save_spec(spec, args.out))
            else:
                print(spec_toml(spec), end="")
            return 0
        scn = scenario_of(cfg)
    except (ScenarioError, GenerateError) as exc:
        print(f"vamppi scenario: {exc}", file=sys.stderr)
        return 2
    print(json.dumps({"name": scn.name, "kind": scn.kind, "seed": scn.seed,
                      "layout": scn.layout, "digest": scn.digest,
                      "description": scn.description,
                      "start": asdict(scn.start), "goal": asdict(scn.goal),
                      "obstacles": [asdict(o) for o in scn.obstacles]}, indent=1))
    if args.plot:
        from deploy.analysis.plots import plot_scenario
        plot_scenario(cfg, cfg.episode.scenario, Path(args.plot))
    return 0


def cmd_bench(args: argparse.Namespace, cfg: Config) -> int:
    from deploy.bench import main as bench
    from deploy.bench.peer import MissingExtra
    from deploy.bench.startup import ImportFailed
    from deploy.sim.experiment import parse_list
    samples = args.samples_list or ("800" if args.what == "pipeline" else "400,800,1000,4000")
    controllers = args.controllers or ("va" if args.what == "pipeline" else "va,deterministic")
    reps = args.reps if args.reps is not None else {"view": 3, "startup": 5}.get(args.what, 20)
    try:
        return bench.main(cfg, args.what, parse_list(samples, int), parse_list(controllers),
                          reps, args.json, overrides_from_args(args), args.duration,
                          args.config, args.record,
                          parse_list(args.forms) if args.forms else None)
    except (MissingExtra, ImportFailed) as exc:
        print(f"vamppi bench {args.what}: {exc}", file=sys.stderr)
        return 2


def cmd_router(args: argparse.Namespace, cfg: Config) -> int:
    """A standalone router until Ctrl-C (services on several machines connect to it): a
    site's JSON5 file (`--config deploy/configs/*.json5`) or the bus settings, secured with
    bus.certs or bus.credentials; listening on loopback unless told otherwise."""
    import dataclasses

    from common.bus import endpoints_of, open_session, zenoh_config
    stop = threading.Event()
    stop_on_signals(stop)
    bus = dataclasses.replace(cfg.bus, mode="router")
    try:
        plain = zenoh_config(dataclasses.replace(bus, certs="", credentials=""))
        listen = endpoints_of(plain, "listen", "router")
        links = [*listen, *endpoints_of(plain, "connect", "router")]
        if not bus.certs and any(e.startswith("tls/") for e in links):
            bus = dataclasses.replace(bus, certs=str(default_certs()))
        secured = bool(bus.certs or bus.credentials)
        if not listen:
            listen = [f"{'tls' if bus.certs else 'tcp'}/127.0.0.1:7447"]
        bus = dataclasses.replace(bus, listen=tuple(listen), identity=bus.identity or (
            "router" if secured else ""))
        zenoh_config(bus)
    except Exception as exc:               # a bad site file (zenoh.ZError), credentials
        print(f"vamppi router: {exc}", file=sys.stderr)
        return 2
    with open_session(bus):
        logging.getLogger(__name__).info("router listening on %s%s", ", ".join(listen),
                                         " (secured)" if secured else "")
        stop.wait()
    return 0


def cmd_health(args: argparse.Namespace, cfg: Config) -> int:
    """Every live service instance of the vehicle and its health counters, one JSON line each."""
    from common.bus import ZenohTransport, alive_instances, query_json
    from common.topics import admin_key
    bus = ZenohTransport.open(with_identity(find_bus(cfg), "viewer").bus)
    try:
        found = sorted(alive_instances(bus, cfg.episode.vehicle))
        for service, instance in found:
            health = query_json(bus, admin_key(cfg.episode.vehicle, service, instance,
                                               "health"))
            print(json.dumps({"service": service, "instance": instance,
                              "health": health[0] if health else None}), flush=True)
    finally:
        bus.close()
    if not found:
        print(f"vamppi health: no live service under vehicle {cfg.episode.vehicle!r}",
              file=sys.stderr)
    return 0 if found else 1


def cmd_experiment(args: argparse.Namespace, cfg: Config) -> int:
    from deploy.analysis.summary import write_summary
    from deploy.sim.cluster import ClusterError, on_cluster
    from deploy.sim.experiment import ExperimentError, expand_scenarios, experiment, parse_list
    _interrupt_on_sigterm()
    try:
        runs = experiment(cfg, expand_scenarios(parse_list(args.scenarios)),
                          parse_list(args.controllers), parse_list(args.samples_list, int),
                          args.runs, args.seed_base, Path(args.out), progress=not args.quiet,
                          jobs=args.jobs,
                          runner=on_cluster(args.cluster, args.jobs) if args.cluster else None)
        summary = write_summary(cfg, runs, Path(args.out), plots=not args.no_plots)
    except (ExperimentError, ClusterError) as exc:
        print(f"vamppi experiment: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"vamppi experiment: interrupted; the finished runs are kept in "
              f"{Path(args.out) / 'runs.jsonl'}, and the same command resumes", file=sys.stderr)
        return 130
    asked = (set(parse_list(args.controllers)), set(parse_list(args.samples_list, int)))
    for row in summary:                  # the directory may hold other runs: not asked for now
        if row.get("controller") in asked[0] and row.get("samples") in asked[1]:
            print(json.dumps(row), flush=True)
    return 0


def cmd_tables(args: argparse.Namespace, cfg: Config) -> int:
    """The tables of record (deploy/sim/tables.py): their state under --root, or with --run
    the named (or, with --stale, the out-of-date) ones made into it, one after another."""
    from deploy.sim.cluster import ClusterError, on_cluster
    from deploy.sim.experiment import ExperimentError, read_runs
    from deploy.sim.tables import RESULTS_DIR, make_table, select, status_markdown, table_state
    if not Path("common/scenarios").is_dir():
        print("vamppi tables: run it from the repository root (the tables name their "
              "scenario files from there)", file=sys.stderr)
        return 2
    try:
        tables = select(args.names)
    except ValueError as exc:
        print(f"vamppi tables: {exc}", file=sys.stderr)
        return 2
    root = Path(args.root)

    def states(where: Path) -> list:
        return [table_state(t, read_runs(where / t.name / "runs.jsonl")) for t in tables]
    if args.stale:
        tables = [s.table for s in states(RESULTS_DIR) if s.state != "current"]
    if args.run:
        _interrupt_on_sigterm()
        runner = on_cluster(args.cluster, args.jobs) if args.cluster else None
        for t in tables:
            print(f"vamppi tables: {t.name} into {root / t.name}: {t.command()}",
                  file=sys.stderr)
            try:
                make_table(t, root, progress=not args.quiet, jobs=args.jobs, runner=runner,
                           plots=not args.no_plots)
            except (ExperimentError, ClusterError) as exc:
                print(f"vamppi tables: {t.name}: {exc}", file=sys.stderr)
                return 2
            except KeyboardInterrupt:
                print(f"vamppi tables: interrupted in {t.name}; the finished runs are kept "
                      "and the same command resumes", file=sys.stderr)
                return 130
    rows = states(root)
    if args.json:
        print(json.dumps([{"table": s.table.name, "state": s.state, "runs": s.found,
                           "want": s.want, "digests": list(s.digests), "digest": s.digest,
                           "worker_hours": round(s.wall_h, 3), "command": s.table.command()}
                          for s in rows], indent=1))
    else:
        print(status_markdown(rows), end="")
    return 0 if not args.run or all(s.state == "current" for s in rows) else 1


def cmd_config(args: argparse.Namespace, cfg: Config) -> int:
    if args.markdown:
        from common.config import parameters_markdown
        print(parameters_markdown(), end="")
    else:
        print(json.dumps(cfg.to_dict(), indent=2))
    return 0


def cmd_up(args: argparse.Namespace, cfg: Config) -> int:
    from deploy.launch.up import up
    _interrupt_on_sigterm()
    try:
        view = ["--host", args.host, "--port", str(args.port), "--map-hz", str(args.map_hz),
                "--rollouts", str(args.rollouts)] if args.view else None
        summary = up(cfg, overrides_from_args(args), args.config, timeout_s=args.wall_timeout,
                     record=args.record, secure=not args.insecure, view=view)
    except KeyboardInterrupt:
        print("vamppi up: interrupted, every service stopped", file=sys.stderr)
        return 130
    print(json.dumps(summary), flush=True)
    return 0 if summary["outcome"] == "success" else 1


def cmd_record(args: argparse.Namespace, cfg: Config) -> int:
    """Record every sample under the key expression until Ctrl-C / SIGTERM / --duration."""
    from common.bus import ZenohTransport, open_session
    from common.topics import PREFIX
    from deploy.recording.record import Recorder, recording_metadata
    stop = _stop_event()
    keys = args.keys or f"{PREFIX}/{cfg.episode.vehicle}/**"
    log = logging.getLogger(__name__)
    with open_session(with_identity(find_bus(cfg), "recorder").bus) as session:
        # the services' configurations, not this command's: the Recorder asks each
        rec = Recorder(ZenohTransport(session), keys, args.output,
                       recording_metadata(None, keys, cfg.episode.vehicle),
                       flush_interval_s=args.flush_interval)
        log.info("recording %s to %s (Ctrl-C stops)", keys, args.output)
        stop.wait(args.duration)
        stats = rec.stop()
    stats.pop("publishers", None)
    print(json.dumps(stats), flush=True)
    return 0


def cmd_recover(args: argparse.Namespace, cfg: Config) -> int:
    from deploy.recording.record import is_complete, recover
    src = Path(args.file)
    out = Path(args.output) if args.output else src.with_suffix(".recovered.mcap")
    if is_complete(src) and not args.force:
        print(f"vamppi recover: {src} is complete (has its summary); nothing to do "
              "(--force rewrites it anyway)", file=sys.stderr)
        return 0
    report = recover(src, out)
    print(json.dumps(report), flush=True)
    return 0


def cmd_replay(args: argparse.Namespace, cfg: Config) -> int:
    from deploy.sim.experiment import parse_list
    if not Path(args.file).is_file():
        raise FileNotFoundError(f"no such recording: {args.file}")
    topics = parse_list(args.topics) if args.topics else None
    if args.feed:
        from deploy.recording.replay import feed

        def progress(r: dict[str, Any]) -> None:
            n = sum(r["compared"].values())
            if n % 20 == 0:
                logging.getLogger(__name__).info("compared %d outputs, %d identical", n,
                                                 r["identical"])
        try:
            overrides = [o for o in overrides_from_args(args) if not o.startswith("bus.")]
            report = feed(args.file, parse_list(args.feed), overrides,
                          keep_going=args.keep_going, progress=progress)
        except ValueError as exc:
            print(f"vamppi replay: {exc}", file=sys.stderr)
            return 2
        print(json.dumps(report), flush=True)
        div = report["first_divergence"]
        if div is None and report["bit_identical"]:
            print(f"identical: {report['identical']} outputs "
                  f"({', '.join(report['compared_topics'])}) bit for bit", file=sys.stderr)
            return 0
        print(f"first divergence: {div}", file=sys.stderr)
        return 1
    from common.bus import open_session
    from deploy.recording.replay import replay
    stop = _stop_event()
    with open_session(find_bus(cfg).bus) as session:
        report = replay(session, args.file, args.rate, topics, args.loop, args.start_offset,
                        stop)
    print(json.dumps(report), flush=True)
    return 0


def cmd_timing(args: argparse.Namespace, cfg: Config) -> int:
    from deploy.recording import timing
    result = timing.analyse(args.file)
    if args.plots:
        for path in timing.plots(result, args.plots):
            print(f"wrote {path}", file=sys.stderr)
    print(json.dumps(timing.public(result)) if args.json else timing.table(result), flush=True)
    return 0


def experiment_runs(args: argparse.Namespace, given: str, cfg: Config
                    ) -> tuple[Path, Config, list[dict[str, Any]]]:
    """An experiment's runs.jsonl (`given`, or its directory), the configuration to read it
    with (its own config.toml, unless --config is given) and its runs (--controller's)."""
    from deploy.sim.experiment import read_runs
    path = Path(given)
    if path.is_dir():
        path = path / "runs.jsonl"
    if not path.exists():
        raise FileNotFoundError(f"no such file: {path}")
    saved = path.parent / "config.toml"            # the experiment's own configuration
    if args.config is None and saved.exists():
        cfg = load_config(saved, overrides_from_args(args))
    runs = [r for r in read_runs(path)
            if args.only is None or r["controller"] in args.only.split(",")]
    return path, cfg, runs


def cmd_reveal(args: argparse.Namespace, cfg: Config) -> int:
    """First sightings of each (hidden) obstacle along the paths of an experiment's runs."""
    from deploy.analysis.reveal import reveal_runs, table
    _, cfg, runs = experiment_runs(args, args.runs, cfg)
    rows = reveal_runs(cfg, runs, "all" if args.all_obstacles else "hidden")
    print(json.dumps(rows, indent=1) if args.json else table(rows))
    return 0


def cmd_collisions(args: argparse.Namespace, cfg: Config) -> int:
    """What each collision of one or more experiments was on (deploy/analysis/collisions.py): one
    table over all of them (a table of record split over two directories reads as one)."""
    from deploy.analysis.collisions import attribute, counts, load_saved, save, table
    rows = []
    for given in args.runs:
        path, run_cfg, runs = experiment_runs(args, given, cfg)
        try:
            earlier = load_saved(path.parent)      # the attributions of earlier reruns
        except ValueError as exc:
            print(f"vamppi collisions: {exc}", file=sys.stderr)
            return 2
        found = attribute(run_cfg, runs, rerun=args.rerun,
                          progress=args.rerun and sys.stderr.isatty(), saved=earlier)
        if args.rerun:
            save(path.parent, earlier, found)
        rows += found
    print(json.dumps(rows, indent=1) if args.json else table(rows))
    print(json.dumps(counts(rows)), file=sys.stderr)
    return 0


def cmd_timeouts(args: argparse.Namespace, cfg: Config) -> int:
    """How each run of one or more experiments that timed out or never stopped at the goal
    ended (deploy/analysis/timeouts.py): one table over all of them."""
    from deploy.analysis.timeouts import counts, endings, table
    rows = []
    for given in args.runs:
        _, run_cfg, runs = experiment_runs(args, given, cfg)
        try:
            rows += endings(run_cfg, runs)
        except ValueError as exc:
            print(f"vamppi timeouts: {given}: {exc}", file=sys.stderr)
            return 2
    print(json.dumps(rows, indent=1) if args.json else table(rows))
    print(json.dumps(counts(rows)), file=sys.stderr)
    return 0


def cmd_near_goal(args: argparse.Namespace, cfg: Config) -> int:
    """One or more experiments' runs split by whether a hidden obstacle stands near the
    goal (deploy/analysis/neargoal.py): one table over all of them."""
    from deploy.analysis.neargoal import split, table
    # a record names its scenario and scenario seed, and the distance is the footprints',
    # not the map's: the first experiment's configuration reads them all
    runs: list[dict[str, Any]] = []
    first: Config | None = None
    for given in args.runs:
        _, run_cfg, more = experiment_runs(args, given, cfg)
        first = run_cfg if first is None else first
        runs += more
    out = split(first or cfg, runs, args.within)
    print(json.dumps(out, indent=1) if args.json else table(out, args.within))
    return 0


def cmd_view(args: argparse.Namespace, cfg: Config) -> int:
    """Serve the bus live to Foxglove until Ctrl-C / SIGTERM / --duration / the parent's
    death (deploy/recording/view.py)."""
    from common.bus import ZenohTransport
    from deploy.recording.view import Viewer, lower_priority
    from services.sensor.core import CameraParams
    stop = _stop_event()
    if args.stop_with_parent:
        die_with_parent()
        when_orphaned(stop.set)
    os.environ.pop(PARENT_ENV, None)
    lower_priority()
    bus = ZenohTransport.open(with_identity(find_bus(cfg), "viewer").bus)
    try:
        viewer = Viewer(bus, cfg.episode.vehicle, CameraParams.from_config(cfg.sensor),
                        args.host, args.port, map_hz=args.map_hz, rollouts=args.rollouts)
    except RuntimeError as exc:           # the port is taken
        bus.close()
        print(f"vamppi view: cannot serve on {args.host}:{args.port}: {exc}", file=sys.stderr)
        return 2
    print(f"vamppi view: Foxglove WebSocket on ws://{args.host}:{viewer.port} (in the "
          "Foxglove app: Open connection, Foxglove WebSocket)", file=sys.stderr, flush=True)
    try:
        stop.wait(args.duration)
    finally:
        stats = viewer.close()
        bus.close()
    print(json.dumps(stats), flush=True)
    return 0


def cmd_export_foxglove(args: argparse.Namespace, cfg: Config) -> int:
    from deploy.recording.foxglove import export
    report = export(args.input, args.output, args.map_stride, args.rollouts)
    print(json.dumps(report), flush=True)
    return 0


def _pipeline_commands(sub: Any) -> None:
    """The pipeline on the bus: launch it, one service, a router, health, swaps, certs."""
    p = sub.add_parser("up", help="embedded router + every service as a process; one episode")
    add_config_args(p)
    p.add_argument("--wall-timeout", type=float, default=900.0,
                   help="give up after this many wall-clock seconds")
    p.add_argument("--record", metavar="FILE.mcap", help="record every message of the episode")
    p.add_argument("--insecure", action="store_true",
                   help="plain TCP, no access control (default: mutual TLS on loopback with "
                        "certificates made on first use, docs/security.md)")
    p.add_argument("--view", action="store_true",
                   help="serve the episode live to Foxglove too (vamppi view, docs/foxglove.md)")
    add_view_args(p, prefix="view-")
    p.set_defaults(func=cmd_up)

    p = sub.add_parser("service", help="run one service on its own")
    p.add_argument("name", choices=sorted(SERVICE_MAINS))
    p.add_argument("--instance", default="0", help="instance id (liveliness, health)")
    p.add_argument("--stop-with-parent", action="store_true",
                   help="stop when the parent process dies (set by vamppi up)")
    p.add_argument("--role", choices=("active", "standby", "candidate", "replay"),
                   default="active", help="planner: what it does (docs/hotswap.md)")
    p.add_argument("--standby", action="store_true",
                   help="planner: a hot standby (--role standby)")
    p.add_argument("--take-over-after", type=float, default=0.0, metavar="S",
                   help="planner, candidate: solve in shadow for S seconds, then ask for "
                        "the authority")
    p.add_argument("--take-over-at", type=float, default=0.0, metavar="T",
                   help="planner, candidate: ask for the authority once the episode reaches "
                        "T (simulation seconds)")
    p.add_argument("--keep-old", action="store_true",
                   help="planner, candidate: the planner it replaces stands by, not retires")
    add_config_args(p)
    add_bus_args(p)
    p.set_defaults(func=cmd_service)

    p = sub.add_parser("router", help="a standalone Zenoh router (default tcp/127.0.0.1:7447, "
                                      "this machine only; --listen tcp/0.0.0.0:7447 for others)")
    add_config_args(p, shorthands=False)       # a router runs no episode
    add_bus_args(p)
    p.set_defaults(func=cmd_router)

    p = sub.add_parser("health", help="live service instances and their counters")
    add_config_args(p)
    add_bus_args(p)
    p.set_defaults(func=cmd_health)

    p = sub.add_parser("swap", help="hot-swap the planner: a new instance takes over")
    p.add_argument("service", choices=("planner",))
    p.add_argument("--instance", help="the new instance's id (default: a fresh one)")
    p.add_argument("--to", metavar="INSTANCE",
                   help="hand the authority to this running planner instance (a standby) "
                        "instead of starting one")
    p.add_argument("--shadow", type=float, default=0.0, metavar="S",
                   help="solve in shadow for S seconds before taking over (plans on "
                        "vamppi/<vehicle>/planner/shadow)")
    p.add_argument("--timeout", type=float, default=120.0,
                   help="give up (the old planner keeps control) after this many seconds")
    p.add_argument("--keep-old", action="store_true",
                   help="the replaced planner stands by instead of retiring")
    add_config_args(p)
    add_bus_args(p)
    p.set_defaults(func=cmd_swap)

    p = sub.add_parser("certs", help="a local CA and a certificate per role (mutual TLS)")
    p.add_argument("dir", help="where the CA and certificates are written (the CA is kept)")
    p.add_argument("--name", action="append", metavar="ROLE[-INSTANCE]",
                   help="a certificate to make (repeatable; default: one per role)")
    p.add_argument("--host", action="append", default=["localhost", "127.0.0.1"],
                   help="a name or address the certificates are valid for (repeatable)")
    p.add_argument("--days", type=int, default=365)
    p.add_argument("--revoke", action="append", metavar="NAME",
                   help="deny this certificate from now on: listed in DIR/revoked.txt, its "
                        "files deleted; restart the routers (repeatable)")
    p.set_defaults(func=cmd_certs)


def _recording_commands(sub: Any) -> None:
    """Recordings: record, recover, replay, timing, export to Foxglove."""
    p = sub.add_parser("record", help="record bus traffic to MCAP (Ctrl-C stops)")
    p.add_argument("-o", "--output", required=True, metavar="FILE.mcap")
    p.add_argument("--keys", help="key expression (default vamppi/<vehicle>/**)")
    p.add_argument("--duration", type=float, help="stop after this many seconds")
    p.add_argument("--flush-interval", type=float, default=0.5,
                   help="seconds between chunk flushes: what a crash may lose")
    add_config_args(p)
    add_bus_args(p)
    p.set_defaults(func=cmd_record)

    p = sub.add_parser("recover", help="make a crashed recording readable and complete")
    p.add_argument("file")
    p.add_argument("-o", "--output", help="default FILE.recovered.mcap")
    p.add_argument("--force", action="store_true", help="rewrite even a complete file")
    p.set_defaults(func=cmd_recover)

    p = sub.add_parser("replay", help="publish a recording, or feed it to fresh services")
    p.add_argument("file")
    p.add_argument("--rate", type=float, default=1.0, help="time scale; 0 = as fast as possible")
    p.add_argument("--topics", help="comma-separated topics or keys (default: all)")
    p.add_argument("--loop", action="store_true")
    p.add_argument("--start-offset", type=float, default=0.0, metavar="S",
                   help="skip the first S seconds")
    p.add_argument("--feed", metavar="SERVICES",
                   help="start fresh services (sensor, mapper, planner) in lockstep, feed them "
                        "the recorded inputs and compare their outputs")
    p.add_argument("--compare", action="store_true",
                   help="with --feed: report the first divergence (the default with --feed)")
    p.add_argument("--keep-going", action="store_true",
                   help="with --feed: go on after the first divergence")
    add_config_args(p)
    add_bus_args(p)
    p.set_defaults(func=cmd_replay)

    p = sub.add_parser("timing", help="rates, latencies, chain and solve times of a recording")
    p.add_argument("file")
    p.add_argument("--json", action="store_true")
    p.add_argument("--plots", metavar="DIR")
    p.set_defaults(func=cmd_timing)

    p = sub.add_parser("view", help="the bus live in Foxglove: a WebSocket server "
                                    "(docs/foxglove.md)")
    add_view_args(p)
    p.add_argument("--duration", type=float, help="stop after this many seconds")
    p.add_argument("--stop-with-parent", action="store_true",
                   help="stop when the parent process dies (set by vamppi up --view)")
    add_config_args(p, shorthands=False)
    add_bus_args(p)
    p.set_defaults(func=cmd_view)

    p = sub.add_parser("export-foxglove", help="a recording in encodings Foxglove decodes")
    p.add_argument("input")
    p.add_argument("output")
    p.add_argument("--map-stride", type=int, default=1,
                   help="export every n-th map (maps are 1.7 MB each as JSON)")
    p.add_argument("--rollouts", type=int, default=30, help="sampled rollouts drawn per plan")
    p.set_defaults(func=cmd_export_foxglove)


def _simulation_commands(sub: Any) -> None:
    """In-process: one episode, the Monte-Carlo experiment, scenarios."""
    p = sub.add_parser("run", help="one lockstep episode in-process, without the bus")
    add_config_args(p)
    p.set_defaults(func=cmd_run)

    p = sub.add_parser("plans", help="the plan at one instant of an in-process episode, priced "
                                     "beside the same plan carried out sooner")
    p.add_argument("--at", type=float, required=True, metavar="SECONDS",
                   help="the instant (simulated time) whose plan is priced")
    p.add_argument("--steady", action="store_true",
                   help="also price plans made by hand: each steering angle held with each "
                        "force, and braking first, then a steering angle held")
    p.add_argument("--price-with", action="append", default=[], metavar="SECTION.KEY=VALUE",
                   help="price every plan again under the configuration with this override "
                        "(repeatable): same state, same map")
    p.add_argument("--top", type=int, metavar="N", help="the table's N cheapest plans only")
    p.add_argument("--json", action="store_true")
    add_config_args(p)
    p.set_defaults(func=cmd_plans)

    p = sub.add_parser("experiment", help="the paper's Monte-Carlo comparison, in-process")
    p.add_argument("--scenario", dest="scenarios", default="alleyway,offroad",
                   help="comma-separated scenarios: built-in names, scenario files, and "
                        "directories of them (every *.toml inside)")
    p.add_argument("--controllers", default="va,deterministic,prescient")
    p.add_argument("--samples", dest="samples_list", default="400", help="e.g. 400,1000,4000")
    p.add_argument("--runs", type=int, default=20, help="runs per scenario/controller/samples")
    p.add_argument("--seed", dest="seed_base", type=int, default=0,
                   help="planner seed of the first run; run i uses seed + i")
    p.add_argument("--out", required=True, help="output directory (resumable)")
    add_runner_args(p)
    add_config_args(p, shorthands=False)
    p.set_defaults(func=cmd_experiment)

    p = sub.add_parser("tables", help="the tables of record (docs/results): whether each is "
                                      "today's program's, and making them again")
    p.add_argument("names", nargs="*", metavar="NAME",
                   help="these tables only (default: every one; `vamppi tables` lists them)")
    p.add_argument("--root", default="docs/results",
                   help="the directory holding the tables' directories (default docs/results)")
    p.add_argument("--run", action="store_true",
                   help="make the tables into --root, resuming what is there; a directory "
                        "of another configuration is refused: give a new --root")
    p.add_argument("--stale", action="store_true",
                   help="only the tables that docs/results does not hold as today's program "
                        "would make them")
    add_runner_args(p)
    p.add_argument("--json", action="store_true", help="JSON rows, each with its command")
    p.set_defaults(func=cmd_tables)

    p = sub.add_parser("scenario", help="a scenario as JSON and its picture; its file; "
                                        "generated worlds")
    p.add_argument("action", nargs="?", default="show",
                   choices=("show", "export", "generate", "set"),
                   help="show (default): --scenario's JSON; export: its scenario file; "
                        "generate: the world of --kind and --seed (default 1); set: "
                        "--per-kind worlds of every kind into OUT/tune and OUT/heldout")
    p.add_argument("--plot", metavar="FILE.png", help="show: write the top-down picture")
    p.add_argument("--kind", help="generate: the world's kind (deploy/sim/generate.py "
                                  "ALL_KINDS); set: only these kinds (comma-separated; "
                                  "default: the benchmark's four, KINDS)")
    p.add_argument("--out", help="export, generate: the file (default: print it); "
                                 "set: the directory")
    p.add_argument("--per-kind", type=_positive_int, default=16,
                   help="set: worlds of each kind, seeds 1 .. N: the odd seeds tune, "
                        "the even ones are held out")
    p.add_argument("--no-drive", action="store_true",
                   help="generate: skip the prescient controller's check drive")
    p.add_argument("--jobs", type=_positive_int, default=1, help="set: worlds drawn side by side")
    add_config_args(p)
    p.set_defaults(func=cmd_scenario)


def _analysis_commands(sub: Any) -> None:
    """An experiment's runs taken apart."""
    p = sub.add_parser("reveal", help="when each hidden obstacle was first seen in a run, "
                                      "and whether the vehicle could still stop")
    p.add_argument("runs", help="an experiment's runs.jsonl (or its directory)")
    p.add_argument("--controller", dest="only", help="only these controllers (a,b)")
    p.add_argument("--all-obstacles", action="store_true", help="every obstacle, not only hidden")
    p.add_argument("--json", action="store_true", help="JSON rows instead of a table")
    add_config_args(p, shorthands=False)
    p.set_defaults(func=cmd_reveal)

    p = sub.add_parser("collisions", help="what each collision of an experiment was on, and "
                                          "how long the map had shown it")
    p.add_argument("runs", nargs="+",
                   help="experiments' runs.jsonl (or their directories): one table over all")
    p.add_argument("--controller", dest="only", help="only these controllers (a,b)")
    p.add_argument("--rerun", action="store_true",
                   help="run again the collisions recorded without attribution (older records)")
    p.add_argument("--json", action="store_true", help="JSON rows instead of a table")
    add_config_args(p, shorthands=False)
    p.set_defaults(func=cmd_collisions)

    p = sub.add_parser("timeouts", help="how each run that timed out ended: standing (since "
                                        "when) or still driving, and how near the goal")
    p.add_argument("runs", nargs="+",
                   help="experiments' runs.jsonl (or their directories): one table over all")
    p.add_argument("--controller", dest="only", help="only these controllers (a,b)")
    p.add_argument("--json", action="store_true", help="JSON rows instead of a table")
    add_config_args(p, shorthands=False)
    p.set_defaults(func=cmd_timeouts)

    p = sub.add_parser("near-goal", help="runs split by whether a hidden obstacle stands "
                                         "near the goal, successes compared")
    p.add_argument("runs", nargs="+",
                   help="experiments' runs.jsonl (or their directories): one table over all")
    p.add_argument("--within", type=float, default=12.0, metavar="M",
                   help="a hidden obstacle's footprint nearer the goal than this counts as "
                        "near (default 12)")
    p.add_argument("--controller", dest="only", help="only these controllers (a,b)")
    p.add_argument("--json", action="store_true", help="JSON rows instead of a table")
    add_config_args(p, shorthands=False)
    p.set_defaults(func=cmd_near_goal)


def _tool_commands(sub: Any) -> None:
    """Benchmarks and the configuration."""
    p = sub.add_parser("bench", help="speed benchmarks (a table, or JSON with --json)")
    p.add_argument("what", choices=("planner", "mapper", "bus", "pipeline", "peer", "record",
                                    "faults", "swaps", "security", "view", "startup"))
    p.add_argument("--samples", dest="samples_list",
                   help="sample counts K (planner, peer: 400,800,1000,4000; pipeline: 800)")
    p.add_argument("--controllers", help="planner: va,deterministic; pipeline: va")
    p.add_argument("--duration", type=float, default=30.0,
                   help="pipeline: wall seconds measured after the episode starts; "
                        "record: seconds of traffic")
    p.add_argument("--scenario", help="pipeline: episode.scenario (default: the config's)")
    p.add_argument("--record", metavar="FILE.mcap",
                   help="pipeline: record each case (vamppi timing analyses the same run)")
    p.add_argument("--reps", type=int, default=None,
                   help="timed repetitions per case (default 20; view: episodes per case, "
                        "3; startup: 5)")
    p.add_argument("--forms", help="planner: the kernels' forms side by side, e.g. "
                                   "native,jax (each sets planner.va_kernel and "
                                   "planner.rollout_kernel; default: as configured)")
    p.add_argument("--json", action="store_true", help="one JSON document instead of a table")
    add_config_args(p, shorthands=False)
    p.set_defaults(func=cmd_bench)

    p = sub.add_parser("config", help="print the effective configuration")
    p.add_argument("--markdown", action="store_true",
                   help="print docs/parameters.md (every parameter, default, meaning)")
    add_config_args(p)
    p.set_defaults(func=cmd_config)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="vamppi", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("-v", "--verbose", action="store_true")
    sub = parser.add_subparsers(dest="command", required=True)
    _pipeline_commands(sub)
    _recording_commands(sub)
    _simulation_commands(sub)
    _analysis_commands(sub)
    _tool_commands(sub)
    return parser


def main(argv: list[str] | None = None) -> Any:
    args = build_parser().parse_args(argv)
    _setup_logging(args.verbose)
    keep_large_buffers()
    compile_cache.enable()
    # before JAX starts: no vamppi process preallocates a GPU; a pipeline's services share
    # one, and a benchmark or an experiment beside them takes only what it uses
    share_device(PIPELINE_PROCESSES if args.func is cmd_service else 1)
    try:
        cfg = config_from_args(args)
    except ConfigError as exc:
        print(f"vamppi: bad configuration: {exc}", file=sys.stderr)
        return 2
    from deploy.recording.record import RecordingError
    try:
        return args.func(args, cfg)
    except (RecordingError, FileNotFoundError, IsADirectoryError, NoRouter) as exc:
        print(f"vamppi {args.command}: {exc}", file=sys.stderr)
        return 2
    except BrokenPipeError:
        # the reader went away (`vamppi config | head`): quiet, as a shell tool, and no
        # second error when Python flushes stdout at exit
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 128 + signal.SIGPIPE
    except Exception as exc:
        if type(exc).__module__.split(".")[0] != "zenoh":
            raise
        why = str(exc).split("  at ")[0]          # zenoh appends its source location
        print(f"vamppi {args.command}: the bus: {why} (is a router running at "
              f"{', '.join(cfg.bus.connect) or 'the endpoint given'}?)", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
