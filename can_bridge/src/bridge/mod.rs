//! The running bridge, by concept: its configuration (here), the state the
//! threads and the caller share (`shared`), the transmit loop (`tx`), the
//! receive loop and the received state (`rx`), the counters (`stats`) and
//! the start/stop life cycle (`lifecycle`). No thread ever needs the GIL;
//! the Python thread touches the shared state only through short critical
//! sections.

mod lifecycle;
mod rx;
mod shared;
mod stats;
mod tx;

pub use lifecycle::{set_realtime, Bridge};
pub use rx::{run_rx, RxConfig, RxStore, VehicleState, RX_NAMES};
pub use shared::{Shared, SEQ_LIMIT, SEQ_MAX_STEP};
pub use stats::Stats;
pub use tx::{run_tx, TransportState, TxCounters, TxParams};

use crate::channel::ChannelSpec;
use crate::e2e::{self, SmConfig};
use crate::error::{clip, Error, Result};
use crate::plausibility::Plausibility;
use crate::safety::SafetyConfig;
use crate::sync::lock;
use std::path::PathBuf;

/// What the bridge does when its transport is lost.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum OnTransportLoss {
    /// Report it in `stats()` (`transport_state`, `safety_state` "lost").
    Report,
    /// Also raise `TransportError` from `set_command` while it lasts.
    Raise,
}

/// Everything a bridge is configured with.
#[derive(Clone, Debug, PartialEq)]
pub struct BridgeConfig {
    /// Channel string (see [`ChannelSpec`]).
    pub channel: String,
    /// Tick period, ns.
    pub period_ns: u64,
    /// Limits and watchdog.
    pub safety: SafetyConfig,
    /// A message is invalid without a usable frame for this long, ns.
    pub state_timeout_ns: u64,
    /// The transport is reported lost when no frame has reached it (written
    /// and taken by the peer) for this long, ns.
    pub transport_timeout_ns: u64,
    /// The actuator applies 0 Nm after this long without a frame (the
    /// actuator contract): a gap in what the peer took that may reach it
    /// restarts the ramp from zero, ns.
    pub actuator_timeout_ns: u64,
    /// Report or raise on a lost transport.
    pub on_transport_loss: OnTransportLoss,
    /// Allow active frames over socketcand, accepting its residual (a
    /// server that stops reading right after answering its probe reads that
    /// frame when it resumes); otherwise only safe frames go out on it.
    pub socketcand_active: bool,
    /// candump log of every frame sent and received.
    pub log_path: Option<PathBuf>,
    /// Replace an existing `log_path` (never through a symbolic link).
    pub log_overwrite: bool,
    /// Most received frames logged per second (a token bucket with a
    /// second's burst); the rest are counted in `log_suppressed`.
    pub log_rx_per_s: u32,
    /// Largest log file, bytes: later lines are counted, not written.
    pub log_max_bytes: u64,
    /// CAN bit rate requested from SLCAN adapters.
    pub bitrate: u32,
    /// Zero-torque frames sent on stop once the output is released (>= 1).
    pub stop_safe_frames: u32,
    /// Largest alive-counter step still in sequence (AUTOSAR MaxDeltaCounter).
    pub rx_max_counter_delta: u8,
    /// In-sequence frames that confirm a (re)anchored counter (SyncCounter).
    pub rx_sync_frames: u8,
    /// The receiver's E2E state machine: window and thresholds.
    pub rx_sm: SmConfig,
    /// A usable received frame is believed once it has stood this long with
    /// no sign of a second sender, ns.
    pub rx_confirm_ns: u64,
    /// Rates of change and the wheel/vehicle speed check.
    pub plausibility: Plausibility,
    /// Tick records kept for `tick_trace` (allocated at start).
    pub trace_capacity: usize,
    /// Run the transmit thread under `SCHED_FIFO` at this priority (1..=99);
    /// needs CAP_SYS_NICE or root. `None`: the default scheduler.
    pub rt_priority: Option<i32>,
}

impl BridgeConfig {
    /// The defaults of the shipped `vehicle.toml` for `channel`.
    pub fn new(channel: &str) -> Self {
        BridgeConfig {
            channel: channel.to_string(),
            period_ns: 50_000_000,
            safety: SafetyConfig::default(),
            state_timeout_ns: 250_000_000,
            transport_timeout_ns: 250_000_000,
            actuator_timeout_ns: 200_000_000,
            on_transport_loss: OnTransportLoss::Report,
            socketcand_active: false,
            log_path: None,
            log_overwrite: false,
            log_rx_per_s: 1000,
            log_max_bytes: 256 << 20,
            bitrate: 500_000,
            stop_safe_frames: 3,
            rx_max_counter_delta: 2,
            rx_sync_frames: 2,
            rx_sm: SmConfig::default(),
            rx_confirm_ns: 25_000_000,
            plausibility: Plausibility::default(),
            trace_capacity: 0,
            rt_priority: None,
        }
    }

    /// The receive side's settings; the brake-only wheels are those whose
    /// actuator cannot drive (`max_nm` 0).
    pub fn rx_config(&self) -> RxConfig {
        RxConfig {
            max_delta: self.rx_max_counter_delta,
            sync_frames: self.rx_sync_frames,
            sm: self.rx_sm,
            confirm_ns: self.rx_confirm_ns,
            state_timeout_ns: self.state_timeout_ns,
            plausibility: self.plausibility,
            undriven: self.safety.wheels.map(|w| w.max_nm <= 0.0),
        }
    }

    /// Check every setting against its bounds; returns the parsed channel.
    pub fn validate(&self) -> Result<ChannelSpec> {
        let spec = ChannelSpec::parse(&self.channel)?;
        let ms = |ns: u64| ns as f64 / 1e6;
        if !(1_000_000..=1_000_000_000).contains(&self.period_ns) {
            return Err(Error::Config(format!(
                "period_ms = {} must be between 1 and 1000",
                ms(self.period_ns)
            )));
        }
        self.safety.validate(self.period_ns)?;
        if !(1_000_000..=5_000_000_000).contains(&self.state_timeout_ns) {
            return Err(Error::Config(format!(
                "state_timeout_ms = {} must be between 1 and 5000",
                ms(self.state_timeout_ns)
            )));
        }
        if !(self.period_ns..=10_000_000_000).contains(&self.transport_timeout_ns) {
            return Err(Error::Config(format!(
                "transport_timeout_ms = {} must be between period_ms ({}) and 10000",
                ms(self.transport_timeout_ns),
                ms(self.period_ns)
            )));
        }
        if !(2 * self.period_ns..=10_000_000_000).contains(&self.actuator_timeout_ns) {
            return Err(Error::Config(format!(
                "actuator_timeout_ms = {} must be between two periods ({}) and 10000: a reader that takes frames late in their period sees gaps of two periods",
                ms(self.actuator_timeout_ns),
                ms(2 * self.period_ns)
            )));
        }
        if !(1..=1_000_000).contains(&self.log_rx_per_s) {
            return Err(Error::Config(format!(
                "log_rx_per_s = {} must be in 1..=1000000",
                self.log_rx_per_s
            )));
        }
        if !(4096..=(1u64 << 50)).contains(&self.log_max_bytes) {
            return Err(Error::Config(format!(
                "log_max_bytes = {} must be in 4096..=2**50",
                self.log_max_bytes
            )));
        }
        if !(1..=100).contains(&self.stop_safe_frames) {
            return Err(Error::Config(format!(
                "stop_safe_frames = {} must be in 1..=100",
                self.stop_safe_frames
            )));
        }
        if !(1..=e2e::MAX_COUNTER).contains(&self.rx_max_counter_delta) {
            return Err(Error::Config(
                "rx_max_counter_delta must be in 1..=14".into(),
            ));
        }
        if !(1..=e2e::MAX_COUNTER).contains(&self.rx_sync_frames) {
            return Err(Error::Config("rx_sync_frames must be in 1..=14".into()));
        }
        self.rx_sm.validate().map_err(Error::Config)?;
        if !(1_000_000..=1_000_000_000).contains(&self.rx_confirm_ns) {
            return Err(Error::Config(format!(
                "rx_confirm_ms = {} must be between 1 and 1000",
                ms(self.rx_confirm_ns)
            )));
        }
        if self.rx_confirm_ns >= self.state_timeout_ns {
            return Err(Error::Config(format!(
                "rx_confirm_ms = {} must be below state_timeout_ms ({}): a frame must be believed before it times out",
                ms(self.rx_confirm_ns),
                ms(self.state_timeout_ns)
            )));
        }
        self.plausibility.validate().map_err(Error::Config)?;
        if self.trace_capacity > 10_000_000 {
            return Err(Error::Config(
                "trace_capacity must be at most 10,000,000".into(),
            ));
        }
        if let Some(p) = self.rt_priority {
            if !(1..=99).contains(&p) {
                return Err(Error::Config(format!(
                    "rt_priority = {p} must be in 1..=99"
                )));
            }
        }
        Ok(spec)
    }
}

/// `clip` re-exported for the pyo3 layer's messages.
pub fn clip_input(s: &str) -> String {
    clip(s)
}

/// Settings the tests of every part of the bridge share.
#[cfg(test)]
mod testutil {
    use super::BridgeConfig;
    use crate::safety::{LimitRule, SafetyConfig, WheelLimits};

    pub const MS: u64 = 1_000_000;

    fn wheel(lim: f64) -> WheelLimits {
        WheelLimits {
            min_nm: -lim,
            max_nm: lim,
            rise_nm_per_s: 200.0,
            release_nm_per_s: 200.0,
        }
    }

    /// +-100 Nm on every wheel at 200 Nm/s (10 Nm per 50 ms tick), watchdog
    /// 120 / 300 / 1000 ms.
    pub fn config() -> BridgeConfig {
        let mut c = BridgeConfig::new("slcan-pty:");
        c.safety = SafetyConfig {
            wheels: [wheel(100.0); 4],
            safe_release_nm_per_s: 400.0,
            limit_rule: LimitRule::Clamp,
            hold_after_ns: 120 * MS,
            safe_after_ns: 300 * MS,
            fault_after_ns: 1000 * MS,
        };
        c
    }
}

#[cfg(test)]
mod tests {
    use super::testutil::{config, MS};
    use super::*;

    #[test]
    fn config_validation_names_the_setting() {
        let c = config();
        assert!(c.validate().is_ok());
        for (f, want) in [
            (
                Box::new(|c: &mut BridgeConfig| c.period_ns = 0) as Box<dyn Fn(&mut BridgeConfig)>,
                "period_ms",
            ),
            (
                Box::new(|c: &mut BridgeConfig| c.period_ns = 5_000 * MS),
                "period_ms",
            ),
            (
                Box::new(|c: &mut BridgeConfig| c.stop_safe_frames = 0),
                "stop_safe_frames",
            ),
            (
                Box::new(|c: &mut BridgeConfig| c.state_timeout_ns = 3_600_000 * MS),
                "state_timeout_ms",
            ),
            (
                Box::new(|c: &mut BridgeConfig| c.transport_timeout_ns = MS),
                "transport_timeout_ms",
            ),
            (
                Box::new(|c: &mut BridgeConfig| c.actuator_timeout_ns = 99 * MS),
                "actuator_timeout_ms = 99 must be between two periods (100)",
            ),
            (
                Box::new(|c: &mut BridgeConfig| c.log_rx_per_s = 0),
                "log_rx_per_s",
            ),
            (
                Box::new(|c: &mut BridgeConfig| c.log_max_bytes = 10),
                "log_max_bytes",
            ),
        ] {
            let mut c = config();
            f(&mut c);
            let e = c.validate().unwrap_err().to_string();
            assert!(e.contains(want), "{e}");
        }
        assert!(matches!(
            Bridge::new(BridgeConfig::new("nope:")),
            Err(Error::Config(_))
        ));
    }
}
