//! socketcand raw-mode protocol: `< ... >` messages, possibly back to back.
//! Client to server: `< send ID LEN B0 .. >`; server to client:
//! `< frame ID SEC.USEC DATA >` with DATA contiguous hex (space-separated bytes
//! are also accepted). The decoder never panics and bounds its memory.

use crate::frame::CanFrame;

/// Longest message body kept; longer ones are dropped as malformed.
pub const MAX_MSG: usize = 160;

/// Encode `< send ID LEN B0 B1 .. >` (ID: 3 hex digits standard, 8 extended).
pub fn encode_send(frame: &CanFrame) -> String {
    use std::fmt::Write;
    let mut s = String::with_capacity(48);
    let _ = if frame.is_extended() {
        write!(s, "< send {:08X} {}", frame.id(), frame.len())
    } else {
        write!(s, "< send {:03X} {}", frame.id(), frame.len())
    };
    for b in frame.data() {
        let _ = write!(s, " {b:02X}");
    }
    s.push_str(" >");
    s
}

/// Encode a server-side `< frame ID SEC.USEC DATA >` (used by tests and peers).
pub fn encode_frame(frame: &CanFrame, sec: u64, usec: u32) -> String {
    use std::fmt::Write;
    let mut s = String::with_capacity(48);
    let _ = if frame.is_extended() {
        write!(s, "< frame {:08X} {sec}.{usec:06} ", frame.id())
    } else {
        write!(s, "< frame {:03X} {sec}.{usec:06} ", frame.id())
    };
    for b in frame.data() {
        let _ = write!(s, "{b:02X}");
    }
    s.push_str(" >");
    s
}

/// One decoded message.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Event {
    /// `< hi >`.
    Hi,
    /// `< ok >`.
    Ok,
    /// `< error ... >` with its text.
    Error(String),
    /// `< frame ... >`.
    Frame(CanFrame),
    /// Another well-formed message (e.g. `< echo >`), by its first word.
    Other(String),
    /// An unparsable or overlong message.
    Malformed,
}

/// Streaming decoder.
#[derive(Clone, Debug, Default)]
pub struct Decoder {
    buf: Vec<u8>,
    inside: bool,
    overflow: bool,
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
    if digits.is_empty() || digits.len() > 8 {
        return None;
    }
    digits
        .iter()
        .try_fold(0u32, |acc, &d| Some((acc << 4) | hex_val(d)?))
}

fn is_time(tok: &[u8]) -> bool {
    let mut parts = tok.split(|&b| b == b'.');
    let ok =
        |p: Option<&[u8]>| p.is_some_and(|p| !p.is_empty() && p.iter().all(u8::is_ascii_digit));
    ok(parts.next()) && ok(parts.next()) && parts.next().is_none()
}

fn parse_frame(toks: &[&[u8]]) -> Option<CanFrame> {
    let (id_tok, rest) = toks.split_first()?;
    let id = hex_num(id_tok)?;
    let extended = id_tok.len() == 8;
    let (time, data_toks) = rest.split_first()?;
    if !is_time(time) {
        return None;
    }
    let mut data = [0u8; 8];
    let mut n = 0usize;
    match data_toks {
        [] => {}
        [one] if one.len() % 2 == 0 => {
            for pair in one.chunks(2) {
                *data.get_mut(n)? = hex_num(pair)? as u8;
                n += 1;
            }
        }
        many => {
            for t in many {
                if t.len() > 2 {
                    return None;
                }
                *data.get_mut(n)? = hex_num(t)? as u8;
                n += 1;
            }
        }
    }
    CanFrame::new(id, extended, &data[..n]).ok()
}

/// Parse the body of one `< ... >` message.
pub fn parse_message(body: &[u8]) -> Event {
    let toks: Vec<&[u8]> = body
        .split(|b| b.is_ascii_whitespace())
        .filter(|t| !t.is_empty())
        .collect();
    match toks.split_first() {
        Some((&b"hi", [])) => Event::Hi,
        Some((&b"ok", [])) => Event::Ok,
        Some((&b"error", rest)) => Event::Error(
            rest.iter()
                .map(|t| String::from_utf8_lossy(t).into_owned())
                .collect::<Vec<_>>()
                .join(" "),
        ),
        Some((&b"frame", rest)) => parse_frame(rest).map_or(Event::Malformed, Event::Frame),
        Some((first, _)) if first.iter().all(u8::is_ascii_alphanumeric) => {
            Event::Other(String::from_utf8_lossy(first).into_owned())
        }
        _ => Event::Malformed,
    }
}

impl Decoder {
    /// Feed bytes in any split; `on_event` is called once per `>`-closed message.
    /// Bytes outside `< >` are ignored; a `<` inside a message restarts it.
    pub fn feed(&mut self, bytes: &[u8], mut on_event: impl FnMut(Event)) {
        for &b in bytes {
            match (b, self.inside) {
                (b'<', true) => {
                    on_event(Event::Malformed);
                    self.buf.clear();
                    self.overflow = false;
                }
                (b'<', false) => {
                    self.inside = true;
                    self.buf.clear();
                    self.overflow = false;
                }
                (b'>', true) => {
                    self.inside = false;
                    if self.overflow {
                        on_event(Event::Malformed);
                    } else {
                        on_event(parse_message(&self.buf));
                    }
                    self.buf.clear();
                    self.overflow = false;
                }
                (_, true) => {
                    if self.buf.len() < MAX_MSG {
                        self.buf.push(b);
                    } else {
                        self.overflow = true;
                    }
                }
                (_, false) => {}
            }
        }
    }

    /// Bytes of an incomplete message held.
    pub fn pending(&self) -> usize {
        self.buf.len()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_support::{cases, data_frame, feed_in_pieces};
    use proptest::prelude::*;

    fn events(d: &mut Decoder, bytes: &[u8]) -> Vec<Event> {
        let mut v = vec![];
        d.feed(bytes, |e| v.push(e));
        v
    }

    #[test]
    fn encodes() {
        let f = CanFrame::new(0x101, false, &[0x0A, 0xFF]).unwrap();
        assert_eq!(encode_send(&f), "< send 101 2 0A FF >");
        let f = CanFrame::new(0x101, true, &[]).unwrap();
        assert_eq!(encode_send(&f), "< send 00000101 0 >");
        assert_eq!(encode_frame(&f, 12, 34), "< frame 00000101 12.000034  >");
    }

    #[test]
    fn decodes_back_to_back_and_both_data_forms() {
        let mut d = Decoder::default();
        let ev = events(
            &mut d,
            b"< hi >< ok >junk< frame 201 1700000000.123456 0102A0 >< frame 1FFFFFFF 1.2  >\
              < frame 12 0.0 1 a2 ff >< error bus not found >< echo >",
        );
        assert_eq!(
            ev,
            vec![
                Event::Hi,
                Event::Ok,
                Event::Frame(CanFrame::new(0x201, false, &[1, 2, 0xA0]).unwrap()),
                Event::Frame(CanFrame::new(0x1FFFFFFF, true, &[]).unwrap()),
                Event::Frame(CanFrame::new(0x12, false, &[1, 0xA2, 0xFF]).unwrap()),
                Event::Error("bus not found".into()),
                Event::Other("echo".into()),
            ]
        );
    }

    #[test]
    fn rejects_malformed() {
        let mut d = Decoder::default();
        for bad in [
            &b"< frame 800 1.0 00 >"[..], // 11-bit overflow
            b"< frame 201 x 00 >",
            b"< frame 201 1.0 0G >",
            b"< frame 201 1.0 001 >",
            b"< frame 201 1.0 000000000000000000 >",
            b"< frame >",
            b"< >",
            b"< frame 201 1.0 <",
        ] {
            let ev = events(&mut d, bad);
            assert_eq!(ev.first(), Some(&Event::Malformed), "{bad:?}");
        }
        let mut d = Decoder::default();
        let mut long = vec![b'<'];
        long.extend(std::iter::repeat_n(b'a', 1000));
        long.push(b'>');
        assert_eq!(events(&mut d, &long), vec![Event::Malformed]);
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(cases(4000)))]

        #[test]
        fn fuzz_arbitrary_bytes(bytes in proptest::collection::vec(any::<u8>(), 0..512)) {
            let mut d = Decoder::default();
            d.feed(&bytes, |_| {});
            prop_assert!(d.pending() <= MAX_MSG);
        }

        #[test]
        fn fuzz_arbitrary_strings(s in "[<>a-zA-Z0-9 .]{0,200}") {
            let mut d = Decoder::default();
            d.feed(s.as_bytes(), |_| {});
            prop_assert!(d.pending() <= MAX_MSG);
        }

        #[test]
        fn fuzz_split_reassembly(
            frames in proptest::collection::vec(data_frame(), 1..8),
            garbage in proptest::collection::vec(any::<u8>(), 0..64),
            cuts in proptest::collection::vec(any::<usize>(), 0..6),
            sec in any::<u32>(), usec in 0u32..1_000_000,
        ) {
            // Garbage closed by '>' so it cannot swallow the first frame.
            let mut stream = garbage.clone();
            stream.push(b'>');
            for f in &frames {
                stream.extend_from_slice(encode_frame(f, u64::from(sec), usec).as_bytes());
            }
            let mut d = Decoder::default();
            let got = feed_in_pieces(&stream, &cuts, |b, out| d.feed(b, |e| out.push(e)));
            let decoded: Vec<CanFrame> = got.iter().filter_map(|e| match e {
                Event::Frame(f) => Some(*f),
                _ => None,
            }).collect();
            prop_assert!(decoded.len() >= frames.len());
            prop_assert_eq!(&decoded[decoded.len() - frames.len()..], &frames[..]);
        }
    }
}
