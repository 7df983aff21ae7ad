"""One registration path for every entrypoint: credential → admission → the request's own problems →
the operator's grant → the fleet.

gRPC (``Register``) and openpi (a websocket's first request) each translate their wire into a
:class:`Registration` and a :class:`FleetError` back into their own refusal; what is checked, in
which order, and what a refusal says is decided here once. The order matters to an attacker:
admission (a per-host and per-credential rate) is counted before any other work, and no grant is
made for a request that has a problem.
"""

from __future__ import annotations

from dataclasses import dataclass

from lerobot_armory.feature_spec import FeatureSpec
from lerobot_armory.robot_spec import RobotSpec
from lerobot_armory.serving.admission import AdmissionLimiter
from lerobot_armory.serving.fleet import Fleet, FleetError
from lerobot_armory.serving.grant_rules import GrantRequest, GrantRules
from lerobot_armory.serving.messages import Grant
from lerobot_armory.serving.security import AuthTokens, Credential
from lerobot_armory.serving.session import RobotSession


@dataclass(frozen=True)
class Registration:
    """A robot's registration, as any entrypoint received it.

    Attributes:
        asked: the fps, horizons, weight and tier it requests (the grant rules decide).
        chunk_size: the chunk size of the policy it registers for.
        features: the features its observations carry.
        task: its task text.
        policy: the served policy's name (None: the default one).
        problems: what the entrypoint already found wrong with the request (refused, no grant).
        check_horizon: refuse a horizon shorter than a batch of one (openpi's clients cannot ask
            for one: their horizon is the server's ``--openpi.replan_steps``).
    """

    asked: GrantRequest
    chunk_size: int
    features: dict[str, FeatureSpec]
    task: str = ""
    policy: str | None = None
    problems: tuple[str, ...] = ()
    check_horizon: bool = True


class Registrar:
    """Admits robots into ``fleet`` (see the module docstring)."""

    def __init__(self, fleet: Fleet, rules: GrantRules, admission: AdmissionLimiter, auth: AuthTokens | None = None) -> None:
        self.fleet = fleet
        self.rules = rules
        self.admission = admission
        self.auth = auth

    def authenticate(self, robot_id: str, token: str, what: str = "auth token for this robot id") -> Credential | None:
        """The credential ``token`` proves for ``robot_id`` (None without ``--auth_token_file``);
        FleetError UNAUTHENTICATED when it proves none. ``what`` names the token as the robot's
        wire calls it."""
        if self.auth is None:
            return None
        credential = self.auth.identify(robot_id, token)
        if credential is None:
            raise FleetError("UNAUTHENTICATED", f"missing or wrong {what}")
        return credential

    def admit(self, host: str, credential: Credential | None) -> None:
        """Count a registration from ``host`` against its rates; FleetError RESOURCE_EXHAUSTED when
        over them. Checked first, before the request is looked at."""
        refused = self.admission.check(host, credential.digest if credential else None)
        if refused is not None:
            raise FleetError("RESOURCE_EXHAUSTED", refused)

    def register(self, registration: Registration, credential: Credential | None, recv: float) -> tuple[RobotSession, Grant]:
        """Grant and register an admitted robot (:meth:`admit` first); FleetError INVALID_ARGUMENT
        with every problem of the request, or the fleet's own refusal (a robot id already
        streaming, a full fleet)."""
        r = registration
        problems = list(r.problems)
        grant = None
        if not problems:
            grant, problems = self.rules.grant(r.asked, credential.group if credential else None, check_horizon=r.check_horizon)
        if problems or grant is None:
            raise FleetError("INVALID_ARGUMENT", "registration refused: " + "; ".join(problems))
        spec = RobotSpec(r.asked.robot_id, grant.fps, r.chunk_size, grant.h_min, grant.h_max, grant.weight, grant.tier)
        session = self.fleet.register(
            spec, r.task, r.features, credential.digest if credential else None, grant, register_recv=recv, policy=r.policy
        )
        return session, grant
