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

/// Status of one received frame, after AUTOSAR E2E Profile 1's
/// `E2E_P01Check` (OK, OKSOMELOST, INITIAL, SYNC, REPEATED, WRONGSEQUENCE,
/// WRONGCRC), plus the checks Profile 1 leaves to the receiver: length,
/// counter 15, and a repeated counter with a different payload (two sources).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Check {
    /// In sequence (counter + 1) and synchronised: the data may be used.
    Ok,
    /// In sequence after 1..max_delta-1 lost frames: the data may be used,
    /// but the loss is a strike against the message.
    OkSomeLost,
    /// First frame (after start or a timeout): anchors the counter, data not used.
    Initial,
    /// In sequence, but the counter was (re)anchored less than `sync_frames`
    /// frames ago (AUTOSAR SyncCounter): data not used yet.
    Sync,
    /// Same counter and payload as the last frame: a frozen or replayed sender.
    Repeated,
    /// Same counter, different payload: two senders on one identifier.
    TwoSources,
    /// Counter jumped by more than `max_delta`: data not used, the counter is
    /// re-anchored and must be confirmed by `sync_frames` in-sequence frames.
    WrongSequence,
    /// Frame not as long as the message.
    BadLength,
    /// CRC mismatch.
    BadCrc,
    /// Counter 15 (not a Profile 1 counter).
    InvalidCounter,
    /// E2E-valid, but a value lies outside its signal's DBC `[min|max]`
    /// (set by the bridge after decoding; the data is not used).
    Implausible,
}

impl Check {
    /// Whether the frame's content may be used.
    pub fn usable(self) -> bool {
        matches!(self, Check::Ok | Check::OkSomeLost)
    }

    /// Whether the frame counts as a strike against the message's validity
    /// (INITIAL and SYNC do not: they are the normal way into OK).
    pub fn is_strike(self) -> bool {
        !matches!(self, Check::Ok | Check::Initial | Check::Sync)
    }

    /// Short name, as reported in `latest_state()["status"]`.
    pub fn name(self) -> &'static str {
        match self {
            Check::Ok => "ok",
            Check::OkSomeLost => "lost frames",
            Check::Initial => "initial",
            Check::Sync => "sync",
            Check::Repeated => "repeated",
            Check::TwoSources => "two sources",
            Check::WrongSequence => "wrong sequence",
            Check::BadLength => "wrong length",
            Check::BadCrc => "wrong crc",
            Check::InvalidCounter => "counter 15",
            Check::Implausible => "implausible",
        }
    }
}

/// Receive-side E2E Profile 1 state of one message: the last valid counter,
/// the synchronisation still owed after an anchor, and the last payload (to
/// tell a repeat from a second sender).
#[derive(Clone, Debug)]
pub struct Receiver {
    data_id: u16,
    length: usize,
    max_delta: u8,
    sync_frames: u8,
    last: Option<u8>,
    sync_left: u8,
    last_payload: [u8; 8],
}

impl Receiver {
    /// A checker for a message of `length` bytes. `max_delta` (1..=14,
    /// AUTOSAR MaxDeltaCounterInit) is the largest counter step still in
    /// sequence; `sync_frames` (1..=14, AUTOSAR SyncCounterInit) in-sequence
    /// frames must follow an anchor before data is used.
    pub fn new(data_id: u16, length: usize, max_delta: u8, sync_frames: u8) -> Self {
        Receiver {
            data_id,
            length,
            max_delta: max_delta.clamp(1, MAX_COUNTER),
            sync_frames: sync_frames.clamp(1, MAX_COUNTER),
            last: None,
            sync_left: 0,
            last_payload: [0; 8],
        }
    }

    /// Forget the counter (after a timeout): the next valid frame is INITIAL.
    pub fn resync(&mut self) {
        self.last = None;
    }

    fn anchor(&mut self, c: u8, payload: &[u8]) {
        self.last = Some(c);
        self.sync_left = self.sync_frames;
        self.remember(payload);
    }

    fn remember(&mut self, payload: &[u8]) {
        self.last_payload = [0; 8];
        let n = payload.len().min(8);
        self.last_payload[..n].copy_from_slice(&payload[..n]);
    }

    /// Check one received payload and update the state.
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
            self.anchor(c, payload);
            return Check::Initial;
        };
        let delta = (c + MAX_COUNTER + 1 - last) % (MAX_COUNTER + 1);
        if delta == 0 {
            let n = payload.len().min(8);
            return if self.last_payload[..n] == payload[..n] {
                Check::Repeated
            } else {
                Check::TwoSources
            };
        }
        if delta > self.max_delta {
            self.anchor(c, payload);
            return Check::WrongSequence;
        }
        self.last = Some(c);
        self.remember(payload);
        if self.sync_left > 1 {
            self.sync_left -= 1;
            return Check::Sync;
        }
        self.sync_left = 0;
        if delta == 1 {
            Check::Ok
        } else {
            Check::OkSomeLost
        }
    }
}

/// Validity of a message judged over its last [`WINDOW`] frames (in the
/// spirit of panda's counter strikes): valid only while the last frame was
/// usable and at most `max_strikes` of the window were strikes. A frozen,
/// repeated, jumping or doubled sender is a strike on every frame, so it is
/// invalid from its first bad frame on and stays invalid until `WINDOW`
/// frames later at most `max_strikes` remain (`e2e::tests` and the property
/// tests pin both).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Judge {
    strikes: u32,
    seen: u32,
    last: Option<Check>,
    max_strikes: u32,
}

/// Frames the [`Judge`] looks back over.
pub const WINDOW: u32 = 16;

impl Judge {
    /// A judge allowing `max_strikes` (0..=WINDOW) strikes per window.
    pub fn new(max_strikes: u32) -> Self {
        Judge {
            strikes: 0,
            seen: 0,
            last: None,
            max_strikes: max_strikes.min(WINDOW),
        }
    }

    /// Record one frame's status.
    pub fn record(&mut self, c: Check) {
        self.strikes = (self.strikes << 1) | u32::from(c.is_strike());
        self.seen = (self.seen << 1) | 1;
        self.last = Some(c);
    }

    /// Strikes among the last [`WINDOW`] frames.
    pub fn strikes(&self) -> u32 {
        (self.strikes & ((1u32 << WINDOW) - 1)).count_ones()
    }

    /// The last frame's status.
    pub fn last(&self) -> Option<Check> {
        self.last
    }

    /// `Ok(())` if the message is valid, else why not.
    pub fn verdict(&self) -> std::result::Result<(), &'static str> {
        match self.last {
            None => Err("no data"),
            Some(c) if !c.usable() => Err(c.name()),
            Some(_) if self.strikes() > self.max_strikes => Err("too many strikes"),
            Some(_) => Ok(()),
        }
    }

    /// Forget the history (after a timeout).
    pub fn reset(&mut self) {
        *self = Judge::new(self.max_strikes);
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

    fn mk(id: u16, c: u8, v: u8) -> [u8; 8] {
        let mut p = [0u8, 0, v, 2, 3, 4, 5, 6];
        protect(&mut p, id, c);
        p
    }

    #[test]
    fn receiver_follows_profile1() {
        let id = 0x0C11;
        let mut r = Receiver::new(id, 8, 2, 2);
        assert_eq!(r.check(&mk(id, 5, 0)), Check::Initial);
        assert_eq!(r.check(&mk(id, 5, 0)), Check::Repeated);
        assert_eq!(r.check(&mk(id, 5, 9)), Check::TwoSources);
        assert_eq!(r.check(&mk(id, 6, 0)), Check::Sync);
        assert_eq!(r.check(&mk(id, 7, 0)), Check::Ok);
        assert_eq!(r.check(&mk(id, 9, 0)), Check::OkSomeLost);
        assert_eq!(r.check(&mk(id, 13, 0)), Check::WrongSequence);
        // re-anchored at 13: two in-sequence frames before data is used
        assert_eq!(r.check(&mk(id, 14, 0)), Check::Sync);
        assert_eq!(r.check(&mk(id, 0, 0)), Check::Ok);
        let mut bad = mk(id, 1, 0);
        bad[3] ^= 0x10;
        assert_eq!(r.check(&bad), Check::BadCrc);
        assert_eq!(r.check(&mk(id, 1, 0)), Check::Ok);
        let mut c15 = [0u8; 8];
        c15[1] = 0x0F;
        c15[0] = p01_crc(id, &c15);
        assert_eq!(r.check(&c15), Check::InvalidCounter);
        assert_eq!(r.check(&mk(id, 2, 0)[..7]), Check::BadLength);
        r.resync();
        assert_eq!(r.check(&mk(id, 9, 0)), Check::Initial);
    }

    #[test]
    fn an_intruders_frame_is_never_used_and_the_sensor_recovers() {
        // Counters 0..4, an intruder's 11 and 12, then the sensor's 5, 6, 7.
        let id = 0x0C11;
        let mut r = Receiver::new(id, 8, 2, 2);
        let mut j = Judge::new(2);
        for c in 0..5 {
            j.record(r.check(&mk(id, c, 1)));
        }
        assert!(j.verdict().is_ok());
        for c in [11, 12] {
            let s = r.check(&mk(id, c, 112));
            assert!(!s.usable(), "{s:?}");
            j.record(s);
            assert!(j.verdict().is_err());
        }
        let got: Vec<Check> = (5..8).map(|c| r.check(&mk(id, c, 1))).collect();
        for s in &got {
            j.record(*s);
        }
        assert_eq!(got, [Check::WrongSequence, Check::Sync, Check::Ok]);
        assert!(j.verdict().is_ok(), "{:?}", j.verdict());
    }

    #[test]
    fn judge_window() {
        let mut j = Judge::new(2);
        assert_eq!(j.verdict(), Err("no data"));
        j.record(Check::Ok);
        assert!(j.verdict().is_ok());
        j.record(Check::Repeated);
        assert_eq!(j.verdict(), Err("repeated"));
        j.record(Check::OkSomeLost);
        j.record(Check::OkSomeLost);
        assert_eq!(j.verdict(), Err("too many strikes"));
        for _ in 0..WINDOW - 3 {
            j.record(Check::Ok);
        }
        assert_eq!(j.strikes(), 3);
        j.record(Check::Ok);
        assert!(j.verdict().is_ok());
    }

    use proptest::prelude::*;

    fn cases() -> u32 {
        std::env::var("CAN_BRIDGE_PROPTEST_CASES")
            .ok()
            .and_then(|s| s.parse().ok())
            .unwrap_or(2000)
    }

    /// One scripted frame: counter step (0 = repeat), payload change, CRC fault.
    fn arb_step() -> impl Strategy<Value = (u8, bool, bool)> {
        (0u8..15, any::<bool>(), prop::bool::weighted(0.1))
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(cases()))]

        /// Whatever arrives: data is used only from a frame with a right CRC
        /// whose counter advanced by 1..=max_delta from the last used or
        /// anchored one, at least `sync` in-sequence frames after the anchor;
        /// a valid verdict needs a usable last frame and <= max_strikes strikes.
        #[test]
        fn receiver_uses_only_confirmed_in_sequence_frames(
            steps in proptest::collection::vec(arb_step(), 1..200),
            max_delta in 1u8..5, sync in 1u8..4, max_strikes in 0u32..4,
        ) {
            let id = 0x0C12;
            let mut r = Receiver::new(id, 8, max_delta, sync);
            let mut j = Judge::new(max_strikes);
            let mut c = 0u8;
            let mut v = 0u8;
            let mut run = 0u32; // in-sequence frames since the last anchor
            let mut prev: Option<u8> = None;
            for (step, change, corrupt) in steps {
                c = (c + step) % 15;
                if change { v = v.wrapping_add(1); }
                let mut p = mk(id, c, v);
                if corrupt { p[4] ^= 0x40; }
                let repeat = prev == Some(c) && !corrupt;
                let s = r.check(&p);
                j.record(s);
                if s.usable() {
                    prop_assert!(!corrupt);
                    let d = (c + 15 - prev.unwrap()) % 15;
                    prop_assert!((1..=max_delta).contains(&d));
                    prop_assert!(run + 1 >= u32::from(sync));
                }
                match s {
                    Check::Initial | Check::WrongSequence => { prev = Some(c); run = 0; }
                    Check::Ok | Check::OkSomeLost | Check::Sync => { prev = Some(c); run += 1; }
                    _ => {}
                }
                if j.verdict().is_ok() {
                    prop_assert!(s.usable());
                    prop_assert!(j.strikes() <= max_strikes);
                }
                // A repeated counter is never usable, and never valid.
                if repeat {
                    prop_assert!(matches!(s, Check::Repeated | Check::TwoSources));
                    prop_assert!(j.verdict().is_err());
                }
            }
        }
    }
}
