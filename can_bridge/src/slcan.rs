//! SLCAN (Lawicel ASCII) encoder and a streaming decoder that never panics,
//! bounds its memory, and resynchronises on the next CR after garbage.

use crate::frame::CanFrame;

/// Longest line kept (`T` + 8 + 1 + 16 + 4 timestamp = 30); longer lines are dropped.
pub const MAX_LINE: usize = 40;

const HEX: &[u8; 16] = b"0123456789ABCDEF";

/// An encoded line, at most 27 bytes with the CR.
#[derive(Clone, Copy, Debug)]
pub struct Line {
    buf: [u8; 32],
    len: usize,
}

impl Line {
    /// The bytes to write.
    pub fn as_bytes(&self) -> &[u8] {
        &self.buf[..self.len]
    }
    fn push(&mut self, b: u8) {
        if let Some(slot) = self.buf.get_mut(self.len) {
            *slot = b;
            self.len += 1;
        }
    }
    fn push_hex(&mut self, value: u32, digits: u32) {
        for i in (0..digits).rev() {
            self.push(HEX[((value >> (4 * i)) & 0xF) as usize]);
        }
    }
}

/// Encode a frame as an SLCAN line (upper-case hex, CR-terminated).
pub fn encode(frame: &CanFrame) -> Line {
    let mut l = Line {
        buf: [0; 32],
        len: 0,
    };
    let kind = match (frame.is_extended(), frame.is_remote()) {
        (false, false) => b't',
        (true, false) => b'T',
        (false, true) => b'r',
        (true, true) => b'R',
    };
    l.push(kind);
    l.push_hex(frame.id(), if frame.is_extended() { 8 } else { 3 });
    l.push(b'0' + frame.len() as u8);
    for &b in frame.data() {
        l.push_hex(u32::from(b), 2);
    }
    l.push(b'\r');
    l
}

/// A command or reply line that is not a frame (e.g. `O`, `S6`, `V1013`),
/// kept whole so each role can check it exactly.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct CmdLine {
    buf: [u8; MAX_LINE],
    len: usize,
}

impl CmdLine {
    fn new(line: &[u8]) -> Self {
        let mut buf = [0u8; MAX_LINE];
        let len = line.len().min(MAX_LINE);
        buf[..len].copy_from_slice(&line[..len]);
        CmdLine { buf, len }
    }

    /// The line without its terminator.
    pub fn as_bytes(&self) -> &[u8] {
        &self.buf[..self.len]
    }
}

/// A command a host may send to an adapter (the device role's view).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Cmd {
    /// `O`: open the channel.
    Open,
    /// `L`: open listen-only (the host will not transmit).
    Listen,
    /// `C`: close the channel.
    Close,
    /// `V`: hardware/firmware version.
    Version,
    /// `N`: serial number.
    Serial,
    /// `F`: status flags.
    Flags,
    /// `S0`..`S8`, `sxxxx`, `Z0`/`Z1`, `Mxxxxxxxx`, `mxxxxxxxx`: a setting.
    Setting,
}

/// A command line parsed exactly: `Cxyz-garbage` is not `C`.
pub fn parse_command(line: &[u8]) -> Option<Cmd> {
    let hex = |d: &[u8], n: usize| d.len() == n && d.iter().all(|b| hex_val(*b).is_some());
    Some(match line {
        b"O" => Cmd::Open,
        b"L" => Cmd::Listen,
        b"C" => Cmd::Close,
        b"V" => Cmd::Version,
        b"N" => Cmd::Serial,
        b"F" => Cmd::Flags,
        [b'S', b'0'..=b'8'] | [b'Z', b'0' | b'1'] => Cmd::Setting,
        [b's', rest @ ..] if hex(rest, 4) => Cmd::Setting,
        [b'M' | b'm', rest @ ..] if hex(rest, 8) => Cmd::Setting,
        _ => return None,
    })
}

/// What one complete line means.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Event {
    /// A data or remote frame.
    Frame(CanFrame),
    /// A line starting with a letter that is not a frame: a command (device
    /// role) or a reply such as `V1013` (host role).
    Command(CmdLine),
    /// `z`/`Z`: transmit acknowledgement from an adapter.
    TxAck,
    /// An empty line: an adapter's OK reply.
    Ok,
    /// BEL: an adapter's error reply.
    Bell,
    /// A line that is neither: malformed frame, overlong, or unknown.
    Malformed,
}

/// Streaming decoder: feed bytes in any split, get events.
#[derive(Clone, Debug)]
pub struct Decoder {
    buf: [u8; MAX_LINE],
    len: usize,
    overflow: bool,
}

impl Default for Decoder {
    fn default() -> Self {
        Decoder {
            buf: [0; MAX_LINE],
            len: 0,
            overflow: false,
        }
    }
}

fn hex_val(b: u8) -> Option<u32> {
    match b {
        b'0'..=b'9' => Some(u32::from(b - b'0')),
        b'a'..=b'f' => Some(u32::from(b - b'a' + 10)),
        b'A'..=b'F' => Some(u32::from(b - b'A' + 10)),
        _ => None,
    }
}

fn hex_num(digits: &[u8]) -> Option<u32> {
    digits
        .iter()
        .try_fold(0u32, |acc, &d| Some((acc << 4) | hex_val(d)?))
}

/// Parse one line without its terminator.
pub fn parse_line(line: &[u8]) -> Event {
    let Some((&first, rest)) = line.split_first() else {
        return Event::Ok;
    };
    let (id_digits, extended, remote) = match first {
        b't' => (3, false, false),
        b'T' => (8, true, false),
        b'r' => (3, false, true),
        b'R' => (8, true, true),
        b'z' | b'Z' if rest.is_empty() => return Event::TxAck,
        b'A'..=b'Z' | b'a'..=b'z' => return Event::Command(CmdLine::new(line)),
        _ => return Event::Malformed,
    };
    parse_frame(rest, id_digits, extended, remote).map_or(Event::Malformed, Event::Frame)
}

fn parse_frame(rest: &[u8], id_digits: usize, extended: bool, remote: bool) -> Option<CanFrame> {
    let id = hex_num(rest.get(..id_digits)?)?;
    let dlc_byte = *rest.get(id_digits)?;
    let dlc = match dlc_byte {
        b'0'..=b'8' => usize::from(dlc_byte - b'0'),
        _ => return None,
    };
    let body = rest.get(id_digits + 1..)?;
    let data_digits = if remote { 0 } else { 2 * dlc };
    // Optional 4-digit timestamp after the data.
    if body.len() != data_digits && body.len() != data_digits + 4 {
        return None;
    }
    if body.len() == data_digits + 4 {
        hex_num(body.get(data_digits..)?)?;
    }
    if remote {
        return CanFrame::remote(id, extended, dlc as u8).ok();
    }
    let mut data = [0u8; 8];
    for (i, slot) in data.iter_mut().enumerate().take(dlc) {
        *slot = hex_num(body.get(2 * i..2 * i + 2)?)? as u8;
    }
    CanFrame::new(id, extended, &data[..dlc]).ok()
}

impl Decoder {
    /// Feed bytes; `on_event` is called once per complete line (CR or LF
    /// terminated) and per BEL.
    pub fn feed(&mut self, bytes: &[u8], mut on_event: impl FnMut(Event)) {
        for &b in bytes {
            match b {
                b'\r' | b'\n' => {
                    if self.overflow {
                        on_event(Event::Malformed);
                    } else if self.len > 0 || b == b'\r' {
                        on_event(parse_line(&self.buf[..self.len]));
                    }
                    self.len = 0;
                    self.overflow = false;
                }
                0x07 if self.len == 0 && !self.overflow => on_event(Event::Bell),
                _ => {
                    if self.overflow {
                        continue;
                    }
                    match self.buf.get_mut(self.len) {
                        Some(slot) => {
                            *slot = b;
                            self.len += 1;
                        }
                        None => self.overflow = true,
                    }
                }
            }
        }
    }

    /// Bytes of an incomplete line held.
    pub fn pending(&self) -> usize {
        self.len
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_support::{any_frame, cases, feed_in_pieces};
    use proptest::prelude::*;

    fn events(d: &mut Decoder, bytes: &[u8]) -> Vec<Event> {
        let mut v = vec![];
        d.feed(bytes, |e| v.push(e));
        v
    }

    #[test]
    fn encodes_like_the_spec() {
        let f = CanFrame::new(0x123, false, &[0xDE, 0xAD, 0xBE, 0xEF]).unwrap();
        assert_eq!(encode(&f).as_bytes(), b"t1234DEADBEEF\r");
        let f = CanFrame::new(0x1234567, true, &[]).unwrap();
        assert_eq!(encode(&f).as_bytes(), b"T012345670\r");
        let f = CanFrame::remote(0x7FF, false, 2).unwrap();
        assert_eq!(encode(&f).as_bytes(), b"r7FF2\r");
    }

    #[test]
    fn decodes_lines() {
        let mut d = Decoder::default();
        let ev = events(
            &mut d,
            b"t1234deadBEEF\rt10121122ABCD\r\rO\rS6\rz\r\x07T1FFFFFFF0\rR000000013\r",
        );
        assert_eq!(
            ev,
            vec![
                Event::Frame(CanFrame::new(0x123, false, &[0xDE, 0xAD, 0xBE, 0xEF]).unwrap()),
                Event::Frame(CanFrame::new(0x101, false, &[0x11, 0x22]).unwrap()),
                Event::Ok,
                Event::Command(CmdLine::new(b"O")),
                Event::Command(CmdLine::new(b"S6")),
                Event::TxAck,
                Event::Bell,
                Event::Frame(CanFrame::new(0x1FFFFFFF, true, &[]).unwrap()),
                Event::Frame(CanFrame::remote(1, true, 3).unwrap()),
            ]
        );
    }

    #[test]
    fn commands_are_parsed_exactly() {
        assert_eq!(parse_command(b"C"), Some(Cmd::Close));
        assert_eq!(parse_command(b"L"), Some(Cmd::Listen));
        assert_eq!(parse_command(b"S6"), Some(Cmd::Setting));
        assert_eq!(parse_command(b"s1A2B"), Some(Cmd::Setting));
        for bad in [
            &b"Cxyz-garbage"[..],
            b"S9",
            b"Ox",
            b"V1",
            b"s12",
            b"Z2",
            b"Q",
        ] {
            assert_eq!(parse_command(bad), None, "{bad:?}");
        }
    }

    #[test]
    fn rejects_malformed() {
        let mut d = Decoder::default();
        for bad in [
            &b"t12\r"[..],
            b"t8001\r",       // id > 0x7FF
            b"t1239\r",       // dlc 9
            b"t1232AA\r",     // short data
            b"t1231AAB\r",    // odd data
            b"t1231GG\r",     // not hex
            b"T2000000000\r", // id > 29 bits
            b"t1231AA12G4\r", // bad timestamp
            b"\x01\r",
        ] {
            assert_eq!(events(&mut d, bad), vec![Event::Malformed], "{bad:?}");
        }
        let long = [b'x'; 200];
        assert!(events(&mut d, &long).is_empty());
        assert_eq!(events(&mut d, b"\r"), vec![Event::Malformed]);
        assert_eq!(d.pending(), 0);
        // Timestamped frame accepted, timestamp ignored.
        assert_eq!(
            events(&mut d, b"t1231AA1234\r"),
            vec![Event::Frame(CanFrame::new(0x123, false, &[0xAA]).unwrap())]
        );
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(cases(4000)))]

        /// Arbitrary bytes: never a panic, bounded memory.
        #[test]
        fn fuzz_arbitrary_bytes(bytes in proptest::collection::vec(any::<u8>(), 0..512)) {
            let mut d = Decoder::default();
            d.feed(&bytes, |_| {});
            prop_assert!(d.pending() <= MAX_LINE);
        }

        /// Garbage, then frames split at arbitrary points: the frames come out.
        #[test]
        fn fuzz_split_reassembly(
            frames in proptest::collection::vec(any_frame(), 1..8),
            garbage in proptest::collection::vec(any::<u8>(), 0..64),
            cuts in proptest::collection::vec(any::<usize>(), 0..6),
        ) {
            let mut stream = garbage.clone();
            stream.push(b'\r');
            for f in &frames {
                stream.extend_from_slice(encode(f).as_bytes());
            }
            let mut d = Decoder::default();
            let got = feed_in_pieces(&stream, &cuts, |b, out| d.feed(b, |e| out.push(e)));
            let decoded: Vec<CanFrame> = got.iter().filter_map(|e| match e {
                Event::Frame(f) => Some(*f),
                _ => None,
            }).collect();
            // Garbage may itself decode to frames; ours are the tail.
            prop_assert!(decoded.len() >= frames.len());
            prop_assert_eq!(&decoded[decoded.len() - frames.len()..], &frames[..]);
        }
    }
}
