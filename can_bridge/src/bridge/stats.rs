//! What `stats()` reports: the transmit side's timing and counters, the
//! receive side's counters and the transport's health, read in one place.

use super::{lock, Bridge};
use crate::codec::Mode;
use crate::scheduler::{TickRecord, TickSummary};
use std::sync::atomic::Ordering;

use super::TransportState;

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
    /// Gaps in transmission (not open, a write error, the link down or
    /// lost) that restarted a non-zero output's ramp from zero.
    pub ramp_restarts: u64,
    /// Frames sent safe instead of active or hold because the transport
    /// cannot keep the age rule (socketcand without `socketcand_active`, or
    /// a server that does not answer echoes).
    pub tx_safe_only: u64,
    /// The last frame written went out under that rule.
    pub safe_only: bool,
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
    /// E2E-valid frames whose values are not physical (all kinds).
    pub rx_implausible: u64,
    /// ... of which a value changed faster than its signal's rate limit.
    pub rx_implausible_rate: u64,
    /// ... of which a brake-only wheel turned faster than the vehicle.
    pub rx_inconsistent: u64,
    /// E2E-valid frames in sequence whose counter steps claim more time
    /// than has passed since the last believed frame plus one cycle (a
    /// burst, or a sender faster than its cycle); not used.
    pub rx_faster_than_cycle: u64,
    /// Usable frames never believed: a second sender's sign (a repeated
    /// counter with other data, a jump, a restart) came before they had
    /// stood for the confirmation time.
    pub rx_discarded: u64,
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
    /// Log lines not written by the log's bounds: received frames over
    /// `log_rx_per_s`, and every line once the file holds `log_max_bytes`.
    pub log_suppressed: u64,
    /// The last write error of the log or its cap, naming the file.
    pub last_log_error: Option<String>,
    /// Mode of the last frame that reached the wire.
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

impl Bridge {
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
        let last_log_error = lock(&sh.log.last_error).clone();
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
            ramp_restarts: tx.ramp_restarts,
            tx_safe_only: tx.tx_safe_only,
            safe_only: tx.safe_only,
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
            rx_implausible_rate: rx.rx_implausible_rate,
            rx_inconsistent: rx.rx_inconsistent,
            rx_faster_than_cycle: rx.rx_faster_than_cycle,
            rx_discarded: rx.rx_discarded,
            rx_length_errors: rx.rx_length_errors,
            rx_malformed: rx.rx_malformed,
            rx_unknown_id: rx.rx_unknown_id,
            rx_transport_errors: rx.rx_transport_errors,
            bus_errors: rx.bus_errors,
            log_dropped: sh.log.dropped.load(Ordering::Relaxed),
            log_errors: sh.log.errors.load(Ordering::Relaxed),
            log_suppressed: sh.log.suppressed.load(Ordering::Relaxed),
            last_log_error,
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
}
