//! AUTOSAR E2E Profile 1 (Data ID mode BOTH): CRC-8 with polynomial 0x1D,
//! start value 0x00 and final XOR 0x00 over the Data ID (low byte, then high
//! byte) and the payload without the CRC byte. CRC in byte 0, alive counter in
//! the low nibble of byte 1, counting 0..=14.

/// Generator polynomial of the Profile 1 CRC-8 (SAE J1850 polynomial).
pub const POLY: u8 = 0x1D;
/// Largest valid alive counter; 15 is invalid.
pub const MAX_COUNTER: u8 = 14;

const fn build_table() -> [u8; 256] {
    let mut table = [0u8; 256];
    let mut i = 0;
    while i < 256 {
        let mut crc = i as u8;
        let mut bit = 0;
        while bit < 8 {
            crc = if crc & 0x80 != 0 {
                (crc << 1) ^ POLY
            } else {
                crc << 1
            };
            bit += 1;
        }
        table[i] = crc;
        i += 1;
    }
    table
}

static TABLE: [u8; 256] = build_table();

/// Feed `bytes` into a running CRC-8 (poly 0x1D, no reflection).
pub fn crc8_update(mut crc: u8, bytes: &[u8]) -> u8 {
    for &b in bytes {
        crc = TABLE[(crc ^ b) as usize];
    }
    crc
}

/// The Profile 1 CRC of `payload` (whose byte 0 is the CRC slot, ignored).
pub fn p01_crc(data_id: u16, payload: &[u8]) -> u8 {
    let [lo, hi] = data_id.to_le_bytes();
    let crc = crc8_update(0x00, &[lo, hi]);
    crc8_update(crc, payload.get(1..).unwrap_or(&[]))
}

/// Write `counter` (mod 15) into the low nibble of byte 1 and the CRC into
/// byte 0. Payloads shorter than 2 bytes are left untouched.
pub fn protect(payload: &mut [u8], data_id: u16, counter: u8) {
    if payload.len() < 2 {
        return;
    }
    payload[1] = (payload[1] & 0xF0) | (counter % (MAX_COUNTER + 1));
    payload[0] = p01_crc(data_id, payload);
}

/// True when byte 0 holds the right CRC.
pub fn crc_ok(payload: &[u8], data_id: u16) -> bool {
    payload.len() >= 2 && payload[0] == p01_crc(data_id, payload)
}

/// The alive counter of a protected payload (`None` if too short).
pub fn counter_of(payload: &[u8]) -> Option<u8> {
    payload.get(1).map(|b| b & 0x0F)
}

/// Next counter value after `c` (0..=14, wrapping).
pub fn next_counter(c: u8) -> u8 {
    if c >= MAX_COUNTER {
        0
    } else {
        c + 1
    }
}

/// Verdict of the receive-side check of one frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Check {
    /// CRC right, counter advanced by one (or first frame after a (re)sync).
    Ok,
    /// CRC right, counter advanced by 2..=max_delta: some frames were lost; accepted.
    OkSomeLost,
    /// Frame shorter than the message length.
    BadLength,
    /// CRC mismatch.
    BadCrc,
    /// Counter repeated (delta 0); the frame is rejected.
    Repeated,
    /// Counter jumped by more than max_delta; rejected, and the checker resynchronises.
    WrongSequence,
    /// Counter 15.
    InvalidCounter,
}

impl Check {
    /// Whether the frame's content may be used.
    pub fn accepted(self) -> bool {
        matches!(self, Check::Ok | Check::OkSomeLost)
    }
    /// Whether the verdict counts as a counter error.
    pub fn is_counter_error(self) -> bool {
        matches!(
            self,
            Check::Repeated | Check::WrongSequence | Check::InvalidCounter
        )
    }
}

/// Receive-side state of one message: CRC and alive-counter continuity.
#[derive(Clone, Debug)]
pub struct Receiver {
    data_id: u16,
    length: usize,
    max_delta: u8,
    last: Option<u8>,
}

impl Receiver {
    /// A checker for a message of `length` bytes. `max_delta` (>= 1) is the
    /// largest counter step still accepted.
    pub fn new(data_id: u16, length: usize, max_delta: u8) -> Self {
        Receiver {
            data_id,
            length,
            max_delta: max_delta.clamp(1, MAX_COUNTER),
            last: None,
        }
    }

    /// Forget the last counter: the next frame with a valid CRC is accepted as is.
    pub fn resync(&mut self) {
        self.last = None;
    }

    /// Check one received payload and update the counter state.
    pub fn check(&mut self, payload: &[u8]) -> Check {
        if payload.len() != self.length || payload.len() < 2 {
            return Check::BadLength;
        }
        if !crc_ok(payload, self.data_id) {
            return Check::BadCrc;
        }
        let c = payload[1] & 0x0F;
        if c > MAX_COUNTER {
            return Check::InvalidCounter;
        }
        let Some(last) = self.last else {
            self.last = Some(c);
            return Check::Ok;
        };
        let delta = (c + MAX_COUNTER + 1 - last) % (MAX_COUNTER + 1);
        if delta == 0 {
            Check::Repeated
        } else if delta == 1 {
            self.last = Some(c);
            Check::Ok
        } else if delta <= self.max_delta {
            self.last = Some(c);
            Check::OkSomeLost
        } else {
            self.last = Some(c);
            Check::WrongSequence
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Vectors from the `autosar-e2e` package's Profile 1 tests (Data ID 0x123, mode BOTH).
    #[test]
    fn published_vectors() {
        let mut p = [0u8; 8];
        protect(&mut p, 0x123, 0);
        assert_eq!(p, [0xCC, 0, 0, 0, 0, 0, 0, 0]);
        let mut p = [0u8; 8];
        protect(&mut p, 0x123, 1);
        assert_eq!(p, [0x91, 0x01, 0, 0, 0, 0, 0, 0]);
        assert!(crc_ok(&p, 0x123));
        assert!(!crc_ok(&p, 0x124));
    }

    /// Bitwise reference implementation, to check the table.
    fn crc_bitwise(bytes: &[u8]) -> u8 {
        let mut crc = 0u8;
        for &b in bytes {
            crc ^= b;
            for _ in 0..8 {
                crc = if crc & 0x80 != 0 {
                    (crc << 1) ^ POLY
                } else {
                    crc << 1
                };
            }
        }
        crc
    }

    #[test]
    fn table_matches_bitwise() {
        let data: Vec<u8> = (0..=255u8).collect();
        for n in 0..data.len() {
            assert_eq!(crc8_update(0, &data[..n]), crc_bitwise(&data[..n]));
        }
        // The published SAE J1850 check value 0x4B uses init/xorout 0xFF.
        assert_eq!(crc8_update(0xFF, b"123456789") ^ 0xFF, 0x4B);
    }

    #[test]
    fn counter_wraps_at_14() {
        assert_eq!(next_counter(13), 14);
        assert_eq!(next_counter(14), 0);
        let mut p = [0u8; 4];
        protect(&mut p, 7, 15);
        assert_eq!(counter_of(&p), Some(0));
    }

    #[test]
    fn receiver_sequence() {
        let id = 0x0C11;
        let mk = |c: u8| {
            let mut p = [0u8, 0, 1, 2, 3, 4, 5, 6];
            protect(&mut p, id, c);
            p
        };
        let mut r = Receiver::new(id, 8, 2);
        assert_eq!(r.check(&mk(5)), Check::Ok);
        assert_eq!(r.check(&mk(5)), Check::Repeated);
        assert_eq!(r.check(&mk(6)), Check::Ok);
        assert_eq!(r.check(&mk(8)), Check::OkSomeLost);
        assert_eq!(r.check(&mk(12)), Check::WrongSequence);
        assert_eq!(r.check(&mk(13)), Check::Ok);
        assert_eq!(r.check(&mk(14)), Check::Ok);
        assert_eq!(r.check(&mk(0)), Check::Ok);
        let mut bad = mk(1);
        bad[3] ^= 0x10;
        assert_eq!(r.check(&bad), Check::BadCrc);
        assert_eq!(r.check(&mk(1)), Check::Ok);
        let mut c15 = [0u8; 8];
        c15[1] = 0x0F;
        c15[0] = p01_crc(id, &c15);
        assert_eq!(r.check(&c15), Check::InvalidCounter);
        assert_eq!(r.check(&mk(2)[..7]), Check::BadLength);
        r.resync();
        assert_eq!(r.check(&mk(9)), Check::Ok);
    }
}
