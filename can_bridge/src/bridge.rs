//! The running bridge: a transmit thread on absolute deadlines, a receive
//! thread, and the shared state the Python thread touches only through short
//! critical sections (no thread ever needs the GIL).

use crate::candump::{self, Dir, LogSender, LogWriter};
use crate::channel::ChannelSpec;
use crate::codec::{encode_torque_cmd, Mode, RX_MESSAGES};
use crate::e2e::{self, Check, Receiver};
use crate::error::{Error, Result};
use crate::frame::CanFrame;
use crate::safety::{Command, Safety, SafetyConfig};
use crate::scheduler::{
    monotonic_ns, realtime_ns, Clock, MonotonicClock, Schedule, TickRecord, TickStats, TickSummary,
};
use crate::transport::{self, RxItem, Sent, Sink, Source};
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::thread::JoinHandle;

/// Receive thread poll timeout, ms (bounds stop latency).
const RX_POLL_MS: i32 = 20;

/// Everything a bridge is configured with.
#[derive(Clone, Debug, PartialEq)]
pub struct BridgeConfig {
    /// Channel string (see [`ChannelSpec`]).
    pub channel: String,
    /// Tick period, ns.
    pub period_ns: u64,
    /// Limits and watchdog.
    pub safety: SafetyConfig,
    /// Received state is invalid when any message is older than this, ns.
    pub state_timeout_ns: u64,
    /// candump log of every frame sent and received.
    pub log_path: Option<PathBuf>,
    /// CAN bit rate requested from SLCAN adapters.
    pub bitrate: u32,
    /// Safe frames sent on stop before the transport closes.
    pub stop_safe_frames: u32,
    /// Largest accepted alive-counter step on receive.
    pub rx_max_counter_delta: u8,
    /// Tick records kept for `tick_trace` (allocated at start).
    pub trace_capacity: usize,
    /// Run the transmit thread under `SCHED_FIFO` at this priority (1..=99);
    /// needs CAP_SYS_NICE or root. `None`: the default scheduler.
    pub rt_priority: Option<i32>,
}

impl BridgeConfig {
    /// Defaults: 50 ms period, default safety limits, 250 ms state timeout.
    pub fn new(channel: &str) -> Self {
        BridgeConfig {
            channel: channel.to_string(),
            period_ns: 50_000_000,
            safety: SafetyConfig::default(),
            state_timeout_ns: 250_000_000,
            log_path: None,
            bitrate: 500_000,
            stop_safe_frames: 3,
            rx_max_counter_delta: 2,
            trace_capacity: 0,
            rt_priority: None,
        }
    }

    /// Check every setting; returns the parsed channel.
    pub fn validate(&self) -> Result<ChannelSpec> {
        let spec = ChannelSpec::parse(&self.channel)?;
        if !(1_000_000..=10_000_000_000).contains(&self.period_ns) {
            return Err(Error::Config(format!(
                "period_ms = {} must be between 1 and 10000",
                self.period_ns as f64 / 1e6
            )));
        }
        self.safety.validate()?;
        if self.state_timeout_ns == 0 {
            return Err(Error::Config("state_timeout_ms must be positive".into()));
        }
        if self.stop_safe_frames > 100 {
            return Err(Error::Config("stop_safe_frames must be at most 100".into()));
        }
        if !(1..=e2e::MAX_COUNTER).contains(&self.rx_max_counter_delta) {
            return Err(Error::Config(
                "rx_max_counter_delta must be in 1..=14".into(),
            ));
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
}

/// Transmit-side counters.
#[derive(Debug)]
pub struct TxCounters {
    tick: TickStats,
    tx_frames: u64,
    tx_errors: u64,
    tx_not_open: u64,
    mode: Mode,
    last_error: Option<String>,
}

impl TxCounters {
    fn new(period_ns: u64, trace: usize) -> Self {
        TxCounters {
            tick: TickStats::new(period_ns, trace),
            tx_frames: 0,
            tx_errors: 0,
            tx_not_open: 0,
            mode: Mode::Safe,
            last_error: None,
        }
    }
}

#[derive(Debug, Clone)]
struct RxSlotState {
    receiver: Receiver,
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
    rx_length_errors: u64,
    rx_malformed: u64,
    rx_unknown_id: u64,
    rx_transport_errors: u64,
    bus_errors: u64,
    last_error: Option<String>,
}

impl RxStore {
    fn new(max_delta: u8) -> Self {
        RxStore {
            slots: RX_MESSAGES
                .iter()
                .map(|m| RxSlotState {
                    receiver: Receiver::new(m.data_id, m.len, max_delta),
                    last_ok_ns: None,
                    values: [0.0; 4],
                })
                .collect(),
            rx_frames: 0,
            rx_crc_errors: 0,
            rx_counter_errors: 0,
            rx_length_errors: 0,
            rx_malformed: 0,
            rx_unknown_id: 0,
            rx_transport_errors: 0,
            bus_errors: 0,
            last_error: None,
        }
    }

    /// Check and store one received frame.
    pub fn on_frame(&mut self, f: &CanFrame, now_ns: u64, state_timeout_ns: u64) {
        self.rx_frames += 1;
        let idx = RX_MESSAGES
            .iter()
            .position(|m| m.id == f.id() && !f.is_extended() && !f.is_remote());
        let Some((i, slot)) = idx.and_then(|i| self.slots.get_mut(i).map(|s| (i, s))) else {
            self.rx_unknown_id += 1;
            return;
        };
        if slot
            .last_ok_ns
            .is_some_and(|t| now_ns.saturating_sub(t) > state_timeout_ns)
        {
            slot.receiver.resync();
        }
        let verdict = slot.receiver.check(f.data());
        match verdict {
            Check::Ok | Check::OkSomeLost => {
                if let Some(m) = RX_MESSAGES.get(i) {
                    m.decode_values(f.data(), &mut slot.values);
                }
                slot.last_ok_ns = Some(now_ns);
            }
            Check::BadCrc => self.rx_crc_errors += 1,
            Check::BadLength => self.rx_length_errors += 1,
            Check::Repeated | Check::WrongSequence | Check::InvalidCounter => {
                self.rx_counter_errors += 1
            }
        }
    }

    /// The vehicle state as of `now_ns`.
    pub fn state(&self, now_ns: u64, state_timeout_ns: u64) -> VehicleState {
        let get = |i: usize| {
            self.slots
                .get(i)
                .and_then(|s| s.last_ok_ns.map(|t| (t, s.values)))
        };
        let motion = get(0);
        let wheels = get(1);
        let steer = get(2);
        let ages: Vec<Option<u64>> = [motion, wheels, steer]
            .iter()
            .map(|x| x.map(|(t, _)| now_ns.saturating_sub(t)))
            .collect();
        let valid = ages
            .iter()
            .all(|a| a.is_some_and(|a| a <= state_timeout_ns));
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
            age_ms,
        }
    }
}

/// The received vehicle state. Fields are `None` until their message has
/// been received once; `valid` is true only while every message is fresh.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct VehicleState {
    /// All three messages received within the state timeout.
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
    /// Age of the oldest of the three messages, ms (`None` until all arrived).
    pub age_ms: Option<f64>,
}

/// State shared by the threads and the caller.
#[derive(Debug)]
pub struct Shared {
    cmd: Mutex<CmdSlot>,
    reset_at: Mutex<Option<u64>>,
    stop: AtomicBool,
    tx: Mutex<TxCounters>,
    rx: Mutex<RxStore>,
    log_dropped: Arc<AtomicU64>,
    log_errors: Arc<AtomicU64>,
}

impl Shared {
    /// Fresh shared state.
    pub fn new(cfg: &BridgeConfig) -> Self {
        Shared {
            cmd: Mutex::new(CmdSlot::default()),
            reset_at: Mutex::new(None),
            stop: AtomicBool::new(false),
            tx: Mutex::new(TxCounters::new(cfg.period_ns, cfg.trace_capacity)),
            rx: Mutex::new(RxStore::new(cfg.rx_max_counter_delta)),
            log_dropped: Arc::new(AtomicU64::new(0)),
            log_errors: Arc::new(AtomicU64::new(0)),
        }
    }

    /// Validate and store the latest command (arrival time `now_ns`).
    pub fn set_command(&self, torques_nm: [f64; 4], seq: u64, now_ns: u64) -> Result<()> {
        let cmd = Command::new(torques_nm, seq, now_ns)?;
        let mut slot = lock(&self.cmd);
        if let Some(last) = slot.last_seq {
            if seq <= last {
                return Err(Error::Command(format!(
                    "seq {seq} is not newer than the last accepted seq {last}; command refused"
                )));
            }
        }
        slot.last_seq = Some(seq);
        slot.cmd = Some(cmd);
        Ok(())
    }

    /// Ask the transmit thread to clear a latched fault.
    pub fn request_reset(&self, now_ns: u64) {
        *lock(&self.reset_at) = Some(now_ns);
    }

    /// Ask the transmit thread to send its safe frames and finish.
    pub fn request_stop(&self) {
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
    /// Safe frames sent after a stop request.
    pub stop_safe_frames: u32,
}

/// The transmit loop: runs until a stop request, then sends the safe frames
/// on the following ticks and closes the sink.
pub fn run_tx<C: Clock>(
    clock: &C,
    p: TxParams,
    shared: &Shared,
    sink: &mut dyn Sink,
    log: Option<&LogSender>,
) {
    let t0 = clock.now_ns();
    let mut sched = Schedule::new(t0 + p.period_ns, p.period_ns);
    let mut safety = Safety::new(p.safety, sched.deadline());
    let mut counter: u8 = 0;
    let mut stopping: Option<u32> = None;
    // Commands received (real time) before the last reset are stale.
    let mut stale_before = 0u64;
    let origin = sched.deadline();
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
        // A reset request clears a latched fault; without one it is a no-op
        // (it must not cut a healthy output to zero past the rate limit).
        if let Some(t) = lock(&shared.reset_at).take() {
            if safety.reset(deadline) {
                stale_before = t;
            }
        }
        let latest = lock(&shared.cmd).cmd;
        // The watchdog measures a command's age from the first deadline after
        // its arrival: whole ticks, so its decisions do not depend on jitter.
        let cmd = latest
            .filter(|c| c.received_ns >= stale_before)
            .map(|c| Command {
                // A (recent) command from before start counts from the first tick.
                received_ns: first_deadline_after(c.received_ns, origin, p.period_ns).max(origin),
                ..c
            });
        let (mode, torques) = if stopping.is_some() {
            safety.force_safe()
        } else {
            safety.step(deadline, cmd.as_ref())
        };
        let frame = encode_torque_cmd(&torques, mode, counter);
        let outcome = match &frame {
            Ok(f) => sink.send(f),
            Err(e) => Err(e.clone()),
        };
        if let Some(n) = stopping.as_mut() {
            *n = n.saturating_sub(1);
        }
        let done = clock.now_ns();
        let skipped = sched.advance(done);
        let mut tx = lock(&shared.tx);
        tx.tick.record_wake(TickRecord {
            index: sched.index().saturating_sub(1 + skipped),
            deadline_ns: deadline,
            wake_ns: wake,
        });
        tx.tick.record_skip(skipped);
        tx.mode = mode;
        match outcome {
            Ok(Sent::Yes) => {
                tx.tx_frames += 1;
                counter = e2e::next_counter(counter);
                if let (Some(l), Ok(f)) = (log, &frame) {
                    l.log(realtime_ns(), f, Dir::Tx);
                }
            }
            Ok(Sent::NotOpen) => tx.tx_not_open += 1,
            Err(e) => {
                tx.tx_errors += 1;
                counter = e2e::next_counter(counter);
                tx.last_error = Some(e.to_string());
            }
        }
    }
    sink.close();
}

/// The first point of the grid `origin + k * period` (k may be negative)
/// strictly after `t`: the first tick that certainly saw a command received at `t`.
pub fn first_deadline_after(t: u64, origin: u64, period: u64) -> u64 {
    let period = period.max(1);
    if t >= origin {
        origin + ((t - origin) / period + 1) * period
    } else {
        origin - ((origin - t - 1) / period) * period
    }
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
    /// Frames handed to the transport.
    pub tx_frames: u64,
    /// Failed sends.
    pub tx_errors: u64,
    /// Ticks on which the SLCAN peer had not opened the channel.
    pub tx_not_open: u64,
    /// Frames received (any ID).
    pub rx_frames: u64,
    /// Received frames rejected for a bad CRC.
    pub rx_crc_errors: u64,
    /// Received frames rejected for a bad alive counter.
    pub rx_counter_errors: u64,
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

    /// Open the transport and start the threads.
    pub fn start(&self) -> Result<()> {
        let _life = lock(&self.lifecycle);
        let mut run = lock(&self.run);
        if run.is_some() {
            return Err(Error::State("bridge is already running".into()));
        }
        // Fresh counters and receive state. The sequence number carries over;
        // the latest command only if it is recent (not older than hold_after),
        // so a command left from an earlier run never drives the actuators.
        let start_ns = monotonic_ns();
        let old = self.shared();
        let fresh = Shared::new(&self.cfg);
        {
            let slot = lock(&old.cmd);
            let mut new_slot = lock(&fresh.cmd);
            new_slot.cmd = slot.cmd.filter(|c| {
                c.received_ns.saturating_add(self.cfg.safety.hold_after_ns) >= start_ns
            });
            new_slot.last_seq = slot.last_seq;
        }
        let shared = Arc::new(fresh);
        *lock(&self.shared) = shared.clone();

        let opened = transport::open(&self.spec, self.cfg.bitrate)?;
        // Published only once the run is up, so a failed start leaves no
        // path to a pty that is already closed again.
        let pty_path = opened.pty_path.clone();
        let (log_tx, log_writer) = match &self.cfg.log_path {
            Some(p) => {
                let (s, w) = candump::start(
                    p,
                    self.spec.log_name(),
                    shared.log_dropped.clone(),
                    shared.log_errors.clone(),
                )?;
                (Some(s), Some(w))
            }
            None => (None, None),
        };
        let params = TxParams {
            period_ns: self.cfg.period_ns,
            safety: self.cfg.safety,
            stop_safe_frames: self.cfg.stop_safe_frames,
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

    /// Send the safe frames, stop the threads, close the transport. Does
    /// nothing if not running.
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

    /// Hand over the latest command (FL, FR, RL, RR in Nm). Refuses NaN/inf
    /// and a `seq` that is not newer than the last accepted one.
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
        let state_valid = self.latest_state().valid;
        let (tick, tx_frames, tx_errors, tx_not_open, mode, last_tx_error) = {
            let tx = lock(&sh.tx);
            (
                tx.tick.summary(),
                tx.tx_frames,
                tx.tx_errors,
                tx.tx_not_open,
                tx.mode,
                tx.last_error.clone(),
            )
        };
        let rx = lock(&sh.rx).clone();
        Stats {
            running,
            tick,
            tx_frames,
            tx_errors,
            tx_not_open,
            rx_frames: rx.rx_frames,
            rx_crc_errors: rx.rx_crc_errors,
            rx_counter_errors: rx.rx_counter_errors,
            rx_length_errors: rx.rx_length_errors,
            rx_malformed: rx.rx_malformed,
            rx_unknown_id: rx.rx_unknown_id,
            rx_transport_errors: rx.rx_transport_errors,
            bus_errors: rx.bus_errors,
            log_dropped: sh.log_dropped.load(Ordering::Relaxed),
            log_errors: sh.log_errors.load(Ordering::Relaxed),
            safety_state: mode,
            state_valid,
            last_tx_error,
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::codec::WHEEL_TORQUE_CMD;
    use std::cell::RefCell;
    use std::sync::atomic::AtomicU64;

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

    type Script<'a> = Box<dyn Fn(usize, &Shared, &FakeClock) + 'a>;

    /// Records frames; runs a script per tick (by tick number) that may set
    /// commands, request a stop, or burn time.
    struct ScriptSink<'a> {
        clock: &'a FakeClock,
        shared: &'a Shared,
        frames: RefCell<Vec<(u64, CanFrame)>>,
        script: Script<'a>,
        closed: bool,
    }

    // SAFETY: the test runs on one thread; the sink never crosses threads.
    unsafe impl Send for ScriptSink<'_> {}

    impl Sink for ScriptSink<'_> {
        fn send(&mut self, f: &CanFrame) -> Result<Sent> {
            let n = self.frames.borrow().len();
            self.frames.borrow_mut().push((self.clock.now_ns(), *f));
            (self.script)(n, self.shared, self.clock);
            Ok(Sent::Yes)
        }
        fn close(&mut self) {
            self.closed = true;
        }
    }

    fn params() -> TxParams {
        TxParams {
            period_ns: 50 * MS,
            safety: SafetyConfig {
                max_torque_nm: [100.0; 4],
                max_delta_nm_per_tick: 10.0,
                hold_after_ns: 120 * MS,
                safe_after_ns: 300 * MS,
                fault_after_ns: 1000 * MS,
            },
            stop_safe_frames: 3,
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

    /// Run the loop with a script; returns (frames, shared).
    fn run(
        late: impl Fn(u64) -> u64 + Send + 'static,
        script: impl Fn(usize, &Shared, &FakeClock),
    ) -> (Vec<(u64, CanFrame)>, Shared, bool) {
        let cfg = BridgeConfig::new("slcan-pty:");
        let shared = Shared::new(&cfg);
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
        run_tx(&clock, params(), &shared, &mut sink, None);
        let closed = sink.closed;
        let frames = std::mem::take(&mut *sink.frames.borrow_mut());
        drop(sink);
        (frames, shared, closed)
    }

    /// A controller that sends a fresh command every tick for 40 ticks, then
    /// goes silent; stop after tick 80.
    fn controller(n: usize, sh: &Shared, c: &FakeClock) {
        if n < 40 {
            let t = [55.0, -55.0, 5.25, 300.0];
            sh.set_command(t, n as u64 + 1, c.now_ns()).unwrap();
        }
        if n == 80 {
            sh.request_stop();
        }
    }

    #[test]
    fn ticks_on_absolute_deadlines_and_stops_with_safe_frames() {
        let (frames, shared, closed) = run(|k| (k % 7) * 100_000, controller);
        assert!(closed);
        // 81 ticks before the stop request is seen, then 3 safe frames.
        assert_eq!(frames.len(), 84);
        let origin = frames[0].0 - (frames[0].0 - 1_050 * MS);
        for (k, (t, _)) in frames.iter().enumerate() {
            let deadline = origin + k as u64 * 50 * MS;
            assert!(*t >= deadline && *t < deadline + MS, "tick {k} at {t}");
        }
        let decoded: Vec<_> = frames.iter().map(|(_, f)| decode(f)).collect();
        // Counters 0..14 wrap.
        for (k, d) in decoded.iter().enumerate() {
            assert_eq!(d.0 as usize, k % 15);
        }
        // First tick: command of tick 0 not yet there -> Safe.
        assert_eq!(decoded[0].1, Mode::Safe as u8);
        assert_eq!(decoded[1].1, Mode::Active as u8);
        assert_eq!(decoded[1].2, [10.0, -10.0, 5.0, 10.0]); // 5.25 rounds to 5.0 (0.5 Nm steps)
        assert_eq!(decoded[12].2, [55.0, -55.0, 5.0, 100.0]);
        // The last command is set during tick 39 and first seen by tick 40.
        // Age at tick 40+j is 50j ms: Active up to 120 ms, Hold to 300, Safe to 1000, then Fault.
        assert_eq!(decoded[42].1, Mode::Active as u8);
        assert_eq!(decoded[43].1, Mode::Hold as u8);
        assert_eq!(decoded[43].2, [55.0, -55.0, 5.0, 100.0]);
        assert_eq!(decoded[46].1, Mode::Hold as u8);
        assert_eq!(decoded[47].1, Mode::Safe as u8);
        assert_eq!(decoded[47].2, [0.0; 4]);
        assert_eq!(decoded[60].1, Mode::Safe as u8);
        assert_eq!(decoded[61].1, Mode::Fault as u8);
        assert_eq!(decoded[80].1, Mode::Fault as u8);
        // Stop frames: zero torque, a latched fault stays visible.
        for d in &decoded[81..] {
            assert_eq!(d.2, [0.0; 4]);
            assert_eq!(d.1, Mode::Fault as u8);
        }
        let s = lock(&shared.tx).tick.summary();
        assert_eq!(s.ticks, 84);
        assert_eq!(s.overruns, 0);
        assert!(s.lateness_max_us <= 600.0 + 1e-9);
        assert!(s.drift_us.unwrap().abs() < 1_000.0);
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
    fn overrun_skips_deadlines_instead_of_bursting() {
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
            },
        );
        let t: Vec<u64> = frames.iter().map(|x| x.0).collect();
        assert_eq!(t[6] - t[5], 150 * MS);
        assert_eq!(t[7] - t[6], 50 * MS);
        let s = lock(&shared.tx).tick.summary();
        assert_eq!(s.overruns, 1);
        assert_eq!(s.skipped_ticks, 2);
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
            },
        );
        let d: Vec<_> = frames.iter().map(|(_, f)| decode(f)).collect();
        assert_eq!(d[30].1, Mode::Fault as u8);
        assert_eq!(d[31].1, Mode::Safe as u8);
        assert_eq!(d[33].1, Mode::Safe as u8);
        assert_eq!(d[34].1, Mode::Active as u8);
        assert_eq!(d[34].2, [10.0; 4]);
        assert_eq!(d[37].1, Mode::Safe as u8);
    }

    #[test]
    fn reset_without_fault_keeps_the_output_and_the_rate_limit() {
        let (frames, ..) = run(
            |_| 0,
            |n, sh, c| {
                if n < 30 {
                    sh.set_command([100.0; 4], n as u64 + 1, c.now_ns())
                        .unwrap();
                }
                if n == 15 {
                    sh.request_reset(c.now_ns());
                }
                if n == 30 {
                    sh.request_stop();
                }
            },
        );
        let d: Vec<_> = frames.iter().map(|(_, f)| decode(f)).collect();
        for (k, dk) in d.iter().enumerate().take(31).skip(1) {
            assert_eq!(dk.1, Mode::Active as u8, "tick {k}: {dk:?}");
            let want = (10.0 * k as f64).min(100.0);
            assert_eq!(dk.2, [want; 4], "tick {k}");
        }
    }

    #[test]
    fn grid_quantisation() {
        assert_eq!(first_deadline_after(100, 100, 50), 150);
        assert_eq!(first_deadline_after(101, 100, 50), 150);
        assert_eq!(first_deadline_after(149, 100, 50), 150);
        assert_eq!(first_deadline_after(150, 100, 50), 200);
        assert_eq!(first_deadline_after(99, 100, 50), 100);
        assert_eq!(first_deadline_after(50, 100, 50), 100);
        assert_eq!(first_deadline_after(49, 100, 50), 50);
        assert_eq!(first_deadline_after(0, 100, 50), 50);
    }

    #[test]
    fn refuses_nan_and_stale_seq() {
        let sh = Shared::new(&BridgeConfig::new("slcan-pty:"));
        assert!(matches!(
            sh.set_command([f64::NAN, 0.0, 0.0, 0.0], 1, 0),
            Err(Error::Command(_))
        ));
        assert!(lock(&sh.cmd).cmd.is_none());
        sh.set_command([1.0; 4], 5, 0).unwrap();
        assert!(matches!(
            sh.set_command([1.0; 4], 5, 0),
            Err(Error::Command(_))
        ));
        assert!(matches!(
            sh.set_command([1.0; 4], 4, 0),
            Err(Error::Command(_))
        ));
        sh.set_command([2.0; 4], 6, 0).unwrap();
    }

    #[test]
    fn receive_checks_and_state_validity() {
        use crate::codec::{STEERING_STATE, VEHICLE_MOTION, WHEEL_SPEEDS};
        let mut rx = RxStore::new(2);
        let to = 250 * MS;
        let t = 10_000 * MS;
        assert!(!rx.state(t, to).valid);
        rx.on_frame(
            &VEHICLE_MOTION.encode(&[12.34, -0.5, 0.25], 0).unwrap(),
            t,
            to,
        );
        rx.on_frame(
            &WHEEL_SPEEDS.encode(&[40.1, 40.2, 40.3, 40.4], 0).unwrap(),
            t,
            to,
        );
        let s = rx.state(t, to);
        assert!(!s.valid);
        assert!(s.steering_angle_rad.is_none());
        rx.on_frame(&STEERING_STATE.encode(&[0.1234], 0).unwrap(), t + MS, to);
        let s = rx.state(t + 2 * MS, to);
        assert!(s.valid);
        assert!((s.long_speed_mps.unwrap() - 12.34).abs() < 1e-9);
        assert!((s.wheel_speeds_radps.unwrap()[3] - 40.4).abs() < 1e-9);
        assert!((s.steering_angle_rad.unwrap() - 0.1234).abs() < 1e-9);
        assert_eq!(s.age_ms, Some(2.0));
        // Bad CRC: rejected, value unchanged.
        let mut bad = VEHICLE_MOTION
            .encode(&[99.0, 0.0, 0.0], 1)
            .unwrap()
            .data()
            .to_vec();
        bad[0] ^= 1;
        rx.on_frame(&CanFrame::new(0x201, false, &bad).unwrap(), t + 3 * MS, to);
        assert_eq!(rx.rx_crc_errors, 1);
        // Repeated counter: rejected.
        rx.on_frame(
            &VEHICLE_MOTION.encode(&[99.0, 0.0, 0.0], 0).unwrap(),
            t + 3 * MS,
            to,
        );
        assert_eq!(rx.rx_counter_errors, 1);
        assert!((rx.state(t + 3 * MS, to).long_speed_mps.unwrap() - 12.34).abs() < 1e-9);
        // Wrong length, unknown id.
        rx.on_frame(&CanFrame::new(0x203, false, &[0; 8]).unwrap(), t, to);
        rx.on_frame(&CanFrame::new(0x555, false, &[0; 8]).unwrap(), t, to);
        assert_eq!(rx.rx_length_errors, 1);
        assert_eq!(rx.rx_unknown_id, 1);
        // Goes invalid when it stops arriving.
        assert!(!rx.state(t + 300 * MS, to).valid);
        // After a gap the counter resynchronises: any counter is accepted.
        rx.on_frame(
            &VEHICLE_MOTION.encode(&[1.0, 0.0, 0.0], 9).unwrap(),
            t + 600 * MS,
            to,
        );
        assert_eq!(rx.rx_counter_errors, 1);
        assert!((rx.state(t + 600 * MS, to).long_speed_mps.unwrap() - 1.0).abs() < 1e-9);
    }

    #[test]
    fn config_validation() {
        let mut c = BridgeConfig::new("slcan-pty:");
        assert!(c.validate().is_ok());
        c.period_ns = 0;
        assert!(matches!(c.validate(), Err(Error::Config(_))));
        let c = BridgeConfig::new("nope:");
        assert!(matches!(Bridge::new(c), Err(Error::Config(_))));
    }
}
