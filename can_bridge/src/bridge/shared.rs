//! The state shared by the transmit and receive threads and the caller, for
//! one run: the latest command (validated, limited and sequence-checked at
//! `set_command`), the reset and stop requests, and each side's counters.

use super::{lock, BridgeConfig, OnTransportLoss, RxStore, TxCounters};
use crate::candump::LogCounters;
use crate::error::{Error, Result};
use crate::safety::{Command, LimitRule, Safety, SafetyConfig, WHEELS};
use crate::transport::Health;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};

/// Largest accepted `seq` (exclusive) and the largest step between two
/// accepted ones: a caller cannot lock itself out by one huge value
/// (`test_f8_seq_cannot_lock_out_commands_and_restarts_with_the_run`).
pub const SEQ_LIMIT: u64 = 1 << 63;
/// See [`SEQ_LIMIT`].
pub const SEQ_MAX_STEP: u64 = 1 << 48;

#[derive(Debug, Default)]
pub(super) struct CmdSlot {
    pub(super) cmd: Option<Command>,
    /// The command before `cmd`: still in force at a deadline that `cmd`
    /// arrived after.
    pub(super) prev: Option<Command>,
    pub(super) last_seq: Option<u64>,
    pub(super) limit_events: u64,
    pub(super) last_limit_event: Option<String>,
}

/// State shared by the threads and the caller, for one run.
#[derive(Debug)]
pub struct Shared {
    pub(super) cmd: Mutex<CmdSlot>,
    pub(super) reset_at: Mutex<Option<u64>>,
    /// Commands are accepted only while this is set (start .. stop).
    pub(super) accepting: AtomicBool,
    pub(super) stop: AtomicBool,
    pub(super) lost: AtomicBool,
    pub(super) safety: SafetyConfig,
    pub(super) on_loss: OnTransportLoss,
    pub(super) tx: Mutex<TxCounters>,
    pub(super) rx: Mutex<RxStore>,
    pub(super) log: Arc<LogCounters>,
    pub(super) health: Mutex<Option<Arc<Health>>>,
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
            rx: Mutex::new(RxStore::new(cfg.rx_config())),
            log: Arc::new(LogCounters::default()),
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
        slot.prev = slot.cmd;
        slot.cmd = Some(Command {
            torques_nm: target,
            ..cmd
        });
        Ok(())
    }

    /// The command in force at `deadline`: the latest one that arrived by
    /// then. A command that arrives after a deadline (while its tick is
    /// being served) takes effect at the next one, so a frame depends on the
    /// commands and their arrival times only, not on when the thread woke.
    pub fn command_at(&self, deadline: u64) -> Option<Command> {
        let slot = lock(&self.cmd);
        match (slot.cmd, slot.prev) {
            (Some(c), _) if c.received_ns <= deadline => Some(c),
            (Some(_), Some(p)) => Some(p),
            (c, _) => c.filter(|c| c.received_ns <= deadline),
        }
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

#[cfg(test)]
mod tests {
    use super::super::testutil::config;
    use super::*;

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
}
