//! SLCAN over a byte stream: a serial adapter (host role) or a
//! pseudo-terminal on which the bridge plays the adapter (device role).
//!
//! **Whole lines or nothing.** Every write is one non-blocking `write` of a
//! whole line into a queue that the age rule keeps (nearly) empty, so the
//! kernel takes it whole; a line the kernel takes only in part is cut off by
//! flushing (pty) or by a CR before the next line (serial), never glued to
//! the next one (`test_f5_slcan_lines_stay_whole_when_the_pty_buffer_fills`).
//!
//! **Age rule, pty.** Before each frame, bytes the peer has not read since
//! the last tick (`FIONREAD` on the bridge's own slave handle; `TIOCOUTQ` on
//! a Linux pty master always reads 0) are discarded by reading them from that
//! handle (the line discipline serialises readers, so the bridge knows to the
//! byte where the peer stopped; `tcflush` races a peer that reads between the
//! count and the flush), so the peer never reads a frame older than one period
//! (`test_f1_no_stale_frame_reaches_a_pty_peer_after_a_stall`). A peer that
//! stopped part-way through a line (it reads byte by byte, as python-can's
//! slcan does, and can be preempted between two bytes) is no exception: the
//! rest of that line is flushed with everything behind it, and the line is
//! ended by its own remainder with its last data digit changed, so the peer
//! parses a frame that fails its CRC (python-can parses it without an
//! error) instead of gluing the head to the next line or completing a
//! frame a stall old (`test_tx_stall_*` in `tests/can_bridge`). The bridge
//! keeps the lines it wrote since the last flush to know where the peer is
//! (`Ledger`). Residual: a peer that stopped after a frame's last data digit
//! and before its CR completes that frame when it resumes (only the CR is
//! left to send). Replies to
//! the peer's commands are written only while its unread input is below
//! [`REPLY_ROOM`]; a peer flooding commands without reading the replies
//! costs dropped replies (counted), never a wait of the transmit thread.
//!
//! **Age rule, serial.** A real tty's `TIOCOUTQ` shows bytes not yet sent:
//! they are flushed (`TCOFLUSH`) and the next line starts with CR, so the
//! adapter discards a line cut by the flush. An adapter that acknowledges
//! frames (`z`/`Z`/CR, Lawicel) and has not acknowledged the last one gets no
//! new frame (it is probed with `V` instead), so after a stall it finds at
//! most the one frame in flight (`test_f1_no_stale_frames_from_a_stalled_serial_adapter`).
//! On start the adapter must answer `V` (version) within [`HANDSHAKE`], or
//! `start()` fails (`test_f8_slcan_without_an_adapter_is_refused_at_start`).

use super::fd::{make_raw, Fd};
use super::{out_queue, Gate, Health, Opened, Ready, RxItem, Sink, Source, Written};
use crate::channel::{baud_constant, slcan_bitrate_code};
use crate::error::{clip, Error, Result};
use crate::frame::CanFrame;
use crate::scheduler::monotonic_ns;
use crate::slcan::{self, parse_command, Cmd, Event};
use crate::sync;
use std::collections::VecDeque;
use std::ffi::CString;
use std::io;
use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// Most unread bytes the peer may have before a reply is dropped instead of
/// written (a line is at most 27 bytes; the pty's line discipline holds 4096).
pub const REPLY_ROOM: usize = 512;

/// Longest wait for the pty peer to finish a read in progress before its
/// unread bytes are taken ([`Port::take_unread`]).
const TAKE_BUDGET: Duration = Duration::from_micros(500);

/// How long the peer is watched for progress before its unread bytes are
/// taken ([`Port::settle`]), at most, and the step between two looks.
const SETTLE_BUDGET: Duration = Duration::from_millis(2);
const SETTLE_STEP: Duration = Duration::from_micros(100);

/// Longest wait at start for each handshake reply of a serial adapter.
pub const HANDSHAKE: Duration = Duration::from_millis(500);

/// Longest wait at close for the pty peer to read what was written (the
/// safe frames of `stop`): closing the master discards unread output.
const DRAIN_BUDGET: Duration = Duration::from_millis(200);

struct Port {
    fd: Fd,
    /// Serialises writes of the two threads so lines never interleave. Held
    /// only around one `ioctl` and one non-blocking `write`: the transmit
    /// thread never waits behind the receive thread for longer than that.
    write_lock: Mutex<()>,
    /// The transmit thread is waiting for `write_lock`: the receive thread
    /// lets it have the lock (drops a reply) rather than take it again, so a
    /// peer flooding commands cannot starve the tick by lock convoy.
    tx_waiting: AtomicBool,
    /// The lines written since the last flush (pty age rule: where the peer
    /// is, and how to end a line it is part-way through). Locked only under
    /// `write_lock`.
    ledger: Mutex<Ledger>,
    /// For a pty: our own handle on the slave, so the master never sees a
    /// hang-up while no peer is connected; also how we see unread output.
    slave_keeper: Option<Fd>,
    what: String,
}

/// Longest line the bridge writes (a leading CR, `T`, 8 digits of ID, the
/// DLC, 16 digits of data, CR: 28 bytes).
const MAX_LINE: usize = 40;

/// One line written to the pty.
#[derive(Clone, Copy, Debug)]
struct Line {
    bytes: [u8; MAX_LINE],
    len: usize,
    /// Where it ends, counted from the last flush.
    end: u64,
    /// A CAN frame (`t`/`T`), whose remainder is made to fail its CRC when
    /// the line is cut.
    frame: bool,
    /// It continues a line the peer had begun before a flush: the peer is
    /// inside a line at its start.
    continues: bool,
}

impl Line {
    fn new(bytes: &[u8], end: u64, continues: bool) -> Self {
        let len = bytes.len().min(MAX_LINE);
        let mut b = [0u8; MAX_LINE];
        b[..len].copy_from_slice(&bytes[..len]);
        let first = bytes.iter().find(|&&c| c != b'\r').copied();
        Line {
            bytes: b,
            len,
            end,
            frame: matches!(first, Some(b't' | b'T')),
            continues,
        }
    }

    fn bytes(&self) -> &[u8] {
        &self.bytes[..self.len]
    }
}

/// The lines written to the pty since the last flush.
#[derive(Debug, Default)]
struct Ledger {
    /// Bytes written since the last flush.
    total: u64,
    /// The lines the peer may not have read completely yet.
    lines: VecDeque<Line>,
    /// The end of the last line the peer has read completely.
    done: u64,
}

/// What the pty peer has left unread, in lines.
#[derive(Debug, PartialEq, Eq)]
enum Unread {
    /// Nothing (or not a pty).
    Nothing,
    /// Only whole lines: flushing them cuts none.
    WholeLines,
    /// The peer has read part of a line (or the head of one cut by an
    /// earlier flush): the bytes that end that line harmlessly once
    /// everything unread is flushed.
    MidLine(Vec<u8>),
}

/// The rest of a cut line as it is sent to end the peer's part of it: for a
/// frame's first cut, with its last data digit changed (the CRC then fails,
/// and the hex stays valid so a lenient parser reads a frame, not garbage);
/// a remainder that is only the CR is left as it is (the residual).
fn ending(rest: &[u8], corrupt: bool) -> Vec<u8> {
    let mut out = rest.to_vec();
    if corrupt {
        let term = out.iter().rposition(|&c| c != b'\r' && c != 0x07);
        if let Some(i) = term.filter(|&i| out[i].is_ascii_hexdigit()) {
            let v = (out[i] as char).to_digit(16).unwrap_or(0) ^ 0x8;
            out[i] = b"0123456789ABCDEF"[v as usize];
        }
    }
    out
}

fn cut() -> io::Error {
    io::Error::new(
        io::ErrorKind::WouldBlock,
        "output buffer full; the line was not written",
    )
}

impl Port {
    /// One non-blocking write of a whole line: `Ok(true)` written,
    /// `Ok(false)` nothing written (full), `Err` on a partial write.
    fn write_once(&self, bytes: &[u8]) -> io::Result<bool> {
        self.write_line(bytes, false)
    }

    /// [`Port::write_once`], recording the line in the ledger (`continues`:
    /// it ends a line the peer had begun before a flush).
    fn write_line(&self, bytes: &[u8], continues: bool) -> io::Result<bool> {
        loop {
            match self.fd.write(bytes) {
                Ok(n) if n == bytes.len() => {
                    let mut l = sync::lock(&self.ledger);
                    l.total += n as u64;
                    let end = l.total;
                    l.lines.push_back(Line::new(bytes, end, continues));
                    return Ok(true);
                }
                Ok(_) => return Err(cut()),
                Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => return Ok(false),
                Err(e) => return Err(e),
            }
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, ()> {
        sync::lock(&self.write_lock)
    }

    /// The transmit thread's lock: announced, so the receive thread yields it.
    fn lock_tx(&self) -> std::sync::MutexGuard<'_, ()> {
        self.tx_waiting.store(true, Ordering::Release);
        let g = self.lock();
        self.tx_waiting.store(false, Ordering::Release);
        g
    }

    /// Bytes written to a pty master that the peer has not read yet (the
    /// slave's input queue, `FIONREAD` on our slave handle).
    fn unread_by_peer(&self) -> Option<usize> {
        let keeper = self.slave_keeper.as_ref()?;
        let mut n: libc::c_int = 0;
        // SAFETY: FIONREAD writes one c_int to a valid pointer.
        let rc = unsafe { libc::ioctl(keeper.raw(), libc::FIONREAD, &mut n) };
        (rc == 0).then_some(n.max(0) as usize)
    }

    /// Discard what the pty peer has not read.
    fn flush_unread(&self) {
        if let Some(k) = &self.slave_keeper {
            // SAFETY: k is an open tty descriptor.
            unsafe { libc::tcflush(k.raw(), libc::TCIFLUSH) };
            *sync::lock(&self.ledger) = Ledger::default();
        }
    }

    /// Take what the pty peer has not read by reading it ourselves from the
    /// slave (call under the write lock): the line discipline serialises
    /// readers, so the bytes taken are exactly the tail the peer has not
    /// read, and the peer cannot read a byte between our count and our
    /// discard (as it can between `FIONREAD` and `tcflush`, which glued a
    /// byte of a flushed line to the next one). Reading until the queue is
    /// empty also takes bytes still on their way from the master: a read
    /// that finds nothing waits for the pty's pending buffer work first, so
    /// a line written a period ago that a starved kernel worker has not yet
    /// delivered (`FIONREAD` 0) is taken too, never left to arrive late.
    /// `None` if the peer holds the read lock for longer than
    /// [`TAKE_BUDGET`] (a read waiting for more bytes than are queued).
    fn take_unread(&self) -> Option<u64> {
        let keeper = self.slave_keeper.as_ref()?;
        let end = Instant::now() + TAKE_BUDGET;
        let mut taken = 0u64;
        let mut buf = [0u8; 4096];
        loop {
            match keeper.read(&mut buf) {
                Ok(0) => return Some(taken),
                Ok(n) => taken += n as u64,
                Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => {
                    // nothing left, or the peer is inside a read right now
                    if self.unread_by_peer().unwrap_or(0) == 0 {
                        return Some(taken);
                    }
                    if Instant::now() >= end {
                        return None;
                    }
                    std::thread::sleep(Duration::from_micros(20));
                }
                Err(_) => return None,
            }
        }
    }

    /// Wait (at most [`SETTLE_BUDGET`]) while the peer is visibly reading:
    /// a peer part-way through a line it is reading now finishes it, and
    /// what is discarded is what a stopped peer left.
    fn settle(&self, mut n: usize) {
        let end = Instant::now() + SETTLE_BUDGET;
        while n > 0 && Instant::now() < end {
            std::thread::sleep(SETTLE_STEP);
            let m = self.unread_by_peer().unwrap_or(0);
            if m >= n {
                break;
            }
            n = m;
        }
    }

    /// Discard what the pty peer has not read (call under the write lock)
    /// and say where that left the peer: at a line's end, or inside a line
    /// (with the bytes that end it harmlessly). The peer has consumed
    /// `total - taken` bytes of what was written since the last discard.
    fn discard_unread(&self) -> Unread {
        let Some(n) = self.unread_by_peer() else {
            return Unread::Nothing;
        };
        if n > 0 {
            self.settle(n);
        }
        let unread = match self.take_unread() {
            Some(m) => m,
            None => {
                let m = self.unread_by_peer().unwrap_or(n) as u64;
                if let Some(k) = &self.slave_keeper {
                    // SAFETY: k is an open tty descriptor.
                    unsafe { libc::tcflush(k.raw(), libc::TCIFLUSH) };
                }
                m
            }
        };
        if unread == 0 {
            *sync::lock(&self.ledger) = Ledger::default();
            return Unread::Nothing;
        }
        let mut l = sync::lock(&self.ledger);
        let consumed = l.total.saturating_sub(unread);
        while let Some(e) = l.lines.front().map(|x| x.end).filter(|&e| e <= consumed) {
            l.done = e;
            l.lines.pop_front();
        }
        let start = l.done;
        let out = match l.lines.front() {
            None => Unread::WholeLines,
            Some(front) if consumed == start && !front.continues => Unread::WholeLines,
            Some(front) => {
                let into = usize::try_from(consumed - start).unwrap_or(usize::MAX);
                let rest = front.bytes().get(into..).unwrap_or(&[]);
                Unread::MidLine(ending(rest, front.frame && !front.continues))
            }
        };
        *l = Ledger::default();
        drop(l);
        // Something to read at once: a reader that saw the discarded bytes
        // ready (select) and reads them a moment later must not find the
        // queue empty (pyserial raises on an empty read after a ready
        // select). An empty line at a line's end; the ending inside one.
        match &out {
            Unread::MidLine(end) => {
                let _ = self.write_line(end, true);
            }
            _ => {
                let _ = self.write_line(b"\r", false);
            }
        }
        out
    }

    /// Wait (at most `budget`) until the peer has read everything written to
    /// the pty. Requires two empty readings 2 ms apart, so bytes still on
    /// their way from the master to the slave's queue are not missed.
    fn drain(&self, budget: Duration) {
        let end = Instant::now() + budget;
        let mut empty = 0;
        while Instant::now() < end {
            match self.unread_by_peer() {
                None => return,
                Some(0) => {
                    empty += 1;
                    if empty >= 2 {
                        return;
                    }
                }
                Some(_) => empty = 0,
            }
            std::thread::sleep(Duration::from_millis(2));
        }
    }
}

/// The device role's channel state, set by the peer's `O`/`L`/`C`.
#[derive(Debug, Default)]
struct Channel {
    open: AtomicBool,
    listen_only: AtomicBool,
}

/// The host role's view of the adapter's acknowledgements.
#[derive(Debug)]
struct Acks {
    /// The adapter has answered a frame: it acknowledges (Lawicel `z`).
    known: AtomicBool,
    /// Replies owed: one per frame and per `V` probe written, counted before
    /// the write (the answer can be read before the writer runs again).
    owed: AtomicU32,
    /// When the last line that owes a reply was written (monotonic ns).
    sent_ns: AtomicU64,
    /// A reply's round trip, a decaying maximum (ns; `u64::MAX`: none yet).
    rtt_ns: AtomicU64,
    /// A frame has been written since the handshake.
    wrote: AtomicBool,
    /// Ticks held since the last frame waiting for an acknowledgement; a `V`
    /// probe goes out on the first and every [`REPROBE_TICKS`]th (a lost
    /// answer must not hold frames forever).
    held: AtomicU32,
}

/// See [`Acks::held`].
const REPROBE_TICKS: u32 = 5;

impl Default for Acks {
    fn default() -> Self {
        Acks {
            known: AtomicBool::new(false),
            owed: AtomicU32::new(0),
            sent_ns: AtomicU64::new(0),
            rtt_ns: AtomicU64::new(u64::MAX),
            wrote: AtomicBool::new(false),
            held: AtomicU32::new(0),
        }
    }
}

impl Acks {
    /// Count a reply owed, then write `bytes`; uncount it if nothing went out.
    fn write_owing(&self, port: &Port, bytes: &[u8]) -> io::Result<bool> {
        self.sent_ns.store(monotonic_ns(), Ordering::Release);
        self.owed.fetch_add(1, Ordering::AcqRel);
        let r = port.write_once(bytes);
        if !matches!(r, Ok(true)) {
            self.settle();
        }
        r
    }

    /// One reply fewer owed (never below zero); the round trip of the last
    /// line if it was the only one owed.
    fn settle(&self) -> u32 {
        self.owed
            .fetch_update(Ordering::AcqRel, Ordering::Acquire, |n| {
                Some(n.saturating_sub(1))
            })
            .unwrap_or(0)
    }
}

#[derive(Clone)]
enum Role {
    /// We are the adapter: frames go out only while the peer has the channel open.
    Device(Arc<Channel>),
    /// We drive an adapter.
    Host(Arc<Acks>),
}

struct SlcanSink {
    port: Arc<Port>,
    role: Role,
    /// Start the next line with CR: a cut line may be on the wire.
    need_cr: bool,
}

impl SlcanSink {
    fn write_frame(&mut self, line: &[u8]) -> Result<bool> {
        let mut buf = [0u8; 40];
        let mut n = 0;
        if self.need_cr {
            buf[0] = b'\r';
            n = 1;
        }
        let end = (n + line.len()).min(buf.len());
        buf[n..end].copy_from_slice(&line[..end - n]);
        match self.port.write_once(&buf[..end]) {
            Ok(w) => {
                if w {
                    self.need_cr = false;
                }
                Ok(w)
            }
            Err(e) => {
                self.need_cr = true;
                self.port.flush_unread();
                Err(Error::io(&format!("{} write", self.port.what), &e))
            }
        }
    }
}

impl Sink for SlcanSink {
    fn prepare(&mut self) -> Result<Ready> {
        match self.role.clone() {
            Role::Device(ch) => {
                if !ch.open.load(Ordering::Acquire) {
                    return Ok(Ready {
                        gate: Gate::NotOpen,
                        flushed: 0,
                    });
                }
                let port = self.port.clone();
                let _g = port.lock_tx();
                Ok(match self.port.discard_unread() {
                    Unread::Nothing => Ready::OPEN,
                    Unread::WholeLines => Ready {
                        gate: Gate::Open,
                        flushed: 1,
                    },
                    // The peer stopped inside a line a period ago: what it has
                    // not read goes, and the line ends with a remainder that
                    // fails its CRC, so the new frame starts a line of its own.
                    Unread::MidLine(_) => Ready {
                        gate: Gate::Open,
                        flushed: 1,
                    },
                })
            }
            Role::Host(acks) => {
                let port = self.port.clone();
                let _g = port.lock_tx();
                let mut flushed = 0;
                if out_queue(self.port.fd.raw()).is_some_and(|n| n > 0) {
                    // SAFETY: fd is an open tty.
                    unsafe { libc::tcflush(self.port.fd.raw(), libc::TCOFLUSH) };
                    self.need_cr = true;
                    flushed = 1;
                }
                if acks.known.load(Ordering::Acquire) && acks.owed.load(Ordering::Acquire) > 0 {
                    // The adapter has not answered the last frame or probe:
                    // do not queue a frame behind it; ask for a sign of life.
                    if acks.held.fetch_add(1, Ordering::AcqRel) % REPROBE_TICKS == 0 {
                        let _ = acks.write_owing(&self.port, b"V\r");
                    }
                    return Ok(Ready {
                        gate: Gate::Busy,
                        flushed,
                    });
                }
                Ok(Ready {
                    gate: Gate::Open,
                    flushed,
                })
            }
        }
    }

    fn write(&mut self, frame: &CanFrame) -> Result<Written> {
        let line = slcan::encode(frame);
        let port = self.port.clone();
        let _g = port.lock_tx();
        let role = self.role.clone();
        if let Role::Host(acks) = &role {
            acks.held.store(0, Ordering::Release);
            acks.sent_ns.store(monotonic_ns(), Ordering::Release);
            acks.owed.fetch_add(1, Ordering::AcqRel);
        }
        let ok = self.write_frame(line.as_bytes());
        if let Role::Host(acks) = &role {
            if matches!(ok, Ok(true)) {
                acks.wrote.store(true, Ordering::Release);
            } else {
                acks.settle();
            }
        }
        Ok(if ok? { Written::Yes } else { Written::Dropped })
    }

    /// An adapter that acknowledges frames gets a `V` probe ahead of each
    /// deadline (three measured round trips plus 1 ms, within 2 ms..half a
    /// period), and the frame only if it answers by the deadline: an
    /// adapter that stopped reading since the last tick gets no frame to
    /// hold (what it has taken cannot be flushed, and a pty standing in for
    /// an adapter hides even its queue from `TIOCOUTQ`).
    fn probe_lead_ns(&self, period_ns: u64) -> Option<u64> {
        let Role::Host(acks) = &self.role else {
            return None;
        };
        if !acks.known.load(Ordering::Acquire) {
            return None;
        }
        Some(super::probe_lead(
            acks.rtt_ns.load(Ordering::Acquire),
            period_ns,
        ))
    }

    fn probe(&mut self) {
        let Role::Host(acks) = self.role.clone() else {
            return;
        };
        if !acks.known.load(Ordering::Acquire) || acks.owed.load(Ordering::Acquire) > 0 {
            return;
        }
        let port = self.port.clone();
        let _g = port.lock_tx();
        let _ = acks.write_owing(&port, if self.need_cr { b"\rV\r" } else { b"V\r" });
    }

    fn close(&mut self) {
        match &self.role {
            Role::Host(_) => {
                let _g = self.port.lock();
                let _ = self
                    .port
                    .write_once(if self.need_cr { b"\rC\r" } else { b"C\r" });
            }
            // Closing the master discards what the peer has not read yet:
            // give a slow reader a bounded time to take the last (safe) frame.
            Role::Device(ch) => {
                if ch.open.load(Ordering::Acquire) {
                    self.port.drain(DRAIN_BUDGET);
                }
            }
        }
    }
}

struct SlcanSource {
    port: Arc<Port>,
    role: Role,
    health: Arc<Health>,
    dec: slcan::Decoder,
    pending: VecDeque<RxItem>,
}

impl SlcanSource {
    /// Reply to the peer without ever waiting: only while it reads, and
    /// never while the transmit thread waits for the port.
    fn reply(&self, bytes: &[u8]) {
        if self.port.tx_waiting.load(Ordering::Acquire) {
            self.health.replies_dropped.fetch_add(1, Ordering::Relaxed);
            return;
        }
        let _g = self.port.lock();
        let room = self
            .port
            .unread_by_peer()
            .is_some_and(|n| n + bytes.len() <= REPLY_ROOM);
        let ok = room && matches!(self.port.write_once(bytes), Ok(true));
        if !ok {
            self.health.replies_dropped.fetch_add(1, Ordering::Relaxed);
        }
    }

    fn handle(&mut self, ev: Event) {
        match (ev, &self.role) {
            (Event::Frame(f), Role::Host(_)) => self.pending.push_back(RxItem::Frame(f)),
            (Event::Frame(f), Role::Device(ch)) => {
                // A closed or listen-only channel does not transmit (Lawicel: BEL).
                if ch.open.load(Ordering::Acquire) && !ch.listen_only.load(Ordering::Acquire) {
                    self.pending.push_back(RxItem::Frame(f));
                } else {
                    self.reply(b"\x07");
                }
            }
            (Event::Malformed, Role::Device(_)) => {
                self.pending.push_back(RxItem::Malformed);
                self.reply(b"\x07");
            }
            (Event::Malformed, Role::Host(_)) => self.pending.push_back(RxItem::Malformed),
            (Event::Command(line), Role::Device(ch)) => {
                let reply: &[u8] = match parse_command(line.as_bytes()) {
                    Some(Cmd::Open) => {
                        ch.listen_only.store(false, Ordering::Release);
                        ch.open.store(true, Ordering::Release);
                        b"\r"
                    }
                    Some(Cmd::Listen) => {
                        ch.listen_only.store(true, Ordering::Release);
                        ch.open.store(true, Ordering::Release);
                        b"\r"
                    }
                    Some(Cmd::Close) => {
                        ch.open.store(false, Ordering::Release);
                        b"\r"
                    }
                    Some(Cmd::Version) => b"V1013\r",
                    Some(Cmd::Serial) => b"NCB01\r",
                    Some(Cmd::Flags) => b"F00\r",
                    Some(Cmd::Setting) => b"\r",
                    None => {
                        self.pending.push_back(RxItem::Malformed);
                        b"\x07"
                    }
                };
                self.reply(reply);
            }
            (Event::Bell, Role::Host(acks)) => {
                self.pending.push_back(RxItem::BusError);
                note_reply(acks);
            }
            (Event::TxAck | Event::Ok | Event::Command(_), Role::Host(acks)) => note_reply(acks),
            _ => {}
        }
    }

    fn idle(timeout_ms: i32) {
        std::thread::sleep(Duration::from_millis(timeout_ms.clamp(1, 100) as u64));
    }
}

fn note_reply(acks: &Acks) {
    if acks.wrote.load(Ordering::Acquire) {
        acks.known.store(true, Ordering::Release);
    }
    if acks.settle() == 1 {
        let rtt = monotonic_ns().saturating_sub(acks.sent_ns.load(Ordering::Acquire));
        let old = acks.rtt_ns.load(Ordering::Acquire);
        let decayed = if old == u64::MAX { 0 } else { old - old / 8 };
        acks.rtt_ns.store(rtt.max(decayed), Ordering::Release);
    }
}

impl Source for SlcanSource {
    fn recv(&mut self, timeout_ms: i32) -> Result<Option<RxItem>> {
        if let Some(x) = self.pending.pop_front() {
            return Ok(Some(x));
        }
        let is_pty = matches!(self.role, Role::Device(_));
        let rev = self
            .port
            .fd
            .poll(libc::POLLIN, timeout_ms)
            .map_err(|e| Error::io(&format!("{} poll", self.port.what), &e))?;
        if rev == 0 {
            return Ok(None);
        }
        if rev & libc::POLLIN == 0 {
            // Hang-up or error without data.
            if is_pty {
                Self::idle(timeout_ms);
                return Ok(None);
            }
            return Err(Error::Transport(format!("{} hung up", self.port.what)));
        }
        let mut buf = [0u8; 512];
        match self.port.fd.read(&mut buf) {
            Ok(0) => {
                Self::idle(timeout_ms);
                Ok(None)
            }
            Ok(n) => {
                let mut events: Vec<Event> = Vec::new();
                self.dec
                    .feed(buf.get(..n).unwrap_or(&[]), |e| events.push(e));
                for e in events {
                    self.handle(e);
                }
                Ok(self.pending.pop_front())
            }
            Err(e)
                if e.kind() == io::ErrorKind::WouldBlock
                    || e.kind() == io::ErrorKind::Interrupted =>
            {
                Ok(None)
            }
            Err(e) if is_pty && e.raw_os_error() == Some(libc::EIO) => {
                Self::idle(timeout_ms);
                Ok(None)
            }
            Err(e) => Err(Error::io(&format!("{} read", self.port.what), &e)),
        }
    }
}

fn cstring(path: &str) -> Result<CString> {
    CString::new(path)
        .map_err(|_| Error::Config(format!("path {} contains a NUL byte", clip(path))))
}

/// Create a pseudo-terminal; the bridge plays an SLCAN adapter on its master.
pub fn open_pty() -> Result<Opened> {
    // SAFETY: plain libc call.
    let m = Fd::new(unsafe { libc::posix_openpt(libc::O_RDWR | libc::O_NOCTTY | libc::O_CLOEXEC) })
        .map_err(|e| Error::io("posix_openpt", &e))?;
    // SAFETY: m is a pty master.
    if unsafe { libc::grantpt(m.raw()) } < 0 || unsafe { libc::unlockpt(m.raw()) } < 0 {
        return Err(Error::last_os("grantpt/unlockpt"));
    }
    let mut name = [0 as libc::c_char; 128];
    // SAFETY: name is writable for its length.
    let rc = unsafe { libc::ptsname_r(m.raw(), name.as_mut_ptr(), name.len()) };
    if rc != 0 {
        return Err(Error::io("ptsname_r", &io::Error::from_raw_os_error(rc)));
    }
    // SAFETY: ptsname_r wrote a NUL-terminated string into name.
    let path = unsafe { std::ffi::CStr::from_ptr(name.as_ptr()) }
        .to_string_lossy()
        .into_owned();
    m.set_nonblocking()
        .map_err(|e| Error::io("pty O_NONBLOCK", &e))?;
    let cpath = cstring(&path)?;
    // SAFETY: cpath is NUL-terminated.
    let keeper = Fd::new(unsafe {
        libc::open(
            cpath.as_ptr(),
            libc::O_RDWR | libc::O_NOCTTY | libc::O_NONBLOCK | libc::O_CLOEXEC,
        )
    })
    .map_err(|e| Error::io(&format!("open pty slave {path}"), &e))?;
    make_raw(&keeper, None).map_err(|e| Error::io("pty raw mode", &e))?;
    let port = Arc::new(Port {
        fd: m,
        write_lock: Mutex::new(()),
        tx_waiting: AtomicBool::new(false),
        ledger: Mutex::new(Ledger::default()),
        slave_keeper: Some(keeper),
        what: format!("slcan-pty {path}"),
    });
    let role = Role::Device(Arc::new(Channel::default()));
    let health = Arc::new(Health::default());
    Ok(Opened {
        sink: Box::new(SlcanSink {
            port: port.clone(),
            role: role.clone(),
            need_cr: false,
        }),
        source: Box::new(SlcanSource {
            port,
            role,
            health: health.clone(),
            dec: slcan::Decoder::default(),
            pending: VecDeque::new(),
        }),
        pty_path: Some(path),
        health,
    })
}

/// Read reply lines from the adapter until `want` returns true for one or
/// `budget` passes; returns the matching line, `Err(what it saw)` if not.
fn await_reply(
    fd: &Fd,
    dec: &mut slcan::Decoder,
    budget: Duration,
    mut want: impl FnMut(&Event) -> bool,
) -> std::result::Result<Event, Vec<Event>> {
    let end = Instant::now() + budget;
    let mut seen = Vec::new();
    loop {
        let left = end.saturating_duration_since(Instant::now());
        if left.is_zero() {
            return Err(seen);
        }
        let ms = left.as_millis().clamp(1, 50) as i32;
        if fd.poll(libc::POLLIN, ms).unwrap_or(0) & libc::POLLIN == 0 {
            continue;
        }
        let mut buf = [0u8; 256];
        let n = match fd.read(&mut buf) {
            Ok(n) => n,
            Err(_) => continue,
        };
        let mut found = None;
        dec.feed(buf.get(..n).unwrap_or(&[]), |e| {
            if found.is_none() && want(&e) {
                found = Some(e);
            } else if seen.len() < 16 {
                seen.push(e);
            }
        });
        if let Some(e) = found {
            return Ok(e);
        }
    }
}

/// Open an SLCAN serial adapter at `baud`: close its channel, ask for its
/// version (`V`, refused if silent), set the CAN bit rate and open the channel.
pub fn open_serial(path: &str, baud: u32, bitrate: u32) -> Result<Opened> {
    let shown = clip(path);
    let speed = baud_constant(baud)
        .ok_or_else(|| Error::Config(format!("unsupported serial speed {baud}")))?;
    let code = slcan_bitrate_code(bitrate).ok_or_else(|| {
        Error::Config(format!(
            "SLCAN supports bit rates 10k, 20k, 50k, 100k, 125k, 250k, 500k, 800k, 1M; got {bitrate}"
        ))
    })?;
    let cpath = cstring(path)?;
    // SAFETY: cpath is NUL-terminated.
    let fd = Fd::new(unsafe {
        libc::open(
            cpath.as_ptr(),
            libc::O_RDWR | libc::O_NOCTTY | libc::O_NONBLOCK | libc::O_CLOEXEC,
        )
    })
    .map_err(|e| Error::io(&format!("cannot open SLCAN device {shown}"), &e))?;
    make_raw(&fd, Some(speed))
        .map_err(|e| Error::io(&format!("{shown} is not a usable tty"), &e))?;
    // SAFETY: fd is a tty.
    unsafe {
        libc::tcflush(fd.raw(), libc::TCIOFLUSH);
    }
    let mut dec = slcan::Decoder::default();
    let send = |bytes: &[u8], step: &str| {
        fd.write_all_within(bytes, 100)
            .map_err(|e| Error::io(&format!("{shown}: sending {step}"), &e))
    };
    // A leading CR ends whatever half line an earlier user left behind.
    send(b"\rC\r", "C")?;
    std::thread::sleep(Duration::from_millis(20));
    // SAFETY: fd is a tty; the replies to CR and C are not needed.
    unsafe { libc::tcflush(fd.raw(), libc::TCIFLUSH) };
    send(b"V\r", "V")?;
    let is_version = |e: &Event| matches!(e, Event::Command(l) if l.as_bytes().first() == Some(&b'V') || l.as_bytes().first() == Some(&b'v'));
    await_reply(&fd, &mut dec, HANDSHAKE, is_version).map_err(|_| {
        Error::Transport(format!(
            "{shown}: no reply to the version query V within {} ms; is an SLCAN adapter connected?",
            HANDSHAKE.as_millis()
        ))
    })?;
    for step in [format!("S{code}"), "O".to_string()] {
        send(format!("{step}\r").as_bytes(), &step)?;
        let answer = |e: &Event| matches!(e, Event::Ok | Event::Bell | Event::TxAck);
        match await_reply(&fd, &mut dec, HANDSHAKE, answer) {
            Ok(Event::Bell) => {
                return Err(Error::Transport(format!(
                    "{shown}: the adapter refused {step} (BEL)"
                )))
            }
            Ok(_) => {}
            Err(_) => {
                return Err(Error::Transport(format!(
                    "{shown}: no reply to {step} within {} ms",
                    HANDSHAKE.as_millis()
                )))
            }
        }
    }
    let port = Arc::new(Port {
        fd,
        write_lock: Mutex::new(()),
        tx_waiting: AtomicBool::new(false),
        ledger: Mutex::new(Ledger::default()),
        slave_keeper: None,
        what: format!("slcan {shown}"),
    });
    let role = Role::Host(Arc::new(Acks::default()));
    let health = Arc::new(Health::default());
    Ok(Opened {
        sink: Box::new(SlcanSink {
            port: port.clone(),
            role: role.clone(),
            need_cr: false,
        }),
        source: Box::new(SlcanSource {
            port,
            role,
            health: health.clone(),
            dec,
            pending: VecDeque::new(),
        }),
        pty_path: None,
        health,
    })
}

#[cfg(test)]
mod tests {
    use super::super::Outcome;
    use super::*;

    fn open_slave(path: &str) -> Fd {
        let c = CString::new(path).unwrap();
        let fd = Fd::new(unsafe {
            libc::open(c.as_ptr(), libc::O_RDWR | libc::O_NOCTTY | libc::O_NONBLOCK)
        })
        .unwrap();
        make_raw(&fd, None).unwrap();
        fd
    }

    /// A pty with a peer that has sent `O` (open) and the source has seen it.
    fn opened_by_a_peer() -> (Box<dyn Sink>, Box<dyn Source>, Fd) {
        let Opened {
            sink,
            mut source,
            pty_path,
            ..
        } = open_pty().unwrap();
        let peer = open_slave(&pty_path.unwrap());
        peer.write(b"O\r").unwrap();
        for _ in 0..5 {
            let _ = source.recv(10).unwrap();
        }
        (sink, source, peer)
    }

    fn read_until(fd: &Fd, want: usize) -> Vec<u8> {
        let mut out = vec![];
        for _ in 0..100 {
            if out.len() >= want {
                break;
            }
            if fd.poll(libc::POLLIN, 20).unwrap() & libc::POLLIN != 0 {
                let mut b = [0u8; 256];
                if let Ok(n) = fd.read(&mut b) {
                    out.extend_from_slice(&b[..n]);
                }
            }
        }
        out
    }

    #[test]
    fn pty_device_role_gates_on_open_and_parses() {
        let Opened {
            mut sink,
            mut source,
            pty_path,
            ..
        } = open_pty().unwrap();
        let peer = open_slave(&pty_path.unwrap());
        let f = CanFrame::new(0x101, false, &[1, 2, 3]).unwrap();
        assert_eq!(sink.send(&f).unwrap(), Outcome::NOT_OPEN);
        peer.write(b"C\rS6\rO\rt2011AA\r").unwrap();
        let mut got = None;
        for _ in 0..50 {
            if let Some(x) = source.recv(20).unwrap() {
                got = Some(x);
                break;
            }
        }
        assert_eq!(
            got,
            Some(RxItem::Frame(CanFrame::new(0x201, false, &[0xAA]).unwrap()))
        );
        // Three CR replies for C, S6, O.
        assert_eq!(read_until(&peer, 3), b"\r\r\r");
        assert_eq!(sink.send(&f).unwrap(), Outcome::YES);
        assert_eq!(read_until(&peer, 12), b"t1013010203\r");
        // Garbage after C neither closes the channel nor goes unanswered.
        peer.write(b"Cxyz\r").unwrap();
        let _ = source.recv(20).unwrap();
        assert_eq!(read_until(&peer, 1), b"\x07");
        assert_eq!(sink.send(&f).unwrap(), Outcome::YES);
        assert_eq!(read_until(&peer, 12), b"t1013010203\r");
        peer.write(b"C\r").unwrap();
        for _ in 0..5 {
            let _ = source.recv(10).unwrap();
        }
        assert_eq!(sink.send(&f).unwrap(), Outcome::NOT_OPEN);
    }

    #[test]
    fn unread_frames_are_flushed_before_the_next_one() {
        let (mut sink, _source, peer) = opened_by_a_peer();
        assert_eq!(read_until(&peer, 1), b"\r");
        let a = CanFrame::new(0x101, false, &[1]).unwrap();
        let b = CanFrame::new(0x101, false, &[2]).unwrap();
        assert_eq!(sink.send(&a).unwrap(), Outcome::YES);
        std::thread::sleep(Duration::from_millis(5));
        let o = sink.send(&b).unwrap();
        assert_eq!((o.written, o.flushed), (Written::Yes, 1));
        // an empty line in place of what was discarded, then the new frame
        assert_eq!(read_until(&peer, 9), b"\rt101102\r");
    }

    /// Read exactly `n` bytes (or what arrives within about 2 s), never more.
    fn read_n(fd: &Fd, n: usize) -> Vec<u8> {
        let mut out = vec![];
        for _ in 0..100 {
            if out.len() >= n {
                break;
            }
            if fd.poll(libc::POLLIN, 20).unwrap() & libc::POLLIN != 0 {
                let mut b = [0u8; 256];
                if let Ok(k) = fd.read(&mut b[..n - out.len()]) {
                    out.extend_from_slice(&b[..k]);
                }
            }
        }
        out
    }

    #[test]
    fn a_line_the_peer_stopped_inside_ends_failing_its_crc() {
        // "t101101\r": the peer reads k bytes and stops for two ticks; then
        // it reads the rest of that line, ended by the bridge with its last
        // data digit changed (1 -> 9: the CRC fails), and only the newest
        // frame after it, never the frame it stopped in nor the one between.
        let a = CanFrame::new(0x101, false, &[1]).unwrap();
        let b = CanFrame::new(0x101, false, &[2]).unwrap();
        let c = CanFrame::new(0x101, false, &[3]).unwrap();
        let line = b"t101101\r";
        for k in 1..line.len() {
            let (mut sink, _source, peer) = opened_by_a_peer();
            assert_eq!(read_until(&peer, 1), b"\r");
            assert_eq!(sink.send(&a).unwrap(), Outcome::YES);
            std::thread::sleep(Duration::from_millis(5));
            assert_eq!(read_n(&peer, k), &line[..k]);
            for f in [&b, &c] {
                let o = sink.send(f).unwrap();
                assert_eq!((o.written, o.flushed), (Written::Yes, 1), "k = {k}");
                std::thread::sleep(Duration::from_millis(5));
            }
            let ended: &[u8] = if k + 1 < line.len() {
                b"t101109\r"
            } else {
                line
            };
            let want = [&ended[k..], b"t101103\r"].concat();
            assert_eq!(read_n(&peer, want.len()), want, "k = {k}");
            // the peer had the whole of it: the next frame goes out alone
            assert_eq!(sink.send(&a).unwrap(), Outcome::YES);
            assert_eq!(read_until(&peer, 8), line);
        }
    }

    #[test]
    fn a_peer_that_stops_again_inside_the_ending_gets_the_rest_of_it() {
        let (mut sink, _source, peer) = opened_by_a_peer();
        assert_eq!(read_until(&peer, 1), b"\r");
        let a = CanFrame::new(0x101, false, &[1]).unwrap();
        let b = CanFrame::new(0x101, false, &[2]).unwrap();
        let c = CanFrame::new(0x101, false, &[3]).unwrap();
        assert_eq!(sink.send(&a).unwrap(), Outcome::YES);
        std::thread::sleep(Duration::from_millis(5));
        assert_eq!(read_n(&peer, 3), b"t10");
        assert_eq!(sink.send(&b).unwrap().flushed, 1);
        std::thread::sleep(Duration::from_millis(5));
        assert_eq!(read_n(&peer, 2), b"11"); // into the ending "1109\r"
        assert_eq!(sink.send(&c).unwrap().flushed, 1);
        std::thread::sleep(Duration::from_millis(5));
        assert_eq!(read_n(&peer, 11), b"09\rt101103\r");
    }

    #[test]
    fn the_ending_keeps_hex_and_changes_the_last_data_digit() {
        assert_eq!(ending(b"018AB\r", true), b"018A3\r");
        assert_eq!(ending(b"0\r", true), b"8\r");
        assert_eq!(ending(b"\r", true), b"\r");
        assert_eq!(ending(b"V1013\r", false), b"V1013\r");
    }

    #[test]
    fn pty_close_waits_for_a_slow_peer_to_read_the_last_frame() {
        let (mut sink, source, peer) = opened_by_a_peer();
        assert_eq!(read_until(&peer, 1), b"\r");
        let f = CanFrame::new(0x101, false, &[0; 8]).unwrap();
        assert_eq!(sink.send(&f).unwrap(), Outcome::YES);
        // The peer reads only after 120 ms: after close() has begun.
        let reader = std::thread::spawn(move || {
            std::thread::sleep(Duration::from_millis(120));
            let mut out = vec![];
            let mut b = [0u8; 256];
            while let Ok(n) = peer.read(&mut b) {
                if n == 0 {
                    break;
                }
                out.extend_from_slice(&b[..n]);
            }
            out
        });
        let t0 = Instant::now();
        sink.close();
        drop(sink);
        drop(source); // the master closes here
        let waited = t0.elapsed();
        let got = reader.join().unwrap();
        let want: Vec<u8> = b"t1018"
            .iter()
            .chain(&[b'0'; 16])
            .chain(b"\r")
            .copied()
            .collect();
        assert_eq!(got, want, "waited {waited:?}");
        assert!(waited < Duration::from_millis(400), "waited {waited:?}");
    }

    #[test]
    fn pty_close_wait_is_bounded_without_a_reader() {
        let (mut sink, _source, peer) = opened_by_a_peer(); // the master stays open
        let f = CanFrame::new(0x101, false, &[0; 8]).unwrap();
        let _ = sink.send(&f).unwrap();
        let t0 = Instant::now();
        sink.close();
        let waited = t0.elapsed();
        assert!(
            waited >= Duration::from_millis(150) && waited < Duration::from_millis(400),
            "waited {waited:?}"
        );
        drop(peer);
    }

    /// A pty master playing the adapter: answers V, acknowledges frames with
    /// `z` while `ack` says so; returns every line it got.
    fn adapter(
        ack: Arc<AtomicBool>,
        stop: Arc<AtomicBool>,
    ) -> (String, std::thread::JoinHandle<Vec<Vec<u8>>>) {
        let m = Fd::new(unsafe { libc::posix_openpt(libc::O_RDWR | libc::O_NOCTTY) }).unwrap();
        unsafe {
            libc::grantpt(m.raw());
            libc::unlockpt(m.raw());
        }
        let mut name = [0 as libc::c_char; 128];
        unsafe { libc::ptsname_r(m.raw(), name.as_mut_ptr(), name.len()) };
        let slave = unsafe { std::ffi::CStr::from_ptr(name.as_ptr()) }
            .to_string_lossy()
            .into_owned();
        m.set_nonblocking().unwrap();
        make_raw(&m, None).unwrap();
        let h = std::thread::spawn(move || {
            let mut lines = vec![];
            let mut cur = vec![];
            while !stop.load(Ordering::SeqCst) {
                if !ack.load(Ordering::SeqCst) {
                    std::thread::sleep(Duration::from_millis(2));
                    continue;
                }
                if m.poll(libc::POLLIN, 10).unwrap_or(0) & libc::POLLIN == 0 {
                    continue;
                }
                let mut b = [0u8; 256];
                let Ok(n) = m.read(&mut b) else { continue };
                for &c in &b[..n] {
                    if c != b'\r' {
                        cur.push(c);
                        continue;
                    }
                    let reply: &[u8] = match cur.first() {
                        Some(b't') => b"z\r",
                        Some(b'V') => b"V1013\r",
                        _ => b"\r",
                    };
                    let _ = m.write(reply);
                    lines.push(std::mem::take(&mut cur));
                }
            }
            lines
        });
        (slave, h)
    }

    #[test]
    fn serial_host_role_handshakes_and_waits_for_acks() {
        let ack = Arc::new(AtomicBool::new(true));
        let stop = Arc::new(AtomicBool::new(false));
        let (slave, h) = adapter(ack.clone(), stop.clone());
        let Opened {
            mut sink,
            mut source,
            ..
        } = open_serial(&slave, 115_200, 500_000).unwrap();
        let f = CanFrame::new(0x7FF, false, &[]).unwrap();
        let pump = |source: &mut Box<dyn Source>| {
            for _ in 0..5 {
                let _ = source.recv(5);
            }
        };
        assert_eq!(sink.send(&f).unwrap(), Outcome::YES);
        pump(&mut source);
        assert_eq!(sink.send(&f).unwrap(), Outcome::YES);
        pump(&mut source);
        // The adapter stalls: no acknowledgement, so no new frame.
        ack.store(false, Ordering::SeqCst);
        std::thread::sleep(Duration::from_millis(20));
        assert_eq!(sink.send(&f).unwrap(), Outcome::YES);
        pump(&mut source);
        assert_eq!(sink.send(&f).unwrap().written, Written::Dropped);
        assert_eq!(sink.send(&f).unwrap().written, Written::Dropped);
        ack.store(true, Ordering::SeqCst);
        std::thread::sleep(Duration::from_millis(30));
        pump(&mut source);
        assert_eq!(sink.send(&f).unwrap(), Outcome::YES);
        sink.close();
        std::thread::sleep(Duration::from_millis(30));
        stop.store(true, Ordering::SeqCst);
        let lines = h.join().unwrap();
        let text: Vec<&[u8]> = lines.iter().map(|l| l.as_slice()).collect();
        assert_eq!(&text[..5], [&b""[..], b"C", b"V", b"S6", b"O"]);
        let frames = text.iter().filter(|l| l.starts_with(b"t")).count();
        assert_eq!(frames, 4);
        assert_eq!(text.last(), Some(&&b"C"[..]));
        assert!(open_serial(&slave, 115_200, 33_000).is_err());
        assert!(open_serial("/nonexistent/tty", 115_200, 500_000).is_err());
    }

    #[test]
    fn a_silent_serial_device_is_refused() {
        let ack = Arc::new(AtomicBool::new(false));
        let stop = Arc::new(AtomicBool::new(false));
        let (slave, h) = adapter(ack, stop.clone());
        let t0 = Instant::now();
        let e = open_serial(&slave, 115_200, 500_000).err().unwrap();
        assert!(
            e.to_string().contains("no reply to the version query"),
            "{e}"
        );
        assert!(t0.elapsed() < Duration::from_secs(2));
        stop.store(true, Ordering::SeqCst);
        h.join().unwrap();
    }
}
