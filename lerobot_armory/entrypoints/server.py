"""``lerobot-armory-server``: the serving process (front end + scheduler + engine).

    lerobot-armory-server --policy.path=lerobot/pi05_libero --policy.device=cuda \\
        --scheduler.type=lookahead --max_batch_size=3 --host=127.0.0.1 --port=8080

Start-up loads the policy through LeRobot's factory, profiles ``d_infer(b)`` for b = 1..cap (or
loads it: ``--latency_profile``), prints a summary, then serves until SIGINT/SIGTERM, logging one
line of fleet status per second. A profiled table keeps learning from the batches served
(``--latency_learning``); a loaded one is pinned.
Shutdown finishes the in-flight batch, tells every robot, and exits 0.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import logging
import signal
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from lerobot_armory.cli_util import run_or_exit
from lerobot_armory.errors import ConfigError
from lerobot_armory.inference_latency import LatencyProfile, OnlineLatency
from lerobot_armory.proto.limits import DEFAULT_MAX_MESSAGE_BYTES
from lerobot_armory.schedulers import SchedulerConfig
from lerobot_armory.engine.startup import StartedEngine, start_engine
from lerobot_armory.serving.fleet import Fleet
from lerobot_armory.serving.admission import AdmissionLimiter
from lerobot_armory.serving.config import OpenpiOptions, ServerConfig, parse_server_args
from lerobot_armory.serving.grant_rules import GrantRules
from lerobot_armory.serving.registration import Registrar
from lerobot_armory.serving.logs import configure_logging
from lerobot_armory.serving.policies_file import PolicyEntry, load_policies
from lerobot_armory.engine.protocol import Engine
from lerobot_armory.serving.loop import BatchRecord, ServedPolicy, ServingLoop
from lerobot_armory.serving.session import DEFAULT_POLICY
from lerobot_armory.serving.metrics import ServerMetrics, status_line
from lerobot_armory.entrypoints.openpi.endpoint import OpenpiEndpoint
from lerobot_armory.entrypoints.openpi.keymap import KeyMap
from lerobot_armory.serving.security import AuthTokens, OperatorTokens, read_tls
from lerobot_armory.serving.swap import LoadedPolicy, Loader, PolicyShape, PolicySwapper, SwapRefused
from lerobot_armory.engine.options import EngineOptions, PolicyOptions, RTCOptions
from lerobot_armory.entrypoints.grpc.admin import AdminService
from lerobot_armory.entrypoints.grpc.service import ArmoryService, PolicyInfo, RunningServer, shutdown_notice, start_grpc_server

log = logging.getLogger("lerobot_armory.server")


class ArmoryServer:
    """The whole serving process in one object: fleet, loop, gRPC front end.

    ``engine`` is anything with ``infer(observations, tasks)``; ``policy`` says what robots must
    send. Tests build it with a real :class:`PolicyEngine` on an ephemeral port. With
    ``learn_latency`` the scheduler's ``d_infer`` table follows the measured batch times
    (:class:`OnlineLatency`, seeded with ``profile``); without, ``profile`` is used as given.
    """

    def __init__(
        self,
        engine: Engine,
        policy: PolicyInfo,
        profile: LatencyProfile,
        scheduler: SchedulerConfig,
        max_batch_size: int,
        host: str = "127.0.0.1",
        port: int = 0,
        max_robots: int = 64,
        max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES,
        clock=time.monotonic,
        auth: AuthTokens | None = None,
        tls: tuple[bytes, bytes] | None = None,
        max_obs_rate_hz: float = 0.0,
        learn_latency: bool = False,
        grant_rules: GrantRules | None = None,
        operators: OperatorTokens | None = None,
        loader: Loader | None = None,
        policy_options: PolicyOptions | None = None,
        policy_name: str = DEFAULT_POLICY,
        others: tuple[ExtraPolicy, ...] = (),
    ) -> None:
        self.policy = policy
        self.profile = profile
        grant_rules = grant_rules or GrantRules.builtin()
        # The shortest horizon a robot may ask for follows the fastest policy's single-robot batch.
        grant_rules.batch_s = min([profile.latency_s(1), *(o.profile.latency_s(1) for o in others)])
        self.scheduler_config = scheduler
        self.scheduler = scheduler.make(profile, max_batch_size)
        history = max([engine.history_steps, *(o.engine.history_steps for o in others)])
        self.fleet = Fleet(clock, max_robots, history_steps=history)
        self.batch_log: list[BatchRecord] = []
        self.batch_listeners: list[Callable[[BatchRecord], None]] = [self._keep_recent]
        # Built even when not learning: it then reports the fixed table (drift 0) to metrics.
        self.latency = OnlineLatency(profile, max_batch_size)
        self.learn_latency = learn_latency
        served = tuple(
            ServedPolicy(
                o.name, o.engine, scheduler.make(o.profile, o.max_batch_size),
                OnlineLatency(o.profile, o.max_batch_size) if learn_latency else None,
            )
            for o in others
        )  # fmt: skip
        self.loop = ServingLoop(
            self.fleet, engine, self.scheduler, on_batch=self._on_batch, latency=self.latency if learn_latency else None,
            policy_name=policy_name, others=served,
        )  # fmt: skip
        # One registration path (credentials, one admission limit per peer and credential, the
        # grant rules), whichever entrypoint the registrations use.
        self.registrar = Registrar(self.fleet, grant_rules, AdmissionLimiter(), auth)
        self.service = ArmoryService(
            self.fleet, policy, max_message_bytes, self.registrar, max_obs_rate_hz,
            policy_name=policy_name, others={o.name: o.info for o in others},
        )  # fmt: skip
        self.metrics = ServerMetrics(self.fleet, self.loop.stats, max_batch_size, self.latency)
        self.batch_listeners.append(self.metrics.on_batch)
        # Live checkpoint swaps (lerobot-armory-admin swap): refused unless operator tokens are set.
        options = policy_options or PolicyOptions(
            getattr(engine, "path", ""), getattr(engine, "device", None), getattr(engine, "cpu_threads", None),
            list(getattr(engine, "overrides", [])),
        )  # fmt: skip
        current = _served_now(options, engine, policy)
        loader = loader or policy_loader()
        self.swapper = PolicySwapper(self.loop, current, loader, self._swapped, policy_name)
        self.swappers = {policy_name: self.swapper}
        for o in others:
            o_current = _served_now(o.options or PolicyOptions(getattr(o.engine, "path", "")), o.engine, o.info)
            self.swappers[o.name] = PolicySwapper(self.loop, o_current, loader, self._other_swapped(o.name), o.name)
        for name, swapper in self.swappers.items():
            swapper.listeners.append(functools.partial(self.metrics.on_swap, policy=name))
            self.metrics.set_policy(name, swapper.current.path)
        self.admin = AdminService(self.swapper, self.fleet, operators, self.status_line, self.swappers)
        self._tls = tls
        self._stop_metrics: Callable[[], None] | None = None
        self.openpi: OpenpiEndpoint | None = None
        self._host, self._port = host, port
        self._max_robots, self._max_message_bytes = max_robots, max_message_bytes
        self.grpc: RunningServer | None = None
        self._stopped = threading.Event()
        self._batch_file = None

    @property
    def port(self) -> int:
        assert self.grpc is not None, "server not started"
        return self.grpc.port

    @property
    def address(self) -> str:
        return f"{self._host}:{self.port}"

    def _swapped(self, new: LoadedPolicy) -> None:
        """After a swap: registrations and openpi handshakes describe the new policy; the shortest
        horizon follows its d_infer."""
        self.policy = dataclasses.replace(self.policy, description=new.description)
        self.service.policy = self.policy
        if self.openpi is not None:  # the handshake dict is read per connection: new ones see the new policy
            self.openpi.metadata["policy"] = new.description
        if new.d_infer:
            self.registrar.rules.batch_s = new.d_infer[0]

    def _other_swapped(self, name: str) -> Callable[[LoadedPolicy], None]:
        """After a swap of a policy other than the first: registrations describe the new checkpoint."""

        def swapped(new: LoadedPolicy) -> None:
            self.service.others[name] = dataclasses.replace(self.service.others[name], description=new.description)

        return swapped

    def _on_batch(self, record: BatchRecord) -> None:
        for listener in self.batch_listeners:
            listener(record)

    def _keep_recent(self, record: BatchRecord) -> None:
        self.batch_log.append(record)
        if len(self.batch_log) > 20000:  # bounded: a server runs for weeks
            del self.batch_log[:10000]

    def log_batches_to(self, path: str) -> None:
        """Append every batch as one JSON line to ``path`` (robots, i_start, times)."""
        handle = open(path, "a", buffering=1)  # noqa: SIM115 - closed in stop()
        self._batch_file = handle
        self.batch_listeners.append(lambda record: handle.write(json.dumps(dataclasses.asdict(record)) + "\n"))

    def serve_metrics(self, port: int) -> int:
        """Start the Prometheus endpoint on the gRPC host; returns the port actually bound
        (``port=0`` picks a free one)."""
        bound, self._stop_metrics = self.metrics.serve(port, self._host)
        return bound

    def serve_openpi(self, options: OpenpiOptions, keymap: str | None = None) -> int:
        """Start the openpi-compatible websocket endpoint on the gRPC host; returns its port.

        Raises:
            ConfigError: the policy reads an observation history: an openpi client sends one
                observation per request, not one per control tick.
        """
        if self.fleet.history_steps > 1:
            raise ConfigError(
                "openpi.port",
                f"the policy reads the last {self.fleet.history_steps} observations of each robot (n_obs_steps), and an "
                "openpi client sends one per request, not one per control tick; serve it to lerobot-armory-client robots",
            )
        self.openpi = OpenpiEndpoint(
            self.fleet, KeyMap.load(self.policy.wire_features, keymap), options, self.policy.chunk_size,
            {"server": "lerobot-armory", "policy": self.policy.description, "chunk_size": self.policy.chunk_size,
             "action_names": self.policy.action_names},
            self._host, self._max_message_bytes, self.registrar, self._tls,
            next(iter(self.swappers)),  # the first policy serves openpi clients, by its name
        ).start()  # fmt: skip
        return self.openpi.port

    def start(self) -> ArmoryServer:
        self.loop.start()
        self.grpc = start_grpc_server(
            self.service, self._host, self._port, self._max_robots, self._max_message_bytes, self._tls, admin=self.admin
        )
        return self

    def stop(self, grace_s: float = 2.0) -> None:
        """Graceful stop: refuse new work, finish the in-flight batch, tell robots, close."""
        if self._stopped.is_set():
            return
        self._stopped.set()
        if self.grpc is not None:
            self.grpc.set_serving(False)
        if self.openpi is not None:
            self.openpi.stop()
        self.loop.stop(timeout=60.0)  # the in-flight batch completes and its chunks are queued
        shutdown_notice(self.fleet)()
        if self.grpc is not None:
            self.grpc.server.stop(grace_s).wait()
        if self._batch_file is not None:
            self._batch_file.close()
        if self._stop_metrics is not None:
            self._stop_metrics()

    def status_line(self) -> str:
        """One line of fleet status (logged every second); after a swap, the policy served and the swaps."""
        line = status_line(self.fleet, self.loop.stats, self.latency if self.learn_latency else None)
        if len(self.loop.policies) > 1:
            by_policy = self.loop.stats.batches_by_policy
            line += " batches=" + ",".join(f"{name}:{by_policy[name]}" for name in self.loop.policies)
        counts = self.swapper.counts.by_result
        if any(counts.values()):
            line += f" policy={self.swapper.current.path} swaps=ok:{counts['ok']},refused:{counts['refused']},failed:{counts['failed']}"
        return line


@dataclass(frozen=True)
class ExtraPolicy:
    """A policy served beside the first from the same device (``--policies=FILE``).

    Attributes:
        name: what robots name at registration (``--policy_name``).
        engine: its engine.
        info: what registration checks against and tells the robot.
        profile: its ``d_infer(b)``.
        max_batch_size: its batch cap.
        options: how it was loaded (a swap of it reuses the device and threads).
    """

    name: str
    engine: Engine
    info: PolicyInfo
    profile: LatencyProfile
    max_batch_size: int
    options: PolicyOptions | None = None


def _served_now(options: PolicyOptions, engine: Engine, info: PolicyInfo) -> LoadedPolicy:
    """The policy a swapper starts from: what is served now (its d_infer is the scheduler's)."""
    shape = PolicyShape(tuple(info.wire_features), len(info.action_names), info.chunk_size, engine.history_steps)
    return LoadedPolicy(options, engine, shape, None, info.description)


def tune_process() -> None:
    """Process settings for serving: the device thread must get the GIL back quickly.

    Between two kernels the model's Python code needs the GIL; with CPython's default 5 ms switch
    interval a network thread holding it can delay every op of a forward pass. 0.5 ms keeps the
    device thread's waits short at a negligible cost to the network threads.
    """
    sys.setswitchinterval(0.0005)


def policy_loader(
    rtc: RTCOptions | None = None,
    engine_options: EngineOptions | None = None,
    profile_reps: int = 5,
    emulate_profile: str | None = None,
) -> Loader:
    """What a swap loads a checkpoint with: the engine, warmed up and profiled for b = 1..the
    policy's cap at the time of the swap (or wrapped in the emulated profile), as start-up does."""

    def load(options: PolicyOptions, drain: bool, max_batch_size: int) -> LoadedPolicy:
        if not drain:
            check_room_beside(options)
        started = start_engine(options, max_batch_size, rtc, engine_options, profile_reps, emulate_profile, quiet=True)
        engine, profile = started.engine, started.profile
        shape = PolicyShape(tuple(engine.wire_features), len(engine.action_names), engine.chunk_size, engine.history_steps)
        d_infer = [profile.latency_s(b) for b in range(1, max_batch_size + 1)]
        return LoadedPolicy(options, started.serving, shape, d_infer, engine.description)

    return load


def check_room_beside(options: PolicyOptions) -> None:
    """On a CUDA device, refuse a checkpoint whose weights (the size of its safetensors files, an
    estimate: activations and workspaces come on top) exceed the free device memory, beside the
    policy being served. Untested here (no GPU on the development machine); kept simple.

    Raises:
        SwapRefused: with the numbers, and the way out (a drain).
    """
    import torch

    device = options.device or ("cuda" if torch.cuda.is_available() else "cpu")
    if not device.startswith("cuda") or not Path(options.path).is_dir():
        return
    need = sum(p.stat().st_size for p in Path(options.path).glob("*.safetensors"))
    free, total = torch.cuda.mem_get_info(torch.device(device))
    if need > free:
        gib = 1 << 30
        raise SwapRefused(
            f"{options.path} needs about {need / gib:.2f} GiB (its safetensors) and {device} has {free / gib:.2f} GiB free "
            f"of {total / gib:.2f} GiB beside the policy served; swap with --drain=true to release it first"
        )


def latency_learning(cfg: ServerConfig, profile: LatencyProfile) -> tuple[bool, str]:
    """Whether the scheduler's ``d_infer`` learns from served batches, and why (for the summary)."""
    if cfg.latency_learning is not None:
        return cfg.latency_learning, f"--latency_learning={str(cfg.latency_learning).lower()}"
    if cfg.engine.emulate_profile:
        return False, "emulated latency: every batch takes exactly the profile"
    if profile.source != "profiled":
        return False, f"pinned by --latency_profile={cfg.latency_profile}"
    return True, "seeded with the start-up profile, follows the measured batch times"


def build_server(cfg: ServerConfig) -> tuple[ArmoryServer, str]:
    """Load the policy, warm it up, resolve ``d_infer`` and start serving on ``cfg.host:cfg.port``.

    Returns the running server and its start-up summary. ``serve`` and each replica of a cluster
    (:mod:`lerobot_armory.entrypoints.cluster.replica`) build the same server through here.
    """
    cfg.validate()
    grant_rules = cfg.fleet.load()  # before the model loads: a bad file is one line, at once
    entries = load_policies(cfg.policies) if cfg.policies else []
    tune_process()
    configure_logging(cfg.log_level, cfg.log_format)
    first = _options_of(cfg, entries[0]) if entries else cfg.policy
    started = _start(cfg, first, cfg.max_batch_size, latency_profile=None if entries else cfg.latency_profile)
    engine, serving_engine, profile, latency_note = started.engine, started.serving, started.profile, started.note
    info = PolicyInfo(engine.description, engine.wire_features, engine.action_names, engine.chunk_size)
    others = []
    for entry in entries[1:]:
        cap = entry.max_batch_size or cfg.max_batch_size
        options = _options_of(cfg, entry)
        o_started = _start(cfg, options, cap)
        o_engine, o_serving, o_profile = o_started.engine, o_started.serving, o_started.profile
        o_info = PolicyInfo(o_engine.description, o_engine.wire_features, o_engine.action_names, o_engine.chunk_size)
        others.append(ExtraPolicy(entry.name, o_serving, o_info, o_profile, cap, options))
    first_cap = (entries[0].max_batch_size if entries else None) or cfg.max_batch_size
    auth = AuthTokens.load(cfg.auth_token_file) if cfg.auth_token_file else None
    operators = OperatorTokens.load(cfg.operator_token_file, auth) if cfg.operator_token_file else None
    tls = read_tls(cfg.tls_cert, cfg.tls_key)
    if auth is not None and tls is None:
        log.warning(
            "auth tokens travel in plaintext (no --tls_cert/--tls_key): anyone on the network path can read and reuse them"
        )
    learn, learn_why = latency_learning(cfg, profile)
    server = ArmoryServer(
        serving_engine, info, profile, cfg.scheduler, first_cap, cfg.host, cfg.port, cfg.max_robots,
        int(cfg.max_message_mb * (1 << 20)), auth=auth, tls=tls, max_obs_rate_hz=cfg.max_obs_rate_hz,
        learn_latency=learn, grant_rules=grant_rules, operators=operators,
        loader=policy_loader(cfg.rtc, cfg.engine, cfg.profile_reps, cfg.engine.emulate_profile),
        policy_options=first, policy_name=entries[0].name if entries else DEFAULT_POLICY, others=tuple(others),
    )  # fmt: skip
    if cfg.batch_log:
        server.log_batches_to(cfg.batch_log)
    server.start()
    metrics_port = server.serve_metrics(cfg.metrics_port) if cfg.metrics_port is not None else None
    openpi_port = server.serve_openpi(cfg.openpi, cfg.openpi.keymap) if cfg.openpi.port is not None else None
    features = "\n".join(f"    {f.name}: {f.describe()}" for f in engine.wire_features)
    policies_line = ""
    if entries:
        policies_line = "  policies (robots name one with --policy_name): " + "; ".join(
            [f"{entries[0].name} (b <= {first_cap})", *(f"{o.name}: {o.info.description} (b <= {o.max_batch_size})" for o in others)]
        ) + "\n"
    summary = (
        f"lerobot-armory-server listening on {server.address}\n"
        f"  policy: {engine.description}\n"
        f"{policies_line}"
        f"  observation features robots must send:\n{features}\n"
        f"  actions: {len(engine.action_names)} dims ({', '.join(engine.action_names)}), chunk size H={engine.chunk_size}\n"
        f"  scheduler: {cfg.scheduler.label()} (max batch size {cfg.max_batch_size})\n"
        f"  security: {'TLS' if tls else 'plaintext'}, {'token auth' if auth else 'no auth'}, "
        f"{'operator token (admin calls on)' if operators else 'no operator token (admin calls off)'}, "
        f"max {cfg.max_robots} robots, {cfg.max_message_mb:g} MiB messages, {cfg.max_obs_rate_hz:g} obs/s per robot\n"
        f"  grant rules: {grant_rules.describe()}\n"
        f"  metrics: {f'http://{cfg.host}:{metrics_port}/metrics' if metrics_port is not None else 'off'}\n"
        f"  openpi clients: {f'{"wss" if tls else "ws"}://{cfg.host}:{openpi_port} (replan {cfg.openpi.replan_steps} steps at {cfg.openpi.fps:g} fps)' if openpi_port is not None else 'off'}\n"
        f"{profile.describe(cfg.max_batch_size)}{latency_note}\n"
        f"  d_infer learning: {'on' if learn else 'off'} ({learn_why})"
    )
    return server, summary


def _options_of(cfg: ServerConfig, entry: PolicyEntry) -> PolicyOptions:
    """The ``--policy.*`` options of one policy of ``--policies``: the server's device and
    threads, the command line's overrides, then the file's."""
    return PolicyOptions(entry.path, cfg.policy.device, cfg.policy.cpu_threads, [*cfg.policy.overrides, *entry.overrides])


def _start(cfg: ServerConfig, options: PolicyOptions, max_batch_size: int, latency_profile: str | None = None) -> StartedEngine:
    """One policy of the server, started for serving with the server's engine options."""
    return start_engine(
        options, max_batch_size, cfg.rtc, cfg.engine, cfg.profile_reps, cfg.engine.emulate_profile, latency_profile
    )


def serve(cfg: ServerConfig) -> None:
    """Build everything, print the summary, serve until a signal."""
    server, summary = build_server(cfg)
    print(summary, flush=True)
    stop = threading.Event()

    def on_signal(signum: int, _frame) -> None:
        log.info("received %s: finishing the in-flight batch and closing streams", signal.Signals(signum).name)
        stop.set()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    next_status = time.monotonic() + cfg.status_interval_s
    while not stop.wait(min(1.0, cfg.status_interval_s) if cfg.status_interval_s > 0 else 1.0):
        if server.loop.error is not None:  # checked every second, whatever the status interval
            log.error("serving loop died: %s", server.loop.error)
            server.stop()
            sys.exit(1)
        if cfg.status_interval_s > 0 and time.monotonic() >= next_status:
            next_status += cfg.status_interval_s
            log.info("%s", server.status_line())
    server.stop()
    log.info("stopped cleanly")


def main(argv: list[str] | None = None) -> None:
    """Console entry point (see :func:`parse_server_args` for ``--policy.<field>``)."""
    run_or_exit(serve, parse_server_args(ServerConfig, argv, "lerobot-armory-server"), "lerobot-armory-server")


if __name__ == "__main__":
    main()
