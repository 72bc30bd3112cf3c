//! Transports: each opens into a sending half (used by the tick thread) and a
//! receiving half (used by the receive thread).

pub mod fd;
pub mod slcan_stream;
pub mod socketcan;
pub mod socketcand;

use crate::channel::ChannelSpec;
use crate::error::Result;
use crate::frame::CanFrame;

/// Outcome of a send that did not fail.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Sent {
    /// Handed to the transport.
    Yes,
    /// Not sent: the peer has not opened the channel (SLCAN device role).
    NotOpen,
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

/// Sending half. `send` must not block for longer than a few milliseconds.
pub trait Sink: Send {
    /// Send one frame.
    fn send(&mut self, frame: &CanFrame) -> Result<Sent>;
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
}

/// Open the transport a channel string names. `bitrate` is the CAN bit rate
/// requested from SLCAN adapters.
pub fn open(spec: &ChannelSpec, bitrate: u32) -> Result<Opened> {
    match spec {
        ChannelSpec::SocketCan { iface } => socketcan::open(iface),
        ChannelSpec::Slcan { path, baud } => slcan_stream::open_serial(path, *baud, bitrate),
        ChannelSpec::SlcanPty => slcan_stream::open_pty(),
        ChannelSpec::Socketcand { host, port, bus } => socketcand::open(host, *port, bus),
    }
}
