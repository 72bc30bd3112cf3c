//! The running bridge: a transmit thread on absolute deadlines, a receive
//! thread, and the shared state the Python thread touches only through short
//! critical sections (no thread ever needs the GIL).

use crate::candump::{self, Dir, LogSender, LogWriter};
use crate::channel::ChannelSpec;
use crate::codec::{encode_torque_cmd, Mode, N_RX, RX_MESSAGES};
use crate::e2e::{self, Check, Judge, Receiver};
use crate::error::{clip, Error, Result};
use crate::frame::CanFrame;
use crate::safety::{Command, LimitRule, Safety, SafetyConfig, WHEELS};
use crate::scheduler::{
    monotonic_ns, realtime_ns, Clock, MonotonicClock, Schedule, TickRecord, TickStats, TickSummary,
};
use crate::transport::{self, Health, RxItem, Sink, Source, Written};
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::thread::JoinHandle;

/// Receive thread poll timeout, ms (bounds stop latency).
const RX_POLL_MS: i32 = 20;

/// Largest accepted `seq` (exclusive) and the largest step between two
/// accepted ones: a caller cannot lock itself out by one huge value
/// (`test_f8_seq_cannot_lock_out_commands_and_restarts_with_the_run`).
pub const SEQ_LIMIT: u64 = 1 << 63;
/// See [`SEQ_LIMIT`].
pub const SEQ_MAX_STEP: u64 = 1 << 48;

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
    /// Report or raise on a lost transport.
    pub on_transport_loss: OnTransportLoss,
    /// candump log of every frame sent and received.
    pub log_path: Option<PathBuf>,
    /// Replace an existing `log_path` (never through a symbolic link).
    pub log_overwrite: bool,
    /// CAN bit rate requested from SLCAN adapters.
    pub bitrate: u32,
    /// Zero-torque frames sent on stop once the output is released (>= 1).
    pub stop_safe_frames: u32,
    /// Largest alive-counter step still in sequence (AUTOSAR MaxDeltaCounter).
    pub rx_max_counter_delta: u8,
    /// In-sequence frames that confirm a (re)anchored counter (SyncCounter).
    pub rx_sync_frames: u8,
    /// Strikes allowed among a message's last 16 frames.
    pub rx_max_strikes: u32,
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
            on_transport_loss: OnTransportLoss::Report,
            log_path: None,
            log_overwrite: false,
            bitrate: 500_000,
            stop_safe_frames: 3,
            rx_max_counter_delta: 2,
            rx_sync_frames: 2,
            rx_max_strikes: 2,
            trace_capacity: 0,
            rt_priority: None,
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
        if self.rx_max_strikes > e2e::WINDOW {
            return Err(Error::Config("rx_max_strikes must be in 0..=16".into()));
        }
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

/// Put the calling thread under `SCHED_FIFO` at `priority`.
pub fn set_realtime(priority: i32) -> Result<()> {
    let param = libc::sched_param {
        sched_priority: priority,
    };
    // SAFETY: pthread_self is always valid; param is a valid sched_param.
    let rc = unsafe { libc::pthread_setschedparam(libc::pthread_self(), libc::SCHED_FIFO, &param) };
    if rc != 0 {
        return Err(Error::Config(format!(
            "rt_priority = {priority}: SCHED_FIFO refused: {} (needs root or CAP_SYS_NICE)",
            std::io::Error::from_raw_os_error(rc)
        )));
    }
    Ok(())
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

#[derive(Debug, Default)]
struct CmdSlot {
    cmd: Option<Command>,
    last_seq: Option<u64>,
    limit_events: u64,
    last_limit_event: Option<String>,
}

/// State of the transport as the transmit thread sees it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TransportState {
    /// Frames reach the peer.
    Up,
    /// An SLCAN pty peer has not opened the channel (nothing to lose yet).
    NotOpen,
    /// Nothing has reached the peer for `transport_timeout`, or the link broke.
    Lost,
}

impl TransportState {
    /// Name in `stats()`.
    pub fn name(self) -> &'static str {
        match self {
            TransportState::Up => "up",
            TransportState::NotOpen => "not_open",
            TransportState::Lost => "lost",
        }
    }
}

/// Transmit-side counters.
#[derive(Debug)]
pub struct TxCounters {
    tick: TickStats,
    tx_frames: u64,
    tx_errors: u64,
    tx_not_open: u64,
    tx_stale_dropped: u64,
    send_max_ns: u64,
    mode: Mode,
    applied: [f64; 4],
    rate_limited_ticks: u64,
    transport: TransportState,
    transport_losses: u64,
    last_error: Option<String>,
}

impl TxCounters {
    fn new(period_ns: u64, trace: usize) -> Self {
        TxCounters {
            tick: TickStats::new(period_ns, trace),
            tx_frames: 0,
            tx_errors: 0,
            tx_not_open: 0,
            tx_stale_dropped: 0,
            send_max_ns: 0,
            mode: Mode::Safe,
            applied: [0.0; 4],
            rate_limited_ticks: 0,
            transport: TransportState::NotOpen,
            transport_losses: 0,
            last_error: None,
        }
    }
}

#[derive(Debug, Clone)]
struct RxSlotState {
    receiver: Receiver,
    judge: Judge,
    /// Last frame that passed length and CRC (for the resync after a gap).
    last_seen_ns: Option<u64>,
    /// Last usable frame.
    last_ok_ns: Option<u64>,
    values: [f64; 4],
}

/// Receive-side state and counters.
#[derive(Debug, Clone)]
pub struct RxStore {
    slots: Vec<RxSlotState>,
    rx_frames: u64,
    rx_crc_errors: u64,
    rx_counter_errors: u64,
    rx_repeated: u64,
    rx_two_sources: u64,
    rx_wrong_sequence: u64,
    rx_lost_frames: u64,
    rx_sync: u64,
    rx_implausible: u64,
    rx_length_errors: u64,
    rx_malformed: u64,
    rx_unknown_id: u64,
    rx_transport_errors: u64,
    bus_errors: u64,
    last_error: Option<String>,
}

/// Names of the received messages, in [`RX_MESSAGES`] order.
pub const RX_NAMES: [&str; N_RX] = [
    "VehicleMotion",
    "WheelSpeeds",
    "SteeringState",
    "VehicleAccel",
    "DriverDemand",
];

impl RxStore {
    /// Empty state; see [`BridgeConfig`] for the receiver settings.
    pub fn new(max_delta: u8, sync_frames: u8, max_strikes: u32) -> Self {
        RxStore {
            slots: RX_MESSAGES
                .iter()
                .map(|m| RxSlotState {
                    receiver: Receiver::new(m.data_id, m.len, max_delta, sync_frames),
                    judge: Judge::new(max_strikes),
                    last_seen_ns: None,
                    last_ok_ns: None,
                    values: [0.0; 4],
                })
                .collect(),
            rx_frames: 0,
            rx_crc_errors: 0,
            rx_counter_errors: 0,
            rx_repeated: 0,
            rx_two_sources: 0,
            rx_wrong_sequence: 0,
            rx_lost_frames: 0,
            rx_sync: 0,
            rx_implausible: 0,
            rx_length_errors: 0,
            rx_malformed: 0,
            rx_unknown_id: 0,
            rx_transport_errors: 0,
            bus_errors: 0,
            last_error: None,
        }
    }

    /// Check, judge and (if usable and plausible) store one received frame.
    pub fn on_frame(&mut self, f: &CanFrame, now_ns: u64, state_timeout_ns: u64) -> Check {
        self.rx_frames += 1;
        let idx = RX_MESSAGES
            .iter()
            .position(|m| m.id == f.id() && !f.is_extended() && !f.is_remote());
        let Some((m, slot)) = idx.and_then(|i| Some((RX_MESSAGES.get(i)?, self.slots.get_mut(i)?)))
        else {
            self.rx_unknown_id += 1;
            return Check::BadLength;
        };
        // After a gap the counter is anchored afresh (INITIAL, then SYNC).
        if slot
            .last_seen_ns
            .is_none_or(|t| now_ns.saturating_sub(t) > state_timeout_ns)
        {
            slot.receiver.resync();
            slot.judge.reset();
        }
        let mut verdict = slot.receiver.check(f.data());
        if !matches!(verdict, Check::BadLength | Check::BadCrc) {
            slot.last_seen_ns = Some(now_ns);
        }
        let mut values = [0.0; 4];
        if verdict.usable() {
            m.decode_values(f.data(), &mut values);
            if let Some((name, v)) = m.implausible(&values[..m.signals.len() - 2]) {
                verdict = Check::Implausible;
                self.last_error = Some(format!("{}: {name} = {v} is implausible", m.name));
            }
        }
        slot.judge.record(verdict);
        match verdict {
            Check::Ok | Check::OkSomeLost => {
                slot.values = values;
                slot.last_ok_ns = Some(now_ns);
                if verdict == Check::OkSomeLost {
                    self.rx_lost_frames += 1;
                }
            }
            Check::Initial | Check::Sync => self.rx_sync += 1,
            Check::BadCrc => self.rx_crc_errors += 1,
            Check::BadLength => self.rx_length_errors += 1,
            Check::Implausible => self.rx_implausible += 1,
            Check::Repeated => {
                self.rx_repeated += 1;
                self.rx_counter_errors += 1;
            }
            Check::TwoSources => {
                self.rx_two_sources += 1;
                self.rx_counter_errors += 1;
            }
            Check::WrongSequence => {
                self.rx_wrong_sequence += 1;
                self.rx_counter_errors += 1;
            }
            Check::InvalidCounter => self.rx_counter_errors += 1,
        }
        verdict
    }

    /// The vehicle state as of `now_ns`.
    pub fn state(&self, now_ns: u64, state_timeout_ns: u64) -> VehicleState {
        let mut status = ["no data"; N_RX];
        for (st, slot) in status.iter_mut().zip(&self.slots) {
            // A sender that keeps sending bad frames is reported by what is
            // wrong with them ("repeated", ...), not merely as a timeout.
            let fresh = slot
                .last_seen_ns
                .is_some_and(|t| now_ns.saturating_sub(t) <= state_timeout_ns);
            *st = match (slot.last_ok_ns, slot.judge.verdict()) {
                (_, Err(why)) if fresh || slot.last_ok_ns.is_none() => why,
                (None, _) => "no data",
                (Some(t), _) if now_ns.saturating_sub(t) > state_timeout_ns => "timeout",
                (Some(_), Err(why)) => why,
                (Some(_), Ok(())) => "ok",
            };
        }
        let valid = status.iter().all(|s| *s == "ok");
        let reason = (!valid).then(|| {
            RX_NAMES
                .iter()
                .zip(status)
                .filter(|(_, s)| *s != "ok")
                .map(|(n, s)| format!("{n}: {s}"))
                .collect::<Vec<_>>()
                .join("; ")
        });
        let get = |i: usize| {
            self.slots
                .get(i)
                .and_then(|s| s.last_ok_ns.map(|t| (t, s.values)))
        };
        let (motion, wheels, steer, accel, driver) = (get(0), get(1), get(2), get(3), get(4));
        // The state is as old as its oldest message, and has no age until
        // every message has arrived once.
        let ages: [Option<u64>; N_RX] = [motion, wheels, steer, accel, driver]
            .map(|x| x.map(|(t, _)| now_ns.saturating_sub(t)));
        let age_ms = if ages.iter().all(Option::is_some) {
            ages.iter().flatten().max().map(|a| *a as f64 / 1e6)
        } else {
            None
        };
        VehicleState {
            valid,
            long_speed_mps: motion.map(|(_, v)| v[0]),
            lat_speed_mps: motion.map(|(_, v)| v[1]),
            yaw_rate_radps: motion.map(|(_, v)| v[2]),
            wheel_speeds_radps: wheels.map(|(_, v)| v),
            steering_angle_rad: steer.map(|(_, v)| v[0]),
            long_accel_mps2: accel.map(|(_, v)| v[0]),
            lat_accel_mps2: accel.map(|(_, v)| v[1]),
            driver_torque_nm: driver.map(|(_, v)| v[0]),
            set_speed_mps: driver.map(|(_, v)| v[1]),
            road_friction: driver.map(|(_, v)| v[2]),
            age_ms,
            status,
            reason,
        }
    }
}

/// The received vehicle state, from the five received messages
/// ([`RX_NAMES`]). Values are those of each message's last usable frame
/// (`None` until there is one); `valid` is true only while all five are
/// judged valid (`status`, `reason` say why not).
#[derive(Clone, Debug, PartialEq)]
pub struct VehicleState {
    /// All five messages fresh and judged valid over their windows.
    pub valid: bool,
    /// Longitudinal speed, m/s.
    pub long_speed_mps: Option<f64>,
    /// Lateral speed, m/s.
    pub lat_speed_mps: Option<f64>,
    /// Yaw rate, rad/s.
    pub yaw_rate_radps: Option<f64>,
    /// Wheel speeds FL, FR, RL, RR, rad/s.
    pub wheel_speeds_radps: Option<[f64; 4]>,
    /// Steering angle, rad.
    pub steering_angle_rad: Option<f64>,
    /// Longitudinal acceleration (body frame, centre of gravity), m/s^2.
    pub long_accel_mps2: Option<f64>,
    /// Lateral acceleration (body frame, centre of gravity), m/s^2.
    pub lat_accel_mps2: Option<f64>,
    /// The driver's rear-axle torque request, Nm.
    pub driver_torque_nm: Option<f64>,
    /// Cruise set speed, m/s.
    pub set_speed_mps: Option<f64>,
    /// Road-friction estimate published by the vehicle (dimensionless).
    pub road_friction: Option<f64>,
    /// Age of the oldest of the five messages, ms (`None` until all arrived).
    pub age_ms: Option<f64>,
    /// Per message (`RX_NAMES` order): "ok" or why it is not valid.
    pub status: [&'static str; N_RX],
    /// `None` when valid, else "Message: why; ...".
    pub reason: Option<String>,
}

/// State shared by the threads and the caller, for one run.
#[derive(Debug)]
pub struct Shared {
    cmd: Mutex<CmdSlot>,
    reset_at: Mutex<Option<u64>>,
    /// Commands are accepted only while this is set (start .. stop).
    accepting: AtomicBool,
    stop: AtomicBool,
    lost: AtomicBool,
    safety: SafetyConfig,
    on_loss: OnTransportLoss,
    tx: Mutex<TxCounters>,
    rx: Mutex<RxStore>,
    log_dropped: Arc<AtomicU64>,
    log_errors: Arc<AtomicU64>,
    health: Mutex<Option<Arc<Health>>>,
}

fn fmt_nm(x: f64) -> String {
    format!("{x}")
}

impl Shared {
    /// Fresh shared state.
    pub fn new(cfg: &BridgeConfig) -> Self {
        Shared {
            cmd: Mutex::new(CmdSlot::default()),
            reset_at: Mutex::new(None),
            accepting: AtomicBool::new(false),
            stop: AtomicBool::new(false),
            lost: AtomicBool::new(false),
            safety: cfg.safety,
            on_loss: cfg.on_transport_loss,
            tx: Mutex::new(TxCounters::new(cfg.period_ns, cfg.trace_capacity)),
            rx: Mutex::new(RxStore::new(
                cfg.rx_max_counter_delta,
                cfg.rx_sync_frames,
                cfg.rx_max_strikes,
            )),
            log_dropped: Arc::new(AtomicU64::new(0)),
            log_errors: Arc::new(AtomicU64::new(0)),
            health: Mutex::new(None),
        }
    }

    /// Accept commands from now on (the run has started).
    pub fn open_for_commands(&self) {
        self.accepting.store(true, Ordering::Release);
    }

    /// Validate, limit and store the latest command (arrival time `now_ns`).
    /// Refused: outside a run, while the transport is lost (if asked), NaN
    /// or infinities, a `seq` not in `last+1 ..= last+2**48` (or >= 2**63),
    /// and, under `limit_rule = refuse`, a torque outside its wheel's range.
    pub fn set_command(&self, torques_nm: [f64; 4], seq: u64, now_ns: u64) -> Result<()> {
        if !self.accepting.load(Ordering::Acquire) {
            return Err(Error::State(
                "bridge is not running: start() it first (commands are valid for one run)".into(),
            ));
        }
        if self.on_loss == OnTransportLoss::Raise && self.lost.load(Ordering::Acquire) {
            return Err(Error::Transport(
                "transport lost: no frame has reached the bus for transport_timeout_ms; see stats()"
                    .into(),
            ));
        }
        let cmd = Command::new(torques_nm, seq, now_ns)?;
        if seq >= SEQ_LIMIT {
            return Err(Error::Command(format!(
                "seq = {seq} must be below 2**63; command refused"
            )));
        }
        let mut slot = lock(&self.cmd);
        if let Some(last) = slot.last_seq {
            if seq <= last {
                return Err(Error::Command(format!(
                    "seq {seq} is not newer than the last accepted seq {last}; command refused"
                )));
            }
            if seq - last > SEQ_MAX_STEP {
                return Err(Error::Command(format!(
                    "seq {seq} jumps more than 2**48 past the last accepted seq {last}; command refused"
                )));
            }
        }
        let (target, events) = Safety::limit(&self.safety, cmd.torques_nm);
        if let Some(e) = events.first() {
            let w = &self.safety.wheels[e.wheel];
            let name = WHEELS.get(e.wheel).copied().unwrap_or("?");
            let range = format!("[{}, {}]", fmt_nm(w.min_nm), fmt_nm(w.max_nm));
            slot.limit_events += 1;
            if self.safety.limit_rule == LimitRule::Refuse {
                let msg = format!(
                    "torque {name} = {} Nm is outside its range {range} Nm (limit_rule = refuse); command refused",
                    fmt_nm(e.commanded_nm)
                );
                slot.last_limit_event = Some(format!("{name}: {msg}"));
                return Err(Error::Command(msg));
            }
            let all: Vec<String> = events
                .iter()
                .map(|e| {
                    format!(
                        "{} {} -> {} Nm",
                        WHEELS.get(e.wheel).copied().unwrap_or("?"),
                        fmt_nm(e.commanded_nm),
                        fmt_nm(e.target_nm)
                    )
                })
                .collect();
            slot.last_limit_event = Some(format!("{} (seq {seq}, clamped)", all.join(", ")));
        }
        slot.last_seq = Some(seq);
        slot.cmd = Some(Command {
            torques_nm: target,
            ..cmd
        });
        Ok(())
    }

    /// Ask the transmit thread to clear a latched fault.
    pub fn request_reset(&self, now_ns: u64) {
        *lock(&self.reset_at) = Some(now_ns);
    }

    /// Refuse commands from now on and ask the transmit thread to release
    /// the output, send its zero frames and finish.
    pub fn request_stop(&self) {
        self.accepting.store(false, Ordering::Release);
        self.stop.store(true, Ordering::Release);
    }
}

/// Settings of the transmit loop.
#[derive(Clone, Copy, Debug)]
pub struct TxParams {
    /// Tick period, ns.
    pub period_ns: u64,
    /// Limits and watchdog.
    pub safety: SafetyConfig,
    /// Zero frames sent after the release on stop.
    pub stop_safe_frames: u32,
    /// Loss after this long without a frame reaching the peer, ns.
    pub transport_timeout_ns: u64,
}

/// Largest number of release frames on stop (4096 Nm at one 2 Nm step a
/// tick): a bound, so stop always ends.
const MAX_RELEASE_FRAMES: u32 = 2048;

/// The transmit loop: runs until a stop request, then releases the output to
/// zero at the safe rate, sends `stop_safe_frames` zero frames, and closes
/// the sink.
pub fn run_tx<C: Clock>(
    clock: &C,
    p: TxParams,
    shared: &Shared,
    sink: &mut dyn Sink,
    health: Option<&Health>,
    log: Option<&LogSender>,
) {
    let t0 = clock.now_ns();
    let mut sched = Schedule::new(t0 + p.period_ns, p.period_ns);
    let mut safety = Safety::new(p.safety, p.period_ns, sched.deadline());
    let mut counter: u8 = 0;
    // Zero frames still to send once stopping (None: not stopping).
    let mut stopping: Option<u32> = None;
    let mut release_frames = 0u32;
    // Commands received (real time) before the last reset are stale.
    let mut stale_before = 0u64;
    // Lateness is measured from the first deadline not yet served, so a tick
    // that comes after skipped deadlines reports the whole wait.
    let mut due = sched.deadline();
    let mut last_good = t0;
    let mut state = TransportState::NotOpen;
    loop {
        let deadline = sched.deadline();
        clock.sleep_until_ns(deadline);
        let wake = clock.now_ns();
        if stopping.is_none() && shared.stop.load(Ordering::Acquire) {
            stopping = Some(p.stop_safe_frames);
        }
        if stopping == Some(0) {
            break;
        }
        if let Some(t) = lock(&shared.reset_at).take() {
            if safety.reset(deadline) {
                stale_before = t;
            }
        }
        // While the transport is lost the output restarts from 0 Nm: the
        // first frame that gets through ramps up at the rise rate.
        if state == TransportState::Lost {
            safety.restart_output();
        }
        let latest = lock(&shared.cmd).cmd;
        let cmd = latest.filter(|c| c.received_ns >= stale_before);
        let (mode, torques) = if stopping.is_some() {
            safety.stopping()
        } else {
            safety.step(deadline, cmd.as_ref())
        };
        let frame = encode_torque_cmd(&torques, mode, counter);
        let before = clock.now_ns();
        let outcome = match &frame {
            Ok(f) => sink.send(f),
            Err(e) => Err(e.clone()),
        };
        let done = clock.now_ns();
        if let Some(n) = stopping.as_mut() {
            if torques == [0.0; 4] || release_frames >= MAX_RELEASE_FRAMES {
                *n = n.saturating_sub(1);
            } else {
                release_frames += 1;
            }
        }
        let link_up = health.is_none_or(|h| h.link_up.load(Ordering::Acquire));
        let good = matches!(&outcome, Ok(o) if o.written == Written::Yes && o.flushed == 0);
        let not_open = matches!(&outcome, Ok(o) if o.written == Written::NotOpen);
        if good && link_up {
            last_good = done;
        }
        let new_state = if !link_up
            || (!good && !not_open && done.saturating_sub(last_good) >= p.transport_timeout_ns)
        {
            TransportState::Lost
        } else if good {
            TransportState::Up
        } else if not_open && state != TransportState::Lost {
            last_good = done;
            TransportState::NotOpen
        } else {
            state
        };
        let skipped = sched.advance(done);
        let mut tx = lock(&shared.tx);
        tx.tick.record_wake(
            TickRecord {
                index: sched.index().saturating_sub(1 + skipped),
                deadline_ns: deadline,
                wake_ns: wake,
            },
            due,
        );
        due = deadline + p.period_ns;
        tx.tick.record_skip(skipped);
        tx.send_max_ns = tx.send_max_ns.max(done.saturating_sub(before));
        tx.mode = mode;
        tx.rate_limited_ticks = safety.rate_limited_ticks();
        if new_state == TransportState::Lost && state != TransportState::Lost {
            tx.transport_losses += 1;
        }
        state = new_state;
        tx.transport = state;
        shared
            .lost
            .store(state == TransportState::Lost, Ordering::Release);
        match outcome {
            Ok(o) => {
                tx.tx_stale_dropped += u64::from(o.flushed);
                match o.written {
                    Written::Yes => {
                        tx.tx_frames += 1;
                        tx.applied = torques;
                        counter = e2e::next_counter(counter);
                        if let (Some(l), Ok(f)) = (log, &frame) {
                            l.log(realtime_ns(), f, Dir::Tx);
                        }
                    }
                    Written::Dropped => {
                        tx.tx_stale_dropped += 1;
                        counter = e2e::next_counter(counter);
                    }
                    Written::NotOpen => tx.tx_not_open += 1,
                }
            }
            Err(e) => {
                tx.tx_errors += 1;
                counter = e2e::next_counter(counter);
                tx.last_error = Some(e.to_string());
            }
        }
    }
    sink.close();
}

/// The receive loop: runs until `stop` is set.
pub fn run_rx(
    shared: &Shared,
    source: &mut dyn Source,
    state_timeout_ns: u64,
    stop: &AtomicBool,
    log: Option<&LogSender>,
) {
    while !stop.load(Ordering::Acquire) {
        match source.recv(RX_POLL_MS) {
            Ok(None) => {}
            Ok(Some(RxItem::Frame(f))) => {
                if let Some(l) = log {
                    l.log(realtime_ns(), &f, Dir::Rx);
                }
                lock(&shared.rx).on_frame(&f, monotonic_ns(), state_timeout_ns);
            }
            Ok(Some(RxItem::Malformed)) => lock(&shared.rx).rx_malformed += 1,
            Ok(Some(RxItem::BusError)) => lock(&shared.rx).bus_errors += 1,
            Err(e) => {
                {
                    let mut rx = lock(&shared.rx);
                    rx.rx_transport_errors += 1;
                    rx.last_error = Some(e.to_string());
                }
                std::thread::sleep(std::time::Duration::from_millis(RX_POLL_MS as u64));
            }
        }
    }
}

/// Counters and timing, as returned by [`Bridge::stats`].
#[derive(Clone, Debug, PartialEq)]
pub struct Stats {
    /// Whether the threads are running.
    pub running: bool,
    /// Tick timing.
    pub tick: TickSummary,
    /// Frames handed to the transport and taken.
    pub tx_frames: u64,
    /// Failed sends.
    pub tx_errors: u64,
    /// Ticks on which the SLCAN peer had not opened the channel.
    pub tx_not_open: u64,
    /// Frames dropped for their age: flushed from the transport's queue, or
    /// not written because the peer had not taken the previous one.
    pub tx_stale_dropped: u64,
    /// Longest `send` call of the transmit thread, ns.
    pub send_max_ns: u64,
    /// Torques of the last frame written, Nm.
    pub applied_torques_nm: [f64; 4],
    /// Commands that exceeded a wheel's range (clamped or refused).
    pub limit_events: u64,
    /// The last such event, with the wheel, the command and the target.
    pub last_limit_event: Option<String>,
    /// Ticks on which a rate limit shaped the output.
    pub rate_limited_ticks: u64,
    /// Transport state.
    pub transport_state: TransportState,
    /// Times the transport was lost.
    pub transport_losses: u64,
    /// Reconnections (socketcand).
    pub reconnects: u64,
    /// SLCAN replies to the peer dropped because it was not reading them.
    pub replies_dropped: u64,
    /// Frames received (any ID).
    pub rx_frames: u64,
    /// Received frames rejected for a bad CRC.
    pub rx_crc_errors: u64,
    /// Received frames rejected for their alive counter (all kinds).
    pub rx_counter_errors: u64,
    /// ... of which repeated (same counter and payload).
    pub rx_repeated: u64,
    /// ... of which a second source (same counter, other payload).
    pub rx_two_sources: u64,
    /// ... of which out of sequence.
    pub rx_wrong_sequence: u64,
    /// Usable frames that followed lost ones.
    pub rx_lost_frames: u64,
    /// Frames spent (re)synchronising a counter (INITIAL, SYNC).
    pub rx_sync: u64,
    /// E2E-valid frames with a value outside its DBC range.
    pub rx_implausible: u64,
    /// Received frames rejected for a wrong length.
    pub rx_length_errors: u64,
    /// Unparsable lines or messages from the transport.
    pub rx_malformed: u64,
    /// Received frames with IDs the bridge does not use.
    pub rx_unknown_id: u64,
    /// Receive errors of the transport itself.
    pub rx_transport_errors: u64,
    /// Bus error reports.
    pub bus_errors: u64,
    /// Log lines dropped because the writer fell behind.
    pub log_dropped: u64,
    /// Log lines lost to write errors (full disk, `/dev/full`, a stalled FIFO).
    pub log_errors: u64,
    /// Mode of the last frame sent.
    pub safety_state: Mode,
    /// Whether the received state is currently valid.
    pub state_valid: bool,
    /// Why it is not, if not.
    pub state_reason: Option<String>,
    /// Last transmit error message.
    pub last_tx_error: Option<String>,
    /// Last receive error message.
    pub last_rx_error: Option<String>,
}

struct Running {
    /// The state this run's threads use: the stop request must go to this
    /// one, not to whatever `Bridge::shared` holds by the time `stop` runs.
    shared: Arc<Shared>,
    tx: JoinHandle<()>,
    rx: JoinHandle<()>,
    rx_stop: Arc<AtomicBool>,
    log: Option<LogWriter>,
}

/// The bridge.
pub struct Bridge {
    cfg: BridgeConfig,
    spec: ChannelSpec,
    shared: Mutex<Arc<Shared>>,
    run: Mutex<Option<Running>>,
    pty_path: Mutex<Option<String>>,
    /// Serialises `start` and `stop` as a whole (held across the joins), so a
    /// start never overlaps a stop that is still sending its safe frames.
    lifecycle: Mutex<()>,
}

impl Bridge {
    /// Validate the configuration; nothing is opened until [`Bridge::start`].
    pub fn new(cfg: BridgeConfig) -> Result<Self> {
        let spec = cfg.validate()?;
        let shared = Arc::new(Shared::new(&cfg));
        Ok(Bridge {
            cfg,
            spec,
            shared: Mutex::new(shared),
            run: Mutex::new(None),
            pty_path: Mutex::new(None),
            lifecycle: Mutex::new(()),
        })
    }

    /// The configuration.
    pub fn config(&self) -> &BridgeConfig {
        &self.cfg
    }

    fn shared(&self) -> Arc<Shared> {
        lock(&self.shared).clone()
    }

    /// Open the transport and start the threads. Each run starts with fresh
    /// counters, no command and a fresh `seq`.
    pub fn start(&self) -> Result<()> {
        let _life = lock(&self.lifecycle);
        let mut run = lock(&self.run);
        if run.is_some() {
            return Err(Error::State("bridge is already running".into()));
        }
        let shared = Arc::new(Shared::new(&self.cfg));
        *lock(&self.shared) = shared.clone();
        let (log_tx, log_writer) = match &self.cfg.log_path {
            Some(p) => {
                let (s, w) = candump::start(
                    p,
                    self.cfg.log_overwrite,
                    self.spec.log_name(),
                    shared.log_dropped.clone(),
                    shared.log_errors.clone(),
                )?;
                (Some(s), Some(w))
            }
            None => (None, None),
        };
        let opened = transport::open(&self.spec, self.cfg.bitrate)?;
        // Published only once the run is up, so a failed start leaves no
        // path to a pty that is already closed again.
        let pty_path = opened.pty_path.clone();
        let health = opened.health.clone();
        *lock(&shared.health) = Some(health.clone());
        let params = TxParams {
            period_ns: self.cfg.period_ns,
            safety: self.cfg.safety,
            stop_safe_frames: self.cfg.stop_safe_frames,
            transport_timeout_ns: self.cfg.transport_timeout_ns,
        };
        let mut sink = opened.sink;
        let mut source = opened.source;
        let tx_shared = shared.clone();
        let tx_log = log_tx.clone();
        let rt = self.cfg.rt_priority;
        let (ready_tx, ready_rx) = std::sync::mpsc::sync_channel::<Result<()>>(1);
        let tx = std::thread::Builder::new()
            .name("can_bridge-tx".into())
            .spawn(move || {
                let ready = rt.map_or(Ok(()), set_realtime);
                let ok = ready.is_ok();
                let _ = ready_tx.send(ready);
                if !ok {
                    return;
                }
                run_tx(
                    &MonotonicClock,
                    params,
                    &tx_shared,
                    sink.as_mut(),
                    Some(&health),
                    tx_log.as_ref(),
                )
            })
            .map_err(|e| Error::io("cannot start transmit thread", &e))?;
        match ready_rx.recv() {
            Ok(Ok(())) => {}
            Ok(Err(e)) => {
                let _ = tx.join();
                return Err(e);
            }
            Err(_) => {
                let _ = tx.join();
                return Err(Error::State("transmit thread ended during start".into()));
            }
        }
        let rx_stop = Arc::new(AtomicBool::new(false));
        let rx_stop2 = rx_stop.clone();
        let rx_shared = shared.clone();
        let timeout = self.cfg.state_timeout_ns;
        let rx = match std::thread::Builder::new()
            .name("can_bridge-rx".into())
            .spawn(move || {
                run_rx(
                    &rx_shared,
                    source.as_mut(),
                    timeout,
                    &rx_stop2,
                    log_tx.as_ref(),
                )
            }) {
            Ok(h) => h,
            Err(e) => {
                shared.request_stop();
                let _ = tx.join();
                return Err(Error::io("cannot start receive thread", &e));
            }
        };
        shared.open_for_commands();
        *run = Some(Running {
            shared,
            tx,
            rx,
            rx_stop,
            log: log_writer,
        });
        *lock(&self.pty_path) = pty_path;
        Ok(())
    }

    /// Release the output, send the zero frames, stop the threads, close the
    /// transport. Does nothing if not running.
    pub fn stop(&self) -> Result<()> {
        let _life = lock(&self.lifecycle);
        let Some(r) = lock(&self.run).take() else {
            return Ok(());
        };
        // The pty closes with this run; its /dev/pts/N may then be handed to
        // another process, so the old path is no longer reported.
        *lock(&self.pty_path) = None;
        r.shared.request_stop();
        let tx_ok = r.tx.join().is_ok();
        r.rx_stop.store(true, Ordering::Release);
        let rx_ok = r.rx.join().is_ok();
        if let Some(w) = r.log {
            w.join();
        }
        if !(tx_ok && rx_ok) {
            return Err(Error::State("a bridge thread ended abnormally".into()));
        }
        Ok(())
    }

    /// Whether the threads are running.
    pub fn is_running(&self) -> bool {
        lock(&self.run).is_some()
    }

    /// Hand over the latest command (FL, FR, RL, RR in Nm); see
    /// [`Shared::set_command`] for what is refused.
    pub fn set_command(&self, torques_nm: [f64; 4], seq: u64) -> Result<()> {
        self.shared().set_command(torques_nm, seq, monotonic_ns())
    }

    /// Clear a latched fault (takes effect on the next tick).
    pub fn reset_fault(&self) {
        self.shared().request_reset(monotonic_ns());
    }

    /// The received vehicle state now.
    pub fn latest_state(&self) -> VehicleState {
        let sh = self.shared();
        let rx = lock(&sh.rx);
        rx.state(monotonic_ns(), self.cfg.state_timeout_ns)
    }

    /// Counters and timing.
    pub fn stats(&self) -> Stats {
        let running = self.is_running();
        let sh = self.shared();
        let state = self.latest_state();
        let (limit_events, last_limit_event) = {
            let c = lock(&sh.cmd);
            (c.limit_events, c.last_limit_event.clone())
        };
        let (reconnects, replies_dropped) = lock(&sh.health)
            .as_ref()
            .map(|h| {
                (
                    h.reconnects.load(Ordering::Relaxed),
                    h.replies_dropped.load(Ordering::Relaxed),
                )
            })
            .unwrap_or((0, 0));
        let tx = lock(&sh.tx);
        let rx = lock(&sh.rx).clone();
        Stats {
            running,
            tick: tx.tick.summary(),
            tx_frames: tx.tx_frames,
            tx_errors: tx.tx_errors,
            tx_not_open: tx.tx_not_open,
            tx_stale_dropped: tx.tx_stale_dropped,
            send_max_ns: tx.send_max_ns,
            applied_torques_nm: tx.applied,
            limit_events,
            last_limit_event,
            rate_limited_ticks: tx.rate_limited_ticks,
            transport_state: tx.transport,
            transport_losses: tx.transport_losses,
            reconnects,
            replies_dropped,
            rx_frames: rx.rx_frames,
            rx_crc_errors: rx.rx_crc_errors,
            rx_counter_errors: rx.rx_counter_errors,
            rx_repeated: rx.rx_repeated,
            rx_two_sources: rx.rx_two_sources,
            rx_wrong_sequence: rx.rx_wrong_sequence,
            rx_lost_frames: rx.rx_lost_frames,
            rx_sync: rx.rx_sync,
            rx_implausible: rx.rx_implausible,
            rx_length_errors: rx.rx_length_errors,
            rx_malformed: rx.rx_malformed,
            rx_unknown_id: rx.rx_unknown_id,
            rx_transport_errors: rx.rx_transport_errors,
            bus_errors: rx.bus_errors,
            log_dropped: sh.log_dropped.load(Ordering::Relaxed),
            log_errors: sh.log_errors.load(Ordering::Relaxed),
            safety_state: tx.mode,
            state_valid: state.valid,
            state_reason: state.reason,
            last_tx_error: tx.last_error.clone(),
            last_rx_error: rx.last_error,
        }
    }

    /// Recorded ticks (up to `trace_capacity`).
    pub fn tick_trace(&self) -> Vec<TickRecord> {
        lock(&self.shared().tx).tick.trace().to_vec()
    }

    /// Pseudo-terminal slave path for `slcan-pty:` while running (`None`
    /// before `start` and once `stop` has begun).
    pub fn pty_path(&self) -> Option<String> {
        lock(&self.pty_path).clone()
    }
}

impl Drop for Bridge {
    fn drop(&mut self) {
        let _ = self.stop();
    }
}

/// `clip` re-exported for the pyo3 layer's messages.
pub fn clip_input(s: &str) -> String {
    clip(s)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::codec::WHEEL_TORQUE_CMD;
    use crate::safety::WheelLimits;
    use crate::transport::Outcome;
    use std::cell::RefCell;

    const MS: u64 = 1_000_000;

    /// A clock that jumps to each deadline plus a scripted lateness, and
    /// advances by a scripted work time inside `send`.
    struct FakeClock {
        now: AtomicU64,
        late: Box<dyn Fn(u64) -> u64 + Send>,
        wakes: AtomicU64,
    }

    impl Clock for FakeClock {
        fn now_ns(&self) -> u64 {
            self.now.load(Ordering::SeqCst)
        }
        fn sleep_until_ns(&self, d: u64) {
            let k = self.wakes.fetch_add(1, Ordering::SeqCst);
            let now = self.now.load(Ordering::SeqCst).max(d) + (self.late)(k);
            self.now.store(now, Ordering::SeqCst);
        }
    }

    type Script<'a> = Box<dyn Fn(usize, &Shared, &FakeClock) -> Outcome + 'a>;

    /// Records frames; runs a script per tick (by tick number) that may set
    /// commands, request a stop, burn time, and says what the transport did.
    struct ScriptSink<'a> {
        clock: &'a FakeClock,
        shared: &'a Shared,
        frames: RefCell<Vec<(u64, CanFrame, Outcome)>>,
        script: Script<'a>,
        closed: bool,
    }

    // SAFETY: the test runs on one thread; the sink never crosses threads.
    unsafe impl Send for ScriptSink<'_> {}

    impl Sink for ScriptSink<'_> {
        fn send(&mut self, f: &CanFrame) -> Result<Outcome> {
            let n = self.frames.borrow().len();
            let o = (self.script)(n, self.shared, self.clock);
            self.frames.borrow_mut().push((self.clock.now_ns(), *f, o));
            Ok(o)
        }
        fn close(&mut self) {
            self.closed = true;
        }
    }

    fn wheel(lim: f64) -> WheelLimits {
        WheelLimits {
            min_nm: -lim,
            max_nm: lim,
            rise_nm_per_s: 200.0,
            release_nm_per_s: 200.0,
        }
    }

    fn config() -> BridgeConfig {
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

    fn params() -> TxParams {
        let c = config();
        TxParams {
            period_ns: 50 * MS,
            safety: c.safety,
            stop_safe_frames: 3,
            transport_timeout_ns: 200 * MS,
        }
    }

    fn decode(f: &CanFrame) -> (u8, u8, [f64; 4]) {
        let m = &WHEEL_TORQUE_CMD;
        assert!(e2e::crc_ok(f.data(), m.data_id));
        let g = |n: &str| m.signal(n).unwrap().get(f.data());
        (
            e2e::counter_of(f.data()).unwrap(),
            g("Mode") as u8,
            [g("TorqueFL"), g("TorqueFR"), g("TorqueRL"), g("TorqueRR")],
        )
    }

    type Run = (Vec<(u64, CanFrame, Outcome)>, Shared, bool);

    /// Run the loop with a script; returns (frames, shared, closed).
    fn run(
        late: impl Fn(u64) -> u64 + Send + 'static,
        script: impl Fn(usize, &Shared, &FakeClock) -> Outcome,
    ) -> Run {
        let shared = Shared::new(&config());
        shared.open_for_commands();
        let clock = FakeClock {
            now: AtomicU64::new(1_000 * MS),
            late: Box::new(late),
            wakes: AtomicU64::new(0),
        };
        let mut sink = ScriptSink {
            clock: &clock,
            shared: &shared,
            frames: RefCell::new(vec![]),
            script: Box::new(script),
            closed: false,
        };
        run_tx(&clock, params(), &shared, &mut sink, None, None);
        let closed = sink.closed;
        let frames = std::mem::take(&mut *sink.frames.borrow_mut());
        drop(sink);
        (frames, shared, closed)
    }

    /// A controller that sends a fresh command every tick for 40 ticks, then
    /// goes silent; stop after tick 80.
    fn controller(n: usize, sh: &Shared, _c: &FakeClock) -> Outcome {
        if n < 40 {
            // Arrival 0.4 ms after this tick's deadline, whatever the wake-up
            // jitter: frames then depend on commands and arrival times only.
            let t = [55.0, -55.0, 5.0, 300.0];
            let at = 1_050 * MS + n as u64 * 50 * MS + 400_000;
            sh.set_command(t, n as u64 + 1, at).unwrap();
        }
        if n == 80 {
            sh.request_stop();
        }
        Outcome::YES
    }

    #[test]
    fn ticks_on_absolute_deadlines_and_stops_with_safe_frames() {
        let (frames, shared, closed) = run(|k| (k % 7) * 100_000, controller);
        assert!(closed);
        // 81 ticks before the stop request is seen, then 3 zero frames.
        assert_eq!(frames.len(), 84);
        for (k, (t, _, _)) in frames.iter().enumerate() {
            let deadline = 1_050 * MS + k as u64 * 50 * MS;
            assert!(*t >= deadline && *t < deadline + MS, "tick {k} at {t}");
        }
        let d: Vec<_> = frames.iter().map(|(_, f, _)| decode(f)).collect();
        for (k, x) in d.iter().enumerate() {
            assert_eq!(x.0 as usize, k % 15);
        }
        // First tick: no command yet -> Safe. Rise 200 Nm/s = 10 Nm per tick.
        assert_eq!(d[0].1, Mode::Safe as u8);
        assert_eq!(d[1].1, Mode::Active as u8);
        assert_eq!(d[1].2, [10.0, -10.0, 4.0, 10.0]); // 5 Nm is a tie: to even (4)
        assert_eq!(d[12].2, [56.0, -56.0, 4.0, 100.0]);
        // The last command arrives during tick 39, 0.4 ms after its
        // deadline: its age at tick 39 + j is 50 j ms minus that.
        // Hold from the first age >= 120 ms (j = 3), Safe from >= 300 (j = 7),
        // Fault from >= 1000 (j = 21).
        assert_eq!(d[41].1, Mode::Active as u8);
        assert_eq!(d[42].1, Mode::Hold as u8);
        assert_eq!(d[42].2, [56.0, -56.0, 4.0, 100.0]);
        assert_eq!(d[45].1, Mode::Hold as u8);
        assert_eq!(d[46].1, Mode::Safe as u8);
        // Released at 400 Nm/s = 20 Nm per tick, not in one step.
        assert_eq!(d[46].2, [36.0, -36.0, 0.0, 80.0]);
        assert_eq!(d[51].2, [0.0; 4]);
        assert_eq!(d[59].1, Mode::Safe as u8);
        assert_eq!(d[60].1, Mode::Fault as u8);
        for x in &d[81..] {
            assert_eq!((x.1, x.2), (Mode::Fault as u8, [0.0; 4]));
        }
        let s = lock(&shared.tx).tick.summary();
        assert_eq!(s.ticks, 84);
        assert_eq!(s.overruns, 0);
        assert!(s.lateness_max_us <= 600.0 + 1e-9);
        assert!(s.drift_us.unwrap().abs() < 1_000.0);
    }

    #[test]
    fn stop_releases_before_its_zero_frames() {
        let (frames, ..) = run(
            |_| 0,
            |n, sh, c| {
                if n < 20 {
                    sh.set_command([-100.0; 4], n as u64 + 1, c.now_ns())
                        .unwrap();
                }
                if n == 19 {
                    sh.request_stop();
                }
                Outcome::YES
            },
        );
        let d: Vec<_> = frames.iter().map(|(_, f, _)| decode(f)).collect();
        assert_eq!(d[19].2, [-100.0; 4]);
        let tail: Vec<f64> = d[20..].iter().map(|x| x.2[0]).collect();
        assert_eq!(tail, [-80.0, -60.0, -40.0, -20.0, 0.0, 0.0, 0.0]);
        assert!(d[20..].iter().all(|x| x.1 == Mode::Safe as u8));
    }

    #[test]
    fn same_commands_in_same_bytes_out() {
        let (a, ..) = run(|k| (k % 3) * 50_000, controller);
        let (b, ..) = run(|k| (k % 5) * 900_000 + 7, controller);
        let fa: Vec<CanFrame> = a.iter().map(|x| x.1).collect();
        let fb: Vec<CanFrame> = b.iter().map(|x| x.1).collect();
        assert_eq!(fa, fb);
    }

    #[test]
    fn overrun_skips_deadlines_and_lateness_counts_the_whole_wait() {
        let (frames, shared, _) = run(
            |_| 0,
            |n, sh, c| {
                if n == 5 {
                    // This tick's work takes 130 ms: deadlines +50 and +100 are skipped.
                    c.now.fetch_add(130 * MS, Ordering::SeqCst);
                }
                if n == 10 {
                    sh.request_stop();
                }
                Outcome::YES
            },
        );
        let t: Vec<u64> = frames.iter().map(|x| x.0).collect();
        assert_eq!(t[6] - t[5], 20 * MS); // frame 5 is stamped after its 130 ms of work
        let s = lock(&shared.tx).tick.summary();
        assert_eq!(s.overruns, 1);
        assert_eq!(s.skipped_ticks, 2);
        // The tick after the overrun was due 100 ms before it woke.
        assert!((s.lateness_max_us - 100_000.0).abs() < 1.0, "{s:?}");
    }

    #[test]
    fn a_transport_that_takes_nothing_is_lost_then_recovers_from_zero() {
        let (frames, shared, _) = run(
            |_| 0,
            |n, sh, c| {
                let _ = sh.set_command([100.0; 4], n as u64 + 1, c.now_ns());
                if n == 40 {
                    sh.request_stop();
                }
                if (15..25).contains(&n) {
                    Outcome::DROPPED
                } else {
                    Outcome::YES
                }
            },
        );
        let tx = lock(&shared.tx);
        assert_eq!(tx.transport_losses, 1);
        assert_eq!(tx.tx_stale_dropped, 10);
        drop(tx);
        let d: Vec<_> = frames.iter().map(|(_, f, _)| decode(f)).collect();
        // Lost after 200 ms (4 ticks) without a frame through; from then on
        // the output restarts from 0 Nm and ramps at the rise rate.
        assert_eq!(d[14].2[0], 100.0);
        assert_eq!(d[25].2[0], 10.0);
        assert_eq!(d[26].2[0], 20.0);
    }

    #[test]
    fn reset_clears_latched_fault() {
        let (frames, ..) = run(
            |_| 0,
            |n, sh, c| {
                if n == 0 {
                    sh.set_command([20.0; 4], 1, c.now_ns()).unwrap();
                }
                if n == 30 {
                    sh.request_reset(c.now_ns());
                }
                if n == 33 {
                    sh.set_command([20.0; 4], 2, c.now_ns()).unwrap();
                }
                if n == 36 {
                    sh.request_stop();
                }
                Outcome::YES
            },
        );
        let d: Vec<_> = frames.iter().map(|(_, f, _)| decode(f)).collect();
        assert_eq!(d[30].1, Mode::Fault as u8);
        assert_eq!(d[31].1, Mode::Safe as u8);
        assert_eq!(d[33].1, Mode::Safe as u8);
        assert_eq!(d[34].1, Mode::Active as u8);
        assert_eq!(d[34].2, [10.0; 4]);
    }

    #[test]
    fn commands_outside_a_run_seq_bounds_and_limit_rules() {
        let mut cfg = config();
        let sh = Shared::new(&cfg);
        assert!(matches!(
            sh.set_command([0.0; 4], 1, 0),
            Err(Error::State(_))
        ));
        sh.open_for_commands();
        assert!(matches!(
            sh.set_command([f64::NAN, 0.0, 0.0, 0.0], 1, 0),
            Err(Error::Command(_))
        ));
        assert!(matches!(
            sh.set_command([0.0; 4], u64::MAX, 0),
            Err(Error::Command(_))
        ));
        sh.set_command([1.0; 4], 5, 0).unwrap();
        assert!(matches!(
            sh.set_command([1.0; 4], 5, 0),
            Err(Error::Command(_))
        ));
        assert!(matches!(
            sh.set_command([1.0; 4], 5 + SEQ_MAX_STEP + 1, 0),
            Err(Error::Command(_))
        ));
        sh.set_command([500.0, 0.0, 0.0, 0.0], 6, 0).unwrap();
        let slot = lock(&sh.cmd);
        assert_eq!(slot.cmd.unwrap().torques_nm, [100.0, 0.0, 0.0, 0.0]);
        assert_eq!(slot.limit_events, 1);
        assert!(slot
            .last_limit_event
            .as_ref()
            .unwrap()
            .starts_with("FL 500 -> 100 Nm"));
        drop(slot);
        sh.request_stop();
        assert!(matches!(
            sh.set_command([0.0; 4], 7, 0),
            Err(Error::State(_))
        ));
        cfg.safety.limit_rule = LimitRule::Refuse;
        let sh = Shared::new(&cfg);
        sh.open_for_commands();
        let e = sh.set_command([0.0, 0.0, -101.0, 0.0], 1, 0).unwrap_err();
        assert!(
            e.to_string()
                .contains("RL = -101 Nm is outside its range [-100, 100]"),
            "{e}"
        );
    }

    /// Feed one healthy frame of each received message but `skip` (an
    /// index into `RX_MESSAGES`), all with counter `c`.
    fn all_but(rx: &mut RxStore, skip: Option<usize>, c: u8, t: u64, to: u64) {
        use crate::codec::{
            DRIVER_DEMAND, STEERING_STATE, VEHICLE_ACCEL, VEHICLE_MOTION, WHEEL_SPEEDS,
        };
        let frames = [
            VEHICLE_MOTION.encode(&[12.34, -0.5, 0.25], c),
            WHEEL_SPEEDS.encode(&[40.1, 40.2, 40.3, 40.4], c),
            STEERING_STATE.encode(&[0.1234], c),
            VEHICLE_ACCEL.encode(&[-3.21, 7.5], c),
            DRIVER_DEMAND.encode(&[-1234.5, 17.25, 0.35], c),
        ];
        for (i, f) in frames.into_iter().enumerate() {
            if Some(i) != skip {
                rx.on_frame(&f.unwrap(), t, to);
            }
        }
    }

    /// One healthy frame of every received message, counter `c`.
    fn all_five(rx: &mut RxStore, c: u8, t: u64, to: u64) {
        all_but(rx, None, c, t, to);
    }

    #[test]
    fn receive_checks_and_state_validity() {
        use crate::codec::VEHICLE_MOTION;
        let mut rx = RxStore::new(2, 2, 2);
        let to = 250 * MS;
        let t = 10_000 * MS;
        let s = rx.state(t, to);
        assert!(
            !s.valid
                && s.reason
                    .as_deref()
                    .unwrap()
                    .contains("VehicleMotion: no data")
        );
        all_five(&mut rx, 0, t, to);
        all_five(&mut rx, 1, t, to);
        assert_eq!(rx.state(t, to).status, ["sync"; N_RX]);
        all_five(&mut rx, 2, t + MS, to);
        let s = rx.state(t + 2 * MS, to);
        assert!(s.valid, "{s:?}");
        assert!((s.long_speed_mps.unwrap() - 12.34).abs() < 1e-9);
        assert!((s.wheel_speeds_radps.unwrap()[3] - 40.4).abs() < 1e-9);
        assert_eq!(s.age_ms, Some(1.0));
        assert_eq!(s.status, ["ok"; N_RX]);
        // Bad CRC: rejected, value unchanged; one strike keeps it valid.
        let mut bad = VEHICLE_MOTION
            .encode(&[19.0, 0.0, 0.0], 3)
            .unwrap()
            .data()
            .to_vec();
        bad[0] ^= 1;
        rx.on_frame(&CanFrame::new(0x201, false, &bad).unwrap(), t + 3 * MS, to);
        assert_eq!(rx.rx_crc_errors, 1);
        assert_eq!(rx.state(t + 3 * MS, to).status[0], "wrong crc");
        rx.on_frame(
            &VEHICLE_MOTION.encode(&[1.0, 0.0, 0.0], 3).unwrap(),
            t + 4 * MS,
            to,
        );
        assert!(rx.state(t + 4 * MS, to).valid);
        // A repeat: invalid at once, and counted.
        rx.on_frame(
            &VEHICLE_MOTION.encode(&[1.0, 0.0, 0.0], 3).unwrap(),
            t + 5 * MS,
            to,
        );
        assert_eq!(rx.rx_repeated, 1);
        assert_eq!(rx.state(t + 5 * MS, to).status[0], "repeated");
        // Implausible value: not used.
        rx.on_frame(
            &VEHICLE_MOTION.encode(&[150.0, 0.0, 0.0], 4).unwrap(),
            t + 6 * MS,
            to,
        );
        assert_eq!(rx.rx_implausible, 1);
        assert!((rx.state(t + 6 * MS, to).long_speed_mps.unwrap() - 1.0).abs() < 1e-9);
        // Wrong length, unknown id.
        rx.on_frame(&CanFrame::new(0x203, false, &[0; 8]).unwrap(), t, to);
        rx.on_frame(&CanFrame::new(0x555, false, &[0; 8]).unwrap(), t, to);
        assert_eq!(rx.rx_length_errors, 1);
        assert_eq!(rx.rx_unknown_id, 1);
        // Goes invalid when it stops arriving; after the gap it re-synchronises.
        assert_eq!(rx.state(t + 300 * MS, to).status[1], "timeout");
        let sync = rx.rx_sync;
        all_five(&mut rx, 9, t + 600 * MS, to);
        all_five(&mut rx, 10, t + 601 * MS, to);
        assert_eq!(rx.rx_sync, sync + 2 * N_RX as u64);
        assert!(!rx.state(t + 601 * MS, to).valid);
        all_five(&mut rx, 11, t + 602 * MS, to);
        assert!(rx.state(t + 602 * MS, to).valid);
    }

    #[test]
    fn accel_and_driver_demand_decode_into_the_state() {
        let mut rx = RxStore::new(2, 2, 2);
        let to = 250 * MS;
        let t = 10_000 * MS;
        let s = rx.state(t, to);
        assert_eq!(
            (s.long_accel_mps2, s.driver_torque_nm, s.road_friction),
            (None, None, None)
        );
        for c in 0..3 {
            all_five(&mut rx, c, t + u64::from(c) * 20 * MS, to);
        }
        let s = rx.state(t + 45 * MS, to);
        assert!(s.valid, "{s:?}");
        let near = |x: Option<f64>, want: f64| (x.unwrap() - want).abs() < 1e-9;
        assert!(near(s.long_accel_mps2, -3.21), "{s:?}");
        assert!(near(s.lat_accel_mps2, 7.5), "{s:?}");
        assert!(near(s.driver_torque_nm, -1234.5), "{s:?}");
        assert!(near(s.set_speed_mps, 17.25), "{s:?}");
        assert!(near(s.road_friction, 0.35), "{s:?}");
        // Oldest of the five: all fed at t + 40 ms.
        assert_eq!(s.age_ms, Some(5.0));
    }

    #[test]
    fn a_missing_accel_or_driver_demand_makes_the_state_invalid() {
        for (skip, name) in [(3, "VehicleAccel"), (4, "DriverDemand")] {
            let mut rx = RxStore::new(2, 2, 2);
            let to = 250 * MS;
            let t = 10_000 * MS;
            // Never received: no data, and no age for the whole state.
            for c in 0..4 {
                all_but(&mut rx, Some(skip), c, t + u64::from(c) * 20 * MS, to);
            }
            let s = rx.state(t + 70 * MS, to);
            assert!(!s.valid);
            assert_eq!(s.reason.as_deref(), Some(&*format!("{name}: no data")));
            assert_eq!(s.status[skip], "no data");
            assert_eq!(s.age_ms, None);
            // Received, then it stops while the others go on: timeout.
            let mut rx = RxStore::new(2, 2, 2);
            for c in 0..4 {
                all_five(&mut rx, c, t + u64::from(c) * 20 * MS, to);
            }
            assert!(rx.state(t + 70 * MS, to).valid);
            for c in 4..20u8 {
                all_but(&mut rx, Some(skip), c % 15, t + u64::from(c) * 20 * MS, to);
            }
            let s = rx.state(t + 390 * MS, to);
            assert!(!s.valid);
            assert_eq!(s.reason.as_deref(), Some(&*format!("{name}: timeout")));
            assert!(s.age_ms.unwrap() > 250.0, "{s:?}");
        }
    }

    #[test]
    fn a_corrupt_or_implausible_accel_or_driver_demand_is_not_used() {
        use crate::codec::{DRIVER_DEMAND, VEHICLE_ACCEL};
        let to = 250 * MS;
        let t = 10_000 * MS;
        for (skip, m) in [(3, &VEHICLE_ACCEL), (4, &DRIVER_DEMAND)] {
            let mut rx = RxStore::new(2, 2, 2);
            for c in 0..3 {
                all_five(&mut rx, c, t + u64::from(c) * 20 * MS, to);
            }
            assert!(rx.state(t + 40 * MS, to).valid);
            let before = rx.state(t + 40 * MS, to);
            // Bad CRC on every frame from now on: rejected, then invalid by
            // the strikes in its window; the last good values stay.
            let other: &[f64] = if skip == 3 {
                &[1.0, 1.0]
            } else {
                &[1.0, 1.0, 1.0]
            };
            for c in 3..7u8 {
                let ts = t + u64::from(c) * 20 * MS;
                all_but(&mut rx, Some(skip), c, ts, to);
                let mut d = m.encode(other, c).unwrap().data().to_vec();
                d[0] ^= 0x01;
                rx.on_frame(&CanFrame::new(m.id, false, &d).unwrap(), ts, to);
            }
            let s = rx.state(t + 121 * MS, to);
            assert!(!s.valid);
            assert_eq!(
                s.reason.as_deref(),
                Some(&*format!("{}: wrong crc", m.name))
            );
            assert_eq!(rx.rx_crc_errors, 4);
            assert_eq!(
                (s.long_accel_mps2, s.driver_torque_nm, s.road_friction),
                (
                    before.long_accel_mps2,
                    before.driver_torque_nm,
                    before.road_friction
                )
            );
            // Implausible values (outside the DBC's [min|max]) are not used.
            let mut rx = RxStore::new(2, 2, 2);
            for c in 0..3 {
                all_five(&mut rx, c, t + u64::from(c) * 20 * MS, to);
            }
            let bad: &[f64] = if skip == 3 {
                &[25.0, 0.0]
            } else {
                &[0.0, 10.0, 0.02]
            };
            rx.on_frame(&m.encode(bad, 3).unwrap(), t + 60 * MS, to);
            assert_eq!(rx.rx_implausible, 1);
            let s = rx.state(t + 61 * MS, to);
            assert_eq!(s.status[skip], "implausible");
            assert!(s
                .reason
                .unwrap()
                .starts_with(&format!("{}: implausible", m.name)));
            assert!(rx.last_error.as_deref().unwrap().starts_with(m.name));
            assert!((s.long_accel_mps2.unwrap() + 3.21).abs() < 1e-9);
            assert!((s.road_friction.unwrap() - 0.35).abs() < 1e-9);
        }
    }

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
