from collections.abc import Sequence
from os import PathLike
from typing import Literal, TypedDict, final

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

SafetyState = Literal["active", "hold", "safe", "fault"]

class VehicleState(TypedDict):
    valid: bool
    long_speed_mps: float | None
    lat_speed_mps: float | None
    yaw_rate_radps: float | None
    steering_angle_rad: float | None
    wheel_speeds_radps: tuple[float, float, float, float] | None
    age_ms: float | None

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
    rx_frames: int
    rx_crc_errors: int
    rx_counter_errors: int
    rx_length_errors: int
    rx_malformed: int
    rx_unknown_id: int
    rx_transport_errors: int
    bus_errors: int
    log_dropped: int
    log_errors: int
    safety_state: SafetyState
    state_valid: bool
    last_tx_error: str | None
    last_rx_error: str | None

@final
class Bridge:
    def __init__(
        self,
        channel: str,
        period_ms: float = 50.0,
        *,
        max_torque_nm: float | Sequence[float] | None = None,
        max_rate_nm_per_tick: float = 25.0,
        hold_after_ms: float = 150.0,
        safe_after_ms: float = 500.0,
        fault_after_ms: float = 2000.0,
        state_timeout_ms: float = 250.0,
        log_path: str | PathLike[str] | None = None,
        bitrate: int = 500000,
        stop_safe_frames: int = 3,
        rx_max_counter_delta: int = 2,
        trace_capacity: int = 0,
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
def encode_message(name: str, values: dict[str, float | str], counter: int) -> bytes: ...
def e2e_p01_crc(data_id: int, data: bytes) -> int: ...
