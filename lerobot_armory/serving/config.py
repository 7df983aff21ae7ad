"""The server's whole configuration, in one place, validated once (``ServerConfig.validate``).

Every option of ``lerobot-armory-server`` (and of each replica of ``lerobot-armory-cluster``) is a
field here or of a sub-option dataclass here: the engine's (``--policy.*``, ``--engine.*``,
``--rtc.*``, defined beside the engine in :mod:`lerobot_armory.engine.options`), the fleet
policy's (``--fleet.*``) and the openpi endpoint's (``--openpi.*``). Plain dataclasses: parsing is
draccus (LeRobot's style), assembly is :mod:`lerobot_armory.entrypoints.server`.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import TypeVar

from lerobot_armory.cli_util import parse_or_exit, split_passthrough
from lerobot_armory.engine.options import EngineOptions, PolicyOptions, RTCOptions
from lerobot_armory.errors import ConfigError
from lerobot_armory.proto.limits import DEFAULT_MAX_MESSAGE_BYTES
from lerobot_armory.schedulers import LookaheadConfig, SchedulerConfig
from lerobot_armory.serving.grant_rules import GrantRules

__all__ = ["EngineOptions", "FleetOptions", "OpenpiOptions", "PolicyOptions", "RTCOptions", "ServerConfig", "parse_server_args"]


@dataclass
class OpenpiOptions:
    """``--openpi.*``: the openpi-compatible endpoint (off unless ``--openpi.port`` is set).

    Attributes:
        port: websocket port (openpi's default is 8000); unset: no endpoint.
        keymap: JSON/YAML file mapping openpi observation keys to the policy's features.
        fps: control rate the mirror assumes for openpi clients (they do not say theirs).
        replan_steps: actions an openpi client executes per chunk (LIBERO's example: 5).
        tier: ``fast`` or ``slow`` for the schedulers' reports.
    """

    port: int | None = None
    keymap: str | None = None
    fps: float = 20.0
    replan_steps: int = 5
    tier: str = "slow"

    def validate(self) -> None:
        if self.port is not None and not 0 <= self.port <= 65535:
            raise ConfigError("openpi.port", f"must be in 0..65535, got {self.port}")
        if not self.fps > 0:
            raise ConfigError("openpi.fps", f"must be > 0, got {self.fps}")
        if self.replan_steps < 1:
            raise ConfigError("openpi.replan_steps", f"must be >= 1, got {self.replan_steps}")


@dataclass
class FleetOptions:
    """``--fleet.rules=FILE``: the operator's grant rules (None: the built-in default).

    Attributes:
        rules: the grant rules file (serving/grant_rules.py).
        policy: its former name (``--fleet.policy``), still read; giving both is an error.
    """

    rules: str | None = None
    policy: str | None = None

    def load(self) -> GrantRules:
        if self.rules and self.policy:
            raise ConfigError("fleet.rules", "given twice: --fleet.rules and its former name --fleet.policy; keep --fleet.rules")
        path = self.rules or self.policy
        return GrantRules.load(path) if path else GrantRules.builtin()


@dataclass
class ServerConfig:
    """Options of ``lerobot-armory-server``.

    Attributes:
        policy: ``--policy.path`` (local directory or hub id), ``--policy.device``,
            ``--policy.cpu_threads``, and any field of the policy's own config
            (``--policy.dtype=bfloat16``, ``--policy.compile_model=true``,
            ``--policy.num_inference_steps=5``, ``--policy.n_action_steps=...``).
        engine: ``--engine.emulate_profile=NAME|FILE`` replays a latency profile (see engine/emulation.py);
            ``--engine.cuda_graphs=auto|on|off`` serves π0.5 through the static sampler recorded as
            one CUDA graph per batch bucket (``--engine.graph_buckets``, ``--engine.attention``,
            ``--engine.static_sampler``; see engine/cuda_graphs.py).
        rtc: ``--rtc.enabled=true``: real-time chunking from the mirror (π0, π0.5, SmolVLA): each
            chunk is guided toward what its robot executes while it is computed and sent, with
            ``--rtc.execution_horizon``, ``--rtc.max_guidance_weight`` and
            ``--rtc.prefix_attention_schedule`` as in LeRobot (see engine/rtc.py).
        scheduler: ``--scheduler.type=rr|edf|lookahead`` and its knobs.
        max_batch_size: batch cap b.
        host: bind address (loopback unless told otherwise).
        port: TCP port (0 picks a free one and prints it).
        latency_profile: a built-in name or a JSON file to load ``d_infer`` from instead of
            profiling; a path that does not exist yet is profiled and saved there.
        latency_learning: keep learning ``d_infer`` from the batches actually served and hand the
            scheduler the updated table (true/false). Unset: learn when the table was profiled at
            start-up; not when ``--latency_profile`` loaded one (pinned) or
            ``--engine.emulate_profile`` replays one (batches take exactly the profile).
        profile_reps: timed repetitions per batch size when profiling.
        max_robots: robots served at once.
        max_message_mb: largest message accepted, MiB.
        status_interval_s: seconds between fleet status lines (0: none).
        log_level: debug, info, warning, error.
        log_format: ``text`` or ``json`` (one JSON object per line, for log shippers).
        batch_log: append one JSON line per dispatched batch to this file (benchmarks).
        metrics_port: serve Prometheus metrics on this port (same host as gRPC); unset: off.
        tls_cert / tls_key: PEM files; with both, the gRPC port speaks TLS only.
        auth_token_file: robots must present a token from this file (see serving/security.py).
        operator_token_file: tokens (one a line) that may call the admin RPCs
            (``lerobot-armory-admin swap|status``: swap the served checkpoint live); distinct from
            every robot token. Unset: admin calls are refused.
        max_obs_rate_hz: observations per second a robot may send (0: unlimited).
        fleet: ``--fleet.rules=FILE`` (YAML or JSON): what each robot may be granted (weight,
            tier, fps and horizon bounds, device share); see serving/grant_rules.py. Without it
            every robot's weight is capped at 1.
        openpi: ``--openpi.port=8000``: also speak openpi's websocket policy protocol (an
            unchanged openpi client is served batched with the gRPC robots); ``--openpi.keymap``,
            ``--openpi.fps``, ``--openpi.replan_steps``, ``--openpi.tier`` (entrypoints/openpi/).
        policies: a YAML/JSON file naming several policies served from the one device, in
            place of ``--policy.path`` (serving/policies_file.py); robots name theirs at
            registration (``--policy_name``). ``--policy.device``, ``--policy.cpu_threads`` and
            any ``--policy.<field>`` apply to every policy; openpi clients are served by the first.
    """

    policy: PolicyOptions = field(default_factory=PolicyOptions)
    policies: str | None = None
    engine: EngineOptions = field(default_factory=EngineOptions)
    rtc: RTCOptions = field(default_factory=RTCOptions)
    scheduler: SchedulerConfig = field(default_factory=LookaheadConfig)
    max_batch_size: int = 3
    host: str = "127.0.0.1"
    port: int = 8080
    latency_profile: str | None = None
    latency_learning: bool | None = None
    profile_reps: int = 5
    max_robots: int = 64
    max_message_mb: float = DEFAULT_MAX_MESSAGE_BYTES / (1 << 20)
    status_interval_s: float = 1.0
    log_level: str = "info"
    log_format: str = "text"
    batch_log: str | None = None
    metrics_port: int | None = None
    tls_cert: str | None = None
    tls_key: str | None = None
    auth_token_file: str | None = None
    operator_token_file: str | None = None
    max_obs_rate_hz: float = 200.0
    fleet: FleetOptions = field(default_factory=lambda: FleetOptions())
    openpi: OpenpiOptions = field(default_factory=OpenpiOptions)

    def validate(self) -> None:
        if self.max_batch_size < 1:
            raise ConfigError("max_batch_size", f"must be >= 1, got {self.max_batch_size}")
        if self.policies and self.policy.path:
            raise ConfigError("policies", "give --policies=FILE or --policy.path, not both")
        if self.policies and self.latency_profile:
            raise ConfigError("latency_profile", "with --policies every policy is profiled at start-up; drop --latency_profile")
        if not 0 <= self.port <= 65535:
            raise ConfigError("port", f"must be in 0..65535, got {self.port}")
        if self.max_robots < 1:
            raise ConfigError("max_robots", f"must be >= 1, got {self.max_robots}")
        if not self.max_message_mb > 0:
            raise ConfigError("max_message_mb", f"must be > 0, got {self.max_message_mb}")
        if self.profile_reps < 1:
            raise ConfigError("profile_reps", f"must be >= 1, got {self.profile_reps}")
        if self.log_level.upper() not in ("DEBUG", "INFO", "WARNING", "ERROR"):
            raise ConfigError("log_level", f"must be debug, info, warning or error, got {self.log_level!r}")
        if self.log_format not in ("text", "json"):
            raise ConfigError("log_format", f"must be text or json, got {self.log_format!r}")
        if self.metrics_port is not None and not 0 <= self.metrics_port <= 65535:
            raise ConfigError("metrics_port", f"must be in 0..65535, got {self.metrics_port}")
        if self.max_obs_rate_hz < 0:
            raise ConfigError("max_obs_rate_hz", f"must be >= 0, got {self.max_obs_rate_hz}")
        self.engine.validate()
        self.rtc.validate()
        self.openpi.validate()


ConfigT = TypeVar("ConfigT", bound=ServerConfig)


def parse_server_args(config_class: type[ConfigT], argv: list[str] | None, prog: str) -> ConfigT:
    """Parse a server's options (``lerobot-armory-server``, ``lerobot-armory-cluster``).

    ``--policy.<field>=value`` for any field of the policy's own config (``--policy.dtype=bfloat16``)
    is kept aside and passed to LeRobot's config parser when the policy loads.
    """
    own = {f.name for f in dataclasses.fields(PolicyOptions)}
    args, overrides = split_passthrough(argv, "policy", own)
    cfg = parse_or_exit(config_class, args, prog)
    cfg.policy.overrides = [*cfg.policy.overrides, *overrides]
    return cfg
