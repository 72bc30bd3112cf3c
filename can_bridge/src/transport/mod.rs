//! Transports: each opens into a sending half (used by the tick thread), a
//! receiving half (used by the receive thread) and a [`Health`] both share.
//!
//! **The age rule.** A torque frame older than one period is never handed to
//! the bus: before each write the sink looks at what the previous writes
//! left behind (the pty slave's unread input, a tty's `TIOCOUTQ`, a socket's
//! `SIOCOUTQ`, or the peer's missing acknowledgement) and flushes it where
//! the kernel allows, or else does not add to it (`Written::Dropped`). Each
//! such frame is counted in `tx_stale_dropped`; a transport on which no
//! frame gets through for `transport_timeout_ms` is reported lost.
//!
//! Where a transport cannot keep the rule for an active frame (TCP cannot
//! take back bytes the server's kernel holds), its sink says so through
//! [`Sink::assurance`] and the bridge sends only safe frames on it.

pub mod fd;
pub mod slcan_stream;
pub mod socketcan;
pub mod socketcand;

use crate::channel::ChannelSpec;
use crate::error::Result;
use crate::frame::CanFrame;
use std::sync::atomic::{AtomicBool, AtomicU64};
use std::sync::Arc;

/// Whether this tick's frame was written.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Written {
    /// Handed to the transport.
    Yes,
    /// Not sent: the peer has not opened the channel (SLCAN device role).
    NotOpen,
    /// Not sent: the peer has not taken the previous frame, and adding this
    /// one would only queue it to arrive stale.
    Dropped,
}

/// Whether this tick's frame may be written, as the age rule decides before
/// the frame is built (so the limiter knows what the wire saw).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Gate {
    /// Write it.
    Open,
    /// The peer has not opened the channel (SLCAN device role).
    NotOpen,
    /// The peer has not taken the previous frame (or has not answered a
    /// probe): a new one would only queue behind it and arrive stale.
    Busy,
}

/// What [`Sink::prepare`] found before a tick's frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Ready {
    /// Whether the frame may be written.
    pub gate: Gate,
    /// The previous tick's frames flushed from the transport's queue for
    /// their age: they never reached the peer.
    pub flushed: u32,
}

impl Ready {
    /// Open, nothing flushed.
    pub const OPEN: Ready = Ready {
        gate: Gate::Open,
        flushed: 0,
    };
}

/// Whether the age rule holds on a transport for the frame about to be
/// written: only then may the frame be active (or hold a torque).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Assurance {
    /// The sink sees what the peer has taken and discards or withholds
    /// what it has not: any frame may go out.
    Holds,
    /// The peer gives no sign of what it has read (a socketcand server that
    /// has not answered an echo): a frame's age cannot be checked.
    Unverified,
    /// The transport cannot take back a frame its peer has not read yet (a
    /// TCP server that stops reading after its last answer still reads the
    /// frame when it resumes), and active frames were not allowed on it.
    Refused,
}

/// Outcome of a send that did not fail.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Outcome {
    /// This frame.
    pub written: Written,
    /// Earlier frames flushed from the transport's queue for their age.
    pub flushed: u32,
}

impl Outcome {
    /// Written, nothing flushed.
    pub const YES: Outcome = Outcome {
        written: Written::Yes,
        flushed: 0,
    };
    /// Not open.
    pub const NOT_OPEN: Outcome = Outcome {
        written: Written::NotOpen,
        flushed: 0,
    };
    /// This frame dropped.
    pub const DROPPED: Outcome = Outcome {
        written: Written::Dropped,
        flushed: 0,
    };
}

/// What the receive half delivers.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RxItem {
    /// A CAN frame.
    Frame(CanFrame),
    /// A line or message that could not be parsed.
    Malformed,
    /// A bus error report (SocketCAN error frame, SLCAN BEL).
    BusError,
}

/// Link state both halves share and `stats()` reads.
#[derive(Debug)]
pub struct Health {
    /// False while the link itself is broken (socketcand: connection lost,
    /// reconnecting): the transport is then lost at once.
    pub link_up: AtomicBool,
    /// Successful reconnections.
    pub reconnects: AtomicU64,
    /// Replies to an SLCAN peer dropped because it was not reading them.
    pub replies_dropped: AtomicU64,
}

impl Default for Health {
    fn default() -> Self {
        Health {
            link_up: AtomicBool::new(true),
            reconnects: AtomicU64::new(0),
            replies_dropped: AtomicU64::new(0),
        }
    }
}

/// Sending half, used once per tick in two steps: [`Sink::prepare`]
/// applies the age rule to what the previous writes left behind, then, if
/// it says so, [`Sink::write`] makes one non-blocking attempt with the frame
/// built in between. Neither ever waits.
pub trait Sink: Send {
    /// Before the tick's frame is built: flush what the peer has not taken
    /// since the last tick where the kernel allows it, and say whether a
    /// frame may go out now.
    fn prepare(&mut self) -> Result<Ready>;
    /// Write the tick's frame (after `prepare` said [`Gate::Open`]):
    /// [`Written::Yes`], or [`Written::Dropped`] if the kernel took none of it.
    fn write(&mut self, frame: &CanFrame) -> Result<Written>;
    /// How long before each deadline this sink wants [`Sink::probe`]
    /// called (a liveness probe whose answer gates the frame), if at all.
    fn probe_lead_ns(&self, _period_ns: u64) -> Option<u64> {
        None
    }
    /// Ask the peer for a sign of life ahead of the deadline.
    fn probe(&mut self) {}
    /// Whether the age rule holds for the next frame (asked after
    /// [`Sink::prepare`]); anything but [`Assurance::Holds`] makes the
    /// bridge send a safe frame instead of an active one.
    fn assurance(&self) -> Assurance {
        Assurance::Holds
    }
    /// `prepare` and `write` in one call (tests and tools).
    fn send(&mut self, frame: &CanFrame) -> Result<Outcome> {
        let r = self.prepare()?;
        let written = match r.gate {
            Gate::Open => self.write(frame)?,
            Gate::NotOpen => Written::NotOpen,
            Gate::Busy => Written::Dropped,
        };
        Ok(Outcome {
            written,
            flushed: r.flushed,
        })
    }
    /// Last words before the transport closes (e.g. SLCAN `C`).
    fn close(&mut self) {}
}

/// Receiving half.
pub trait Source: Send {
    /// Wait up to `timeout_ms` for the next item.
    fn recv(&mut self, timeout_ms: i32) -> Result<Option<RxItem>>;
}

/// An opened transport.
pub struct Opened {
    /// Sending half.
    pub sink: Box<dyn Sink>,
    /// Receiving half.
    pub source: Box<dyn Source>,
    /// Path of the pseudo-terminal slave for `slcan-pty:`.
    pub pty_path: Option<String>,
    /// Shared link state.
    pub health: Arc<Health>,
}

/// How a transport is opened, besides its channel string.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct OpenOptions {
    /// CAN bit rate requested from SLCAN adapters.
    pub bitrate: u32,
    /// Allow active frames over socketcand, accepting its residual (a
    /// server that stops reading right after answering its probe reads that
    /// one frame when it resumes; `docs/bus-safety.md`).
    pub socketcand_active: bool,
}

/// Open the transport a channel string names.
pub fn open(spec: &ChannelSpec, opts: OpenOptions) -> Result<Opened> {
    match spec {
        ChannelSpec::SocketCan { iface } => socketcan::open(iface),
        ChannelSpec::Slcan { path, baud } => slcan_stream::open_serial(path, *baud, opts.bitrate),
        ChannelSpec::SlcanPty => slcan_stream::open_pty(),
        ChannelSpec::Socketcand { host, port, bus } => {
            socketcand::open(host, *port, bus, opts.socketcand_active)
        }
    }
}

/// Lead of a liveness probe before a deadline: three measured round trips
/// (`rtt_ns`, `u64::MAX` while none is known) plus 1 ms, at least 2 ms, at
/// most half a period. A peer that stops reading within the lead before a
/// deadline can still find that one frame when it resumes; a longer lead
/// would widen that window, a shorter one hold frames back from a slow peer.
pub fn probe_lead(rtt_ns: u64, period_ns: u64) -> u64 {
    let half = period_ns / 2;
    if rtt_ns == u64::MAX {
        return half;
    }
    rtt_ns
        .saturating_mul(3)
        .saturating_add(1_000_000)
        .clamp(2_000_000u64.min(half), half)
}

/// Bytes queued for output on `fd` (`TIOCOUTQ`, which is `SIOCOUTQ` on a
/// socket: for TCP the bytes the peer has not acknowledged); `None` if the
/// descriptor cannot tell.
pub fn out_queue(fd: std::os::fd::RawFd) -> Option<usize> {
    let mut n: libc::c_int = 0;
    // SAFETY: TIOCOUTQ writes one c_int to a valid pointer.
    let rc = unsafe { libc::ioctl(fd, libc::TIOCOUTQ, &mut n) };
    (rc == 0).then_some(n.max(0) as usize)
}
