//! The transmit loop: one frame per absolute deadline, the watchdog and the
//! limiter, the age rule's outcome per tick and the transport's health.
//!
//! **Gaps restart the ramp.** The actuator applies 0 Nm once it has had no
//! frame for its timeout (`actuator_timeout_ms`, the contract
//! `ampc_jax.vehicle.actuators` and `vehicle.toml` share). The bridge knows
//! when the peer took a frame only at the next tick (the pty's unread
//! bytes, an echo or acknowledgement answered, the socket's queue empty),
//! and a frame written now may be read up to a period later (the age rule
//! discards it then); so it restarts the output from 0 Nm whenever the time
//! since the write of the last frame known taken, plus one period, reaches
//! the actuator's timeout: every frame the actuator may read after acting
//! on a gap is a ramp from zero (`test_tx_gap_*` in `tests/can_bridge`).

use super::{lock, Shared};
use crate::candump::{Dir, LogSender};
use crate::codec::{encode_torque_cmd, Mode};
use crate::e2e;
use crate::safety::{Safety, SafetyConfig};
use crate::scheduler::{realtime_ns, Clock, Schedule, TickRecord, TickStats};
use crate::transport::{Assurance, Gate, Health, Sink, Written};
use std::sync::atomic::Ordering;

/// State of the transport as the transmit thread sees it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TransportState {
    /// Frames reach the peer.
    Up,
    /// An SLCAN pty peer has not opened the channel (nothing to lose yet).
    NotOpen,
    /// Frames reach the peer, but it gives no sign of what it has read (a
    /// socketcand server that does not answer echoes): only safe frames go.
    Unverified,
    /// Nothing has reached the peer for `transport_timeout`, or the link broke.
    Lost,
}

impl TransportState {
    /// Name in `stats()`.
    pub fn name(self) -> &'static str {
        match self {
            TransportState::Up => "up",
            TransportState::NotOpen => "not_open",
            TransportState::Unverified => "unverified",
            TransportState::Lost => "lost",
        }
    }
}

/// Transmit-side counters.
#[derive(Debug)]
pub struct TxCounters {
    pub(super) tick: TickStats,
    pub(super) tx_frames: u64,
    pub(super) tx_errors: u64,
    pub(super) tx_not_open: u64,
    pub(super) tx_stale_dropped: u64,
    pub(super) send_max_ns: u64,
    pub(super) mode: Mode,
    pub(super) applied: [f64; 4],
    pub(super) rate_limited_ticks: u64,
    pub(super) ramp_restarts: u64,
    pub(super) tx_safe_only: u64,
    pub(super) safe_only: bool,
    pub(super) transport: TransportState,
    pub(super) transport_losses: u64,
    pub(super) last_error: Option<String>,
}

impl TxCounters {
    pub(super) fn new(period_ns: u64, trace: usize) -> Self {
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
            ramp_restarts: 0,
            tx_safe_only: 0,
            safe_only: false,
            transport: TransportState::NotOpen,
            transport_losses: 0,
            last_error: None,
        }
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
    /// The actuator applies 0 Nm after this long without a frame, ns: a gap
    /// that may reach it restarts the ramp.
    pub actuator_timeout_ns: u64,
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
    // The last tick put no frame on the wire because of a gap (not open, a
    // write error, the link down or lost, or silence the actuator may have
    // acted on).
    let mut in_gap = true;
    // Write time of the last frame whose fate is not known yet (taken or
    // flushed), and of the last frame known taken by the peer.
    let mut pending_ns: Option<u64> = None;
    let mut taken_ns = t0;
    loop {
        let deadline = sched.deadline();
        if let Some(lead) = sink.probe_lead_ns(p.period_ns) {
            clock.sleep_until_ns(deadline.saturating_sub(lead));
            sink.probe();
        }
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
        let before = clock.now_ns();
        let ready = sink.prepare();
        let link_up = health.is_none_or(|h| h.link_up.load(Ordering::Acquire));
        let flushed = ready.as_ref().map_or(0, |r| r.flushed);
        let gate = ready.as_ref().map(|r| r.gate);
        let assurance = sink.assurance();
        match (pending_ns, &ready) {
            (Some(_), Ok(r)) if r.flushed > 0 => pending_ns = None,
            (Some(w), Ok(r)) if r.gate == Gate::Open => {
                taken_ns = w;
                pending_ns = None;
            }
            _ => {}
        }
        // The frame written now may be read up to a period from now: if the
        // actuator's last frame may then be a timeout old, it may have
        // acted on the gap.
        let silent = before.saturating_sub(taken_ns) + p.period_ns >= p.actuator_timeout_ns;
        let mut tx = lock(&shared.tx);
        // A gap in transmission restarts the ramp from zero: the actuator
        // has seen nothing (a channel not open, a write error, a link down,
        // reconnecting or lost, or nothing taken for its timeout) and may
        // have timed out or been reset.
        let gap = silent
            || !link_up
            || state == TransportState::Lost
            || matches!(gate, Err(_) | Ok(Gate::NotOpen));
        if gap {
            if !in_gap && safety.output_steps() != [0; 4] {
                tx.ramp_restarts += 1;
            }
            safety.restart_output();
        }
        drop(tx);
        let cmd = shared
            .command_at(deadline)
            .filter(|c| c.received_ns >= stale_before);
        let seen = safety.output_steps();
        // Where the age rule cannot hold, only safe frames go out.
        let safe_only = assurance != Assurance::Holds;
        let mut replaced = false;
        let (mode, mut torques) = if stopping.is_some() {
            safety.stopping()
        } else if safe_only {
            let (m, t, would) = safety.step_safe_only(deadline, cmd.as_ref());
            replaced = matches!(would, Mode::Active | Mode::Hold);
            (m, t)
        } else {
            safety.step(deadline, cmd.as_ref())
        };
        if flushed > 0 && !gap {
            // The last frame was flushed unread (or read in the instant
            // before the flush): this tick repeats its output, one step from
            // either frame the peer may have last seen, and does not advance.
            safety.set_output_steps(seen);
            torques = safety.output();
        }
        let frame = encode_torque_cmd(&torques, mode, counter);
        let outcome = match (&ready, &frame) {
            (Err(e), _) | (Ok(_), Err(e)) => Err(e.clone()),
            (Ok(r), Ok(f)) => match r.gate {
                Gate::Open => sink.write(f),
                Gate::NotOpen => Ok(Written::NotOpen),
                Gate::Busy => Ok(Written::Dropped),
            },
        };
        let done = clock.now_ns();
        let written = matches!(outcome, Ok(Written::Yes));
        if written {
            pending_ns = Some(before);
        }
        if outcome.is_err() {
            safety.restart_output();
        } else if !written {
            safety.set_output_steps(seen);
        }
        in_gap = gap || outcome.is_err();
        if let Some(n) = stopping.as_mut() {
            if torques == [0.0; 4] || release_frames >= MAX_RELEASE_FRAMES {
                *n = n.saturating_sub(1);
            } else {
                release_frames += 1;
            }
        }
        let good = written && flushed == 0;
        let not_open = matches!(outcome, Ok(Written::NotOpen));
        if good && link_up {
            last_good = done;
        }
        let new_state = if !link_up
            || (!good && !not_open && done.saturating_sub(last_good) >= p.transport_timeout_ns)
        {
            TransportState::Lost
        } else if good && assurance == Assurance::Unverified {
            TransportState::Unverified
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
        tx.rate_limited_ticks = safety.rate_limited_ticks();
        if new_state == TransportState::Lost && state != TransportState::Lost {
            tx.transport_losses += 1;
        }
        state = new_state;
        tx.transport = state;
        shared
            .lost
            .store(state == TransportState::Lost, Ordering::Release);
        tx.tx_stale_dropped += u64::from(flushed);
        match outcome {
            Ok(Written::Yes) => {
                tx.tx_frames += 1;
                tx.applied = torques;
                tx.mode = mode;
                tx.safe_only = safe_only && stopping.is_none();
                tx.tx_safe_only += u64::from(replaced);
                counter = e2e::next_counter(counter);
                if let (Some(l), Ok(f)) = (log, &frame) {
                    l.log(realtime_ns(), f, Dir::Tx);
                }
            }
            Ok(Written::Dropped) => {
                tx.tx_stale_dropped += 1;
                counter = e2e::next_counter(counter);
            }
            Ok(Written::NotOpen) => tx.tx_not_open += 1,
            Err(e) => {
                tx.tx_errors += 1;
                counter = e2e::next_counter(counter);
                tx.last_error = Some(e.to_string());
            }
        }
    }
    sink.close();
}

#[cfg(test)]
mod tests {
    use super::super::testutil::{config, MS};
    use super::*;
    use crate::codec::WHEEL_TORQUE_CMD;
    use crate::error::Result;
    use crate::frame::CanFrame;
    use crate::transport::{Outcome, Ready};
    use std::cell::RefCell;
    use std::sync::atomic::AtomicU64;

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

    /// A scripted write error (the link broke): `prepare` fails.
    const FAIL: Outcome = Outcome {
        written: Written::NotOpen,
        flushed: u32::MAX,
    };

    /// Runs a script per tick (by tick number) that may set commands,
    /// request a stop, burn time, and says what the transport does with this
    /// tick's frame; records every frame written, with its tick.
    struct ScriptSink<'a> {
        clock: &'a FakeClock,
        shared: &'a Shared,
        frames: RefCell<Vec<(u64, CanFrame, Outcome)>>,
        ticks: Vec<usize>,
        tick: usize,
        current: Outcome,
        script: Script<'a>,
        closed: bool,
    }

    // SAFETY: the test runs on one thread; the sink never crosses threads.
    unsafe impl Send for ScriptSink<'_> {}

    impl Sink for ScriptSink<'_> {
        fn prepare(&mut self) -> Result<Ready> {
            let o = (self.script)(self.tick, self.shared, self.clock);
            self.tick += 1;
            self.current = o;
            if o == FAIL {
                return Err(crate::error::Error::Transport("scripted failure".into()));
            }
            let gate = match o.written {
                Written::Yes => Gate::Open,
                Written::NotOpen => Gate::NotOpen,
                Written::Dropped => Gate::Busy,
            };
            Ok(Ready {
                gate,
                flushed: o.flushed,
            })
        }
        fn write(&mut self, f: &CanFrame) -> Result<Written> {
            self.frames
                .borrow_mut()
                .push((self.clock.now_ns(), *f, self.current));
            self.ticks.push(self.tick - 1);
            Ok(Written::Yes)
        }
        fn close(&mut self) {
            self.closed = true;
        }
    }

    fn params() -> TxParams {
        let c = config();
        TxParams {
            period_ns: 50 * MS,
            safety: c.safety,
            stop_safe_frames: 3,
            transport_timeout_ns: 200 * MS,
            actuator_timeout_ns: 200 * MS,
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

    type Run = (Vec<(u64, CanFrame, Outcome)>, Shared, bool, Vec<usize>);

    /// Each tick's frame decoded, `None` where nothing was written.
    fn by_tick(
        frames: &[(u64, CanFrame, Outcome)],
        ticks: &[usize],
    ) -> Vec<Option<(u8, u8, [f64; 4])>> {
        let n = ticks.last().map_or(0, |t| t + 1);
        let mut out = vec![None; n];
        for ((_, f, _), t) in frames.iter().zip(ticks) {
            out[*t] = Some(decode(f));
        }
        out
    }

    /// Run the loop with a script; returns (frames written, shared, closed,
    /// the tick of each frame).
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
            ticks: vec![],
            tick: 0,
            current: Outcome::YES,
            script: Box::new(script),
            closed: false,
        };
        run_tx(&clock, params(), &shared, &mut sink, None, None);
        let closed = sink.closed;
        let frames = std::mem::take(&mut *sink.frames.borrow_mut());
        let ticks = std::mem::take(&mut sink.ticks);
        drop(sink);
        (frames, shared, closed, ticks)
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
        let (frames, shared, closed, _) = run(|k| (k % 7) * 100_000, controller);
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
        let (frames, shared, _, _) = run(
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
        let (frames, shared, _, ticks) = run(
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
        let d = by_tick(&frames, &ticks);
        // Ticks 15..24 put nothing on the wire; lost after 200 ms (4 ticks)
        // without a frame through; the first frame that gets through ramps
        // from 0 Nm at the rise rate.
        assert_eq!(d[14].unwrap().2[0], 100.0);
        assert!(d[15..25].iter().all(Option::is_none));
        assert_eq!(d[25].unwrap().2[0], 10.0);
        assert_eq!(d[26].unwrap().2[0], 20.0);
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
        assert_eq!(d[32].1, Mode::Safe as u8);
        // the command handed over at tick 33 (by its deadline) is in force there
        assert_eq!(d[33].1, Mode::Active as u8);
        assert_eq!(d[33].2, [10.0; 4]);
    }

    /// A fresh 100 Nm command every tick, the transport doing `what(n)`;
    /// stop after tick 30.
    fn held_at_100(what: impl Fn(usize) -> Outcome) -> Run {
        run(
            |_| 0,
            move |n, sh, c| {
                let _ = sh.set_command([100.0; 4], n as u64 + 1, c.now_ns());
                if n == 30 {
                    sh.request_stop();
                }
                what(n)
            },
        )
    }

    #[test]
    fn a_channel_that_opens_late_gets_a_ramp_from_zero() {
        // Rule: the limiter does not advance while nothing goes out.
        let (frames, shared, _, ticks) = held_at_100(|n| {
            if n < 10 {
                Outcome::NOT_OPEN
            } else {
                Outcome::YES
            }
        });
        let d = by_tick(&frames, &ticks);
        assert!(d[..10].iter().all(Option::is_none));
        assert_eq!(d[10].unwrap().1, Mode::Active as u8);
        assert_eq!(d[10].unwrap().2, [10.0; 4]);
        assert_eq!(d[11].unwrap().2, [20.0; 4]);
        let tx = lock(&shared.tx);
        assert_eq!(tx.tx_not_open, 10);
    }

    #[test]
    fn the_wire_state_is_what_the_wire_saw() {
        // While nothing goes out, the reported mode is that of the last
        // frame written (none yet: the initial safe), never "active".
        let shared = Shared::new(&config());
        shared.open_for_commands();
        let clock = FakeClock {
            now: AtomicU64::new(1_000 * MS),
            late: Box::new(|_| 0),
            wakes: AtomicU64::new(0),
        };
        let modes = RefCell::new(vec![]);
        let mut sink = ScriptSink {
            clock: &clock,
            shared: &shared,
            frames: RefCell::new(vec![]),
            ticks: vec![],
            tick: 0,
            current: Outcome::YES,
            script: Box::new(|n, sh: &Shared, c: &FakeClock| {
                let _ = sh.set_command([100.0; 4], n as u64 + 1, c.now_ns());
                let t = lock(&sh.tx);
                modes.borrow_mut().push((t.mode, t.transport, t.applied));
                drop(t);
                if n == 12 {
                    sh.request_stop();
                }
                if n < 8 {
                    Outcome::NOT_OPEN
                } else {
                    Outcome::YES
                }
            }),
            closed: false,
        };
        run_tx(&clock, params(), &shared, &mut sink, None, None);
        drop(sink);
        let m = modes.into_inner();
        // read at the start of each tick: what the ticks before it left
        for (mode, transport, applied) in &m[1..8] {
            assert_eq!(*mode, Mode::Safe);
            assert_eq!(*transport, TransportState::NotOpen);
            assert_eq!(*applied, [0.0; 4]);
        }
        assert_eq!(m[9].0, Mode::Active);
        assert_eq!(m[9].2, [10.0; 4]);
    }

    #[test]
    fn a_reopened_channel_gets_a_ramp_from_zero() {
        let (frames, shared, _, ticks) = held_at_100(|n| {
            if (15..20).contains(&n) {
                Outcome::NOT_OPEN
            } else {
                Outcome::YES
            }
        });
        let d = by_tick(&frames, &ticks);
        assert_eq!(d[14].unwrap().2, [100.0; 4]);
        assert_eq!(d[20].unwrap().2, [10.0; 4]);
        assert_eq!(lock(&shared.tx).ramp_restarts, 1);
    }

    #[test]
    fn a_frame_flushed_unread_does_not_advance_the_ramp() {
        // Tick 5 finds tick 4's frame (50 Nm) unread and flushes it: the peer
        // last saw 40 Nm, or 50 if it read the frame in the instant before
        // the flush; tick 5 repeats 50 Nm, one step from either.
        let (frames, shared, _, ticks) = held_at_100(|n| {
            if n == 5 {
                Outcome {
                    written: Written::Yes,
                    flushed: 1,
                }
            } else {
                Outcome::YES
            }
        });
        let d = by_tick(&frames, &ticks);
        let t = |k: usize| d[k].unwrap().2[0];
        assert_eq!((t(3), t(4), t(5), t(6)), (40.0, 50.0, 50.0, 60.0));
        assert_eq!(lock(&shared.tx).tx_stale_dropped, 1);
    }

    #[test]
    fn a_frame_held_back_by_the_age_rule_does_not_advance_the_ramp() {
        let (frames, _, _, ticks) = held_at_100(|n| {
            if n == 5 {
                Outcome::DROPPED
            } else {
                Outcome::YES
            }
        });
        let d = by_tick(&frames, &ticks);
        assert!(d[5].is_none());
        assert_eq!((d[4].unwrap().2[0], d[6].unwrap().2[0]), (50.0, 60.0));
    }

    #[test]
    fn a_gap_the_actuator_may_have_acted_on_restarts_the_ramp() {
        // The actuator times out after 200 ms (four periods). Frames the peer
        // never took (flushed unread at the next tick, or held back) leave a
        // gap; a frame written now may be read a period later. One frame
        // lost: the gap can reach 150 ms, the ramp goes on; two in a row: it
        // can reach 200 ms, the ramp restarts from zero.
        let flushed = Outcome {
            written: Written::Yes,
            flushed: 1,
        };
        for (lost, what) in [
            (1, flushed),
            (2, flushed),
            (3, flushed),
            (2, Outcome::DROPPED),
        ] {
            let (frames, shared, _, ticks) = held_at_100(move |n| {
                if (10..10 + lost).contains(&n) {
                    what
                } else {
                    Outcome::YES
                }
            });
            let d = by_tick(&frames, &ticks);
            let t = |k: usize| d[k].map(|x| x.2[0]);
            assert_eq!(t(9), Some(100.0));
            let restarts = lock(&shared.tx).ramp_restarts;
            if lost == 1 {
                assert_eq!((t(10), t(11)), (Some(100.0), Some(100.0)));
                assert_eq!(restarts, 0);
            } else {
                // the first frame the actuator may read after the gap
                let k = if what == flushed { 11 } else { 12 };
                assert_eq!(t(k), Some(10.0), "{lost} {what:?}: {d:?}");
                assert_eq!(restarts, 1);
            }
        }
    }

    #[test]
    fn a_write_error_restarts_the_ramp_from_zero() {
        let (frames, shared, _, ticks) = held_at_100(|n| if n == 12 { FAIL } else { Outcome::YES });
        let d = by_tick(&frames, &ticks);
        assert_eq!(d[11].unwrap().2, [100.0; 4]);
        assert!(d[12].is_none());
        assert_eq!(d[13].unwrap().2, [10.0; 4]);
        let tx = lock(&shared.tx);
        assert_eq!((tx.tx_errors, tx.ramp_restarts), (1, 1));
    }

    use crate::test_support::cases;
    use proptest::prelude::*;

    fn arb_outcome() -> impl Strategy<Value = Outcome> {
        prop_oneof![
            6 => Just(Outcome::YES),
            1 => Just(Outcome { written: Written::Yes, flushed: 1 }),
            1 => Just(Outcome::DROPPED),
            1 => Just(Outcome::NOT_OPEN),
            1 => Just(FAIL),
        ]
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(cases(300)))]

        /// Whatever the transport does, the sequence the wire saw (frames
        /// written, less those flushed unread) moves by at most one step a
        /// frame (rise/release 10 Nm, the safe release 20 Nm), or restarts
        /// within one rise step of zero after a gap; the frame after a flush
        /// is within a step of the flushed frame too (the peer may have read
        /// it in the instant before the flush).
        #[test]
        fn the_wire_only_ever_sees_ramps(
            ticks in proptest::collection::vec((arb_outcome(), proptest::array::uniform4(-150.0f64..150.0), any::<bool>()), 5..80),
        ) {
            let n = ticks.len();
            let plan = ticks.clone();
            let (frames, _, _, at) = run(
                |_| 0,
                move |k, sh, c| {
                    let (o, t, fresh) = plan.get(k).copied().unwrap_or((Outcome::YES, [0.0; 4], false));
                    if fresh {
                        let _ = sh.set_command(t, k as u64 + 1, c.now_ns());
                    }
                    if k + 1 == n {
                        sh.request_stop();
                    }
                    o
                },
            );
            // A flush retracts the last frame written, once.
            let mut wire: Vec<[f64; 4]> = vec![[0.0; 4]];
            let mut retractable = false;
            for ((_, f, o), k) in frames.iter().zip(&at) {
                let v = decode(f).2;
                let mut before = vec![];
                if o.flushed > 0 && retractable {
                    before.extend(wire.pop());
                }
                before.push(*wire.last().unwrap_or(&[0.0; 4]));
                for prev in before {
                    for (a, b) in prev.iter().zip(&v) {
                        prop_assert!((b - a).abs() <= 20.0 + 1e-9 || b.abs() <= 10.0 + 1e-9,
                            "tick {k}: {prev:?} -> {v:?}");
                    }
                }
                wire.push(v);
                retractable = true;
            }
        }
    }
}
