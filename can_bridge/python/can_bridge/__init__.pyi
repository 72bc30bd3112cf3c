from collections.abc import Sequence
from os import PathLike
from typing import Any, Literal, TypedDict, final

from ._errors import (
    CanBridgeError as CanBridgeError,
)
from ._errors import (
    CommandError as CommandError,
)
from ._errors import (
    ConfigError as ConfigError,
)
from ._errors import (
    StateError as StateError,
)
from ._errors import (
    TransportError as TransportError,
)

__version__: str
DEFAULT_CONFIG_TOML: str

Mode = Literal["active", "hold", "safe", "fault"]
SafetyState = Literal["active", "hold", "safe", "fault", "lost", "not_open", "safe_only"]
TransportState = Literal["up", "not_open", "lost", "unverified"]
PerWheel = float | Sequence[float]

class RxStatus(TypedDict):
    VehicleMotion: str
    WheelSpeeds: str
    SteeringState: str
    VehicleAccel: str
    DriverDemand: str

class VehicleState(TypedDict):
    valid: bool
    long_speed_mps: float | None
    lat_speed_mps: float | None
    yaw_rate_radps: float | None
    steering_angle_rad: float | None
    wheel_speeds_radps: tuple[float, float, float, float] | None
    long_accel_mps2: float | None
    lat_accel_mps2: float | None
    driver_torque_nm: float | None
    set_speed_mps: float | None
    road_friction: float | None
    age_ms: float | None
    status: RxStatus
    reason: str | None

class Stats(TypedDict):
    running: bool
    ticks: int
    overruns: int
    skipped_ticks: int
    lateness_mean_ms: float
    lateness_p50_ms: float
    lateness_p99_ms: float
    lateness_max_ms: float
    mean_period_ms: float | None
    drift_ms: float | None
    tx_frames: int
    tx_errors: int
    tx_not_open: int
    tx_stale_dropped: int
    send_max_ms: float
    applied_torques_nm: tuple[float, float, float, float]
    limit_events: int
    last_limit_event: str | None
    rate_limited_ticks: int
    ramp_restarts: int
    tx_safe_only: int
    transport_state: TransportState
    transport_losses: int
    reconnects: int
    replies_dropped: int
    rx_frames: int
    rx_crc_errors: int
    rx_counter_errors: int
    rx_repeated: int
    rx_two_sources: int
    rx_wrong_sequence: int
    rx_lost_frames: int
    rx_sync: int
    rx_implausible: int
    rx_implausible_rate: int
    rx_inconsistent: int
    rx_faster_than_cycle: int
    rx_discarded: int
    rx_length_errors: int
    rx_malformed: int
    rx_unknown_id: int
    rx_transport_errors: int
    bus_errors: int
    log_dropped: int
    log_errors: int
    log_suppressed: int
    last_log_error: str | None
    safety_state: SafetyState
    tx_mode: Mode
    state_valid: bool
    state_reason: str | None
    last_tx_error: str | None
    last_rx_error: str | None

@final
class Bridge:
    def __init__(
        self,
        channel: str,
        period_ms: float | None = None,
        *,
        config: str | PathLike[str] | None = None,
        torque_min_nm: PerWheel | None = None,
        torque_max_nm: PerWheel | None = None,
        rise_nm_per_s: PerWheel | None = None,
        release_nm_per_s: PerWheel | None = None,
        safe_release_nm_per_s: float | None = None,
        limit_rule: Literal["clamp", "refuse"] | None = None,
        hold_after_ms: float | None = None,
        safe_after_ms: float | None = None,
        fault_after_ms: float | None = None,
        state_timeout_ms: float | None = None,
        transport_timeout_ms: float | None = None,
        actuator_timeout_ms: float | None = None,
        socketcand_active: bool | None = None,
        on_transport_loss: Literal["report", "raise"] | None = None,
        log_path: str | PathLike[str] | None = None,
        log_overwrite: bool | None = None,
        log_rx_per_s: int | None = None,
        log_max_bytes: int | None = None,
        bitrate: int | None = None,
        stop_safe_frames: int | None = None,
        rx_max_counter_delta: int | None = None,
        rx_sync_frames: int | None = None,
        rx_max_strikes: int | None = None,
        rx_window: int | None = None,
        rx_min_ok_init: int | None = None,
        rx_max_error_init: int | None = None,
        rx_min_ok_valid: int | None = None,
        rx_max_error_valid: int | None = None,
        rx_min_ok_invalid: int | None = None,
        rx_max_error_invalid: int | None = None,
        rx_confirm_ms: float | None = None,
        rx_max_rate: dict[str, float] | None = None,
        rx_wheels: dict[str, float] | None = None,
        trace_capacity: int | None = None,
        rt_priority: int | None = None,
    ) -> None: ...
    def start(self) -> None: ...
    def stop(self) -> None: ...
    def __enter__(self) -> Bridge: ...
    def __exit__(self, *args: object) -> bool: ...
    def set_command(self, torques: Sequence[float], seq: int) -> None: ...
    def reset_fault(self) -> None: ...
    def latest_state(self) -> VehicleState: ...
    def stats(self) -> Stats: ...
    def tick_trace(self) -> list[tuple[int, int, int]]: ...
    @property
    def pty_path(self) -> str | None: ...
    @property
    def running(self) -> bool: ...
    @property
    def channel(self) -> str: ...
    @property
    def period_ms(self) -> float: ...

def dbc_path() -> str: ...
def default_config_path() -> str: ...
def load_config(path: str | PathLike[str] | None = None) -> dict[str, Any]: ...
def encode_message(name: str, values: dict[str, float | str], counter: int) -> bytes: ...
def e2e_p01_crc(data_id: int, data: bytes) -> int: ...
