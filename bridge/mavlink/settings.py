"""What the MAVLink output takes from the configuration: :class:`MavlinkSettings`."""

from __future__ import annotations

from dataclasses import dataclass

from bridge.config import Config
from bridge.mavlink import telemetry as T  # noqa: N812 - short
from bridge.mavlink.dialect import mavlink as M  # noqa: N812 - the generated module, short
from bridge.mavlink.paramproto import FLAVOURS, Flavour

MAV_COMP_ID_IMU = int(M.MAV_COMP_ID_IMU)
DEFAULT_QUEUE_PACKETS = 128


@dataclass(frozen=True, slots=True)
class MavlinkSettings:
    """Everything the output takes from the configuration (``[mavlink]``).

    ``component_id`` None means "by role": 1 standalone, 200 (MAV_COMP_ID_IMU)
    companion. ``autopilot`` is the standalone HEARTBEAT's flavour, which also
    decides how a standalone bridge's parameters are encoded
    (:mod:`bridge.mavlink.paramproto`); a companion's always travel as REAL32.
    """

    endpoints: tuple[str, ...] = ("udpout:127.0.0.1:14550",)
    system_id: int = 1
    component_id: int | None = None
    role: T.Role = "standalone"
    autopilot: Flavour = "generic"
    signing_key: bytes | None = None
    queue_packets: int = DEFAULT_QUEUE_PACKETS

    def __post_init__(self) -> None:
        if self.role not in T.ROLES:
            raise ValueError(f"role must be one of {T.ROLES}, got {self.role!r}")
        if self.autopilot not in FLAVOURS:
            raise ValueError(f"autopilot must be one of {FLAVOURS}, got {self.autopilot!r}")
        if not 1 <= self.system_id <= 255:
            raise ValueError(f"system_id must be 1..255, got {self.system_id}")
        if self.component_id is not None and not 1 <= self.component_id <= 255:
            raise ValueError(f"component_id must be 1..255, got {self.component_id}")

    @property
    def effective_component_id(self) -> int:
        """Our component id."""
        if self.component_id is not None:
            return self.component_id
        return MAV_COMP_ID_IMU if self.role == "companion" else 1

    @classmethod
    def from_config(cls, cfg: Config) -> MavlinkSettings:
        """From a loaded configuration."""
        m = cfg.mavlink
        role: T.Role = "companion" if m.role == "companion" else "standalone"
        # Component 1 is the autopilot's in companion role: 1 there means "the role's default".
        comp: int | None = m.component_id
        if role == "companion" and comp == 1:
            comp = None
        return cls(
            endpoints=tuple(m.endpoints),
            system_id=m.system_id,
            component_id=comp,
            role=role,
            autopilot=m.autopilot,  # type: ignore[arg-type]  # validated by config
            signing_key=m.signing_key,
        )
