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
    /// In sequence, but its counter steps claim more time than has passed
    /// since the last believed frame plus one cycle: a burst, or a sender
    /// faster than its cycle (set by the bridge; the data is not used).
    FasterThanCycle,
}

impl Check {
    /// Whether the frame's content may be used.
    pub fn usable(self) -> bool {
        matches!(self, Check::Ok | Check::OkSomeLost)
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
            Check::FasterThanCycle => "faster than its cycle",
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

/// AUTOSAR's profile-independent status of one frame
/// (`E2E_PCheckStatusType`), as the state machine counts it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum PStatus {
    /// Usable and in sequence (Profile 1 OK, OKSOMELOST, SYNC).
    Ok,
    /// The counter did not move: a frozen, replayed or second sender.
    Repeated,
    /// The counter jumped, or was (re)anchored (Profile 1 WRONGSEQUENCE, INITIAL).
    WrongSequence,
    /// The frame itself is broken (CRC, length, counter 15), its values
    /// implausible, or it came faster than its cycle.
    Error,
}

impl Check {
    /// The Profile 1 status mapped onto the state machine's
    /// (`E2E_P01MapStatusToSM`, AUTOSAR 4.2 behaviour); the checks Profile 1
    /// leaves to the receiver map to `Error` (length, counter 15,
    /// implausible, faster than its cycle) and `Repeated` (two sources).
    pub fn p_status(self) -> PStatus {
        match self {
            Check::Ok | Check::OkSomeLost | Check::Sync => PStatus::Ok,
            Check::Repeated | Check::TwoSources => PStatus::Repeated,
            Check::Initial | Check::WrongSequence => PStatus::WrongSequence,
            Check::BadLength
            | Check::BadCrc
            | Check::InvalidCounter
            | Check::Implausible
            | Check::FasterThanCycle => PStatus::Error,
        }
    }
}

/// Largest window of the state machine.
pub const WINDOW: u32 = 16;

/// The receiver state machine's thresholds (AUTOSAR `E2E_SMConfigType`):
/// counts of [`PStatus::Ok`] and [`PStatus::Error`] over the last `window`
/// frames decide each transition.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SmConfig {
    /// Frames the counts look back over (`WindowSize`, 1..=16).
    pub window: u8,
    /// INIT -> VALID once at least this many OK (`MinOkStateInit`) ...
    pub min_ok_init: u8,
    /// ... and at most this many errors (`MaxErrorStateInit`); more: INVALID.
    pub max_error_init: u8,
    /// VALID stays while at least this many OK (`MinOkStateValid`) ...
    pub min_ok_valid: u8,
    /// ... and at most this many errors (`MaxErrorStateValid`).
    pub max_error_valid: u8,
    /// INVALID -> VALID once at least this many OK (`MinOkStateInvalid`) ...
    pub min_ok_invalid: u8,
    /// ... and at most this many errors (`MaxErrorStateInvalid`).
    pub max_error_invalid: u8,
}

impl Default for SmConfig {
    /// The shipped `vehicle.toml`: a window of 8 frames (160 ms at 20 ms);
    /// valid from the third frame of a fresh sender; one error in 8 frames
    /// tolerated (a bad CRC costs one frame, issue 29 item 13), two frames
    /// without a counter step (a frozen sender) are not; once invalid, a
    /// whole window of sound frames before the message is valid again.
    fn default() -> Self {
        SmConfig {
            window: 8,
            min_ok_init: 2,
            max_error_init: 1,
            min_ok_valid: 7,
            max_error_valid: 1,
            min_ok_invalid: 8,
            max_error_invalid: 0,
        }
    }
}

impl SmConfig {
    /// Check the thresholds against the window; errors name the setting.
    pub fn validate(&self) -> std::result::Result<(), String> {
        let w = self.window;
        if !(1..=WINDOW as u8).contains(&w) {
            return Err(format!("rx_window = {w} must be in 1..={WINDOW}"));
        }
        for (name, v, lo) in [
            ("rx_min_ok_init", self.min_ok_init, 1),
            ("rx_max_error_init", self.max_error_init, 0),
            ("rx_min_ok_valid", self.min_ok_valid, 1),
            ("rx_max_error_valid", self.max_error_valid, 0),
            ("rx_min_ok_invalid", self.min_ok_invalid, 1),
            ("rx_max_error_invalid", self.max_error_invalid, 0),
        ] {
            if !(lo..=w).contains(&v) {
                return Err(format!("{name} = {v} must be in {lo}..=rx_window ({w})"));
            }
        }
        Ok(())
    }
}

/// The receiver state machine's state (AUTOSAR `E2E_SMStateType`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum SmState {
    /// Nothing received since start or the last timeout.
    NoData,
    /// A sender is being confirmed.
    Init,
    /// The stream is sound: its data may be believed.
    Valid,
    /// The stream is not sound: nothing is believed until a window of sound
    /// frames has passed.
    Invalid,
}

/// The AUTOSAR E2E receiver state machine (`E2E_SMCheck`) over one
/// message's frames, with two rules of this bridge on top:
///
/// * **A sender change is invalid at once.** The same counter with another
///   payload (`TwoSources`) can only be a second sender on the identifier:
///   the machine goes INVALID and clears its window (AUTOSAR's
///   `ClearToInvalid`), so it takes `min_ok_invalid` sound frames in a row
///   before the message is valid again.
/// * **A sender confirmed in INIT starts VALID with a clean window.** On the
///   INIT -> VALID transition the window is set to OK throughout (INIT's
///   INITIAL and its unfilled slots included), so a strict `min_ok_valid` (7
///   of 8) does not throw a message that has just become valid out again;
///   AUTOSAR keeps INIT's statuses and leaves unfilled slots "not
///   available", which works only with a lenient `MinOkStateValid`.
///
/// Every other transition is AUTOSAR's: INIT -> VALID at `min_ok_init` OK
/// and at most `max_error_init` errors (INVALID past that), VALID stays
/// while `min_ok_valid` OK and at most `max_error_valid` errors, INVALID ->
/// VALID at `min_ok_invalid` OK and at most `max_error_invalid` errors;
/// entering INVALID clears the window.
#[derive(Clone, Debug)]
pub struct StateMachine {
    cfg: SmConfig,
    state: SmState,
    /// The last `cfg.window` statuses, newest last (`None`: not available).
    ring: [Option<PStatus>; WINDOW as usize],
    top: usize,
    last: Option<Check>,
}

impl StateMachine {
    /// A machine in NODATA.
    pub fn new(cfg: SmConfig) -> Self {
        StateMachine {
            cfg,
            state: SmState::NoData,
            ring: [None; WINDOW as usize],
            top: 0,
            last: None,
        }
    }

    fn window(&self) -> usize {
        usize::from(self.cfg.window.clamp(1, WINDOW as u8))
    }

    fn clear(&mut self) {
        self.ring = [None; WINDOW as usize];
        self.top = 0;
    }

    /// Put `p` in the window's oldest slot (`top` is always below the window).
    fn add(&mut self, p: PStatus) {
        if let Some(slot) = self.ring.get_mut(self.top) {
            *slot = Some(p);
        }
        self.top = (self.top + 1) % self.window();
    }

    /// (OK, errors) over the window.
    pub fn counts(&self) -> (u8, u8) {
        let w = self.window();
        let seen = self.ring.iter().take(w).flatten();
        seen.fold((0, 0), |(ok, err), p| match p {
            PStatus::Ok => (ok + 1, err),
            PStatus::Error => (ok, err + 1),
            _ => (ok, err),
        })
    }

    fn go_invalid(&mut self) {
        self.state = SmState::Invalid;
        self.clear();
    }

    /// Feed one frame's check; returns the new state.
    pub fn check(&mut self, c: Check) -> SmState {
        self.last = Some(c);
        let p = c.p_status();
        if c == Check::TwoSources && self.state != SmState::NoData {
            self.go_invalid();
            return self.state;
        }
        self.add(p);
        let (ok, err) = self.counts();
        let cfg = self.cfg;
        match self.state {
            SmState::NoData => {
                if p != PStatus::Error {
                    self.state = SmState::Init;
                }
            }
            SmState::Init => {
                if err <= cfg.max_error_init && ok >= cfg.min_ok_init {
                    self.state = SmState::Valid;
                    let w = self.window();
                    for slot in self.ring.iter_mut().take(w) {
                        *slot = Some(PStatus::Ok);
                    }
                } else if err > cfg.max_error_init {
                    self.go_invalid();
                }
            }
            SmState::Valid => {
                if !(err <= cfg.max_error_valid && ok >= cfg.min_ok_valid) {
                    self.go_invalid();
                }
            }
            SmState::Invalid => {
                if err <= cfg.max_error_invalid && ok >= cfg.min_ok_invalid {
                    self.state = SmState::Valid;
                }
            }
        }
        self.state
    }

    /// The current state.
    pub fn state(&self) -> SmState {
        self.state
    }

    /// Back to NODATA with an empty window (after a timeout).
    pub fn reset(&mut self) {
        *self = StateMachine::new(self.cfg);
    }

    /// `Ok(())` if the stream is VALID, else why not, by the state and the
    /// last frame: that frame's problem if it had one, else "initial"/"sync"
    /// while a sender is being confirmed and "resync" while a window of sound
    /// frames is still owed.
    pub fn verdict(&self) -> std::result::Result<(), &'static str> {
        match (self.state, self.last) {
            (SmState::Valid, _) => Ok(()),
            (SmState::NoData, _) | (_, None) => Err("no data"),
            (_, Some(c)) if c.p_status() != PStatus::Ok => Err(c.name()),
            (SmState::Init, Some(Check::Sync)) => Err("sync"),
            (SmState::Init, _) => Err("initial"),
            (SmState::Invalid, _) => Err("resync"),
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
    fn an_intruders_frame_is_never_used_and_the_sensor_recovers_over_a_window() {
        // Counters 0..4, an intruder's 11 and 12, then the sensor's 5, 6, ...
        let id = 0x0C11;
        let mut r = Receiver::new(id, 8, 2, 2);
        let mut sm = StateMachine::new(SmConfig::default());
        for c in 0..5 {
            sm.check(r.check(&mk(id, c, 1)));
        }
        assert_eq!(sm.state(), SmState::Valid);
        for c in [11, 12] {
            let s = r.check(&mk(id, c, 112));
            assert!(!s.usable(), "{s:?}");
            sm.check(s);
        }
        let got: Vec<Check> = (5..8).map(|c| r.check(&mk(id, c, 1))).collect();
        assert_eq!(got, [Check::WrongSequence, Check::Sync, Check::Ok]);
        for s in &got {
            sm.check(*s);
        }
        // two jumps in one window: invalid, and a whole window of sound
        // frames is owed before the message is valid again
        assert_eq!(sm.verdict(), Err("resync"));
        for c in 8..13 {
            sm.check(r.check(&mk(id, c, 1)));
            assert_eq!(sm.state(), SmState::Invalid, "counter {c}");
        }
        sm.check(r.check(&mk(id, 13, 1)));
        assert_eq!(sm.verdict(), Ok(()));
    }

    /// Feed `n` checks.
    fn feed(sm: &mut StateMachine, c: Check, n: usize) {
        for _ in 0..n {
            sm.check(c);
        }
    }

    #[test]
    fn state_machine_init_valid_invalid() {
        let mut sm = StateMachine::new(SmConfig::default());
        assert_eq!(sm.verdict(), Err("no data"));
        // a bad frame alone does not start anything
        sm.check(Check::BadCrc);
        assert_eq!(sm.state(), SmState::NoData);
        sm.check(Check::Initial);
        assert_eq!((sm.state(), sm.verdict()), (SmState::Init, Err("initial")));
        sm.check(Check::Sync);
        assert_eq!(sm.verdict(), Err("sync"));
        sm.check(Check::Ok);
        assert_eq!(sm.state(), SmState::Valid);
        // a clean window from here: one error tolerated, two not
        sm.check(Check::BadCrc);
        assert_eq!(sm.state(), SmState::Valid);
        sm.check(Check::OkSomeLost);
        sm.check(Check::BadCrc);
        assert_eq!(sm.verdict(), Err("wrong crc"));
        // INVALID with a cleared window: 8 OK in a row, no error
        feed(&mut sm, Check::Ok, 7);
        assert_eq!(sm.verdict(), Err("resync"));
        sm.check(Check::Ok);
        assert_eq!(sm.verdict(), Ok(()));
        // too many errors while confirming a sender
        let mut sm = StateMachine::new(SmConfig::default());
        sm.check(Check::Initial);
        sm.check(Check::BadCrc);
        sm.check(Check::BadCrc);
        assert_eq!(sm.state(), SmState::Invalid);
    }

    #[test]
    fn one_bad_crc_in_eight_frames_keeps_the_message_valid() {
        // Issue 29 item 13: the bad frame is one error; the next frame, two
        // counter steps on, is OKSOMELOST, which the state machine counts OK.
        let id = 0x0C11;
        let mut r = Receiver::new(id, 8, 2, 2);
        let mut sm = StateMachine::new(SmConfig::default());
        let mut valid_after_warmup = 0;
        for k in 0..400u32 {
            let mut p = mk(id, (k % 15) as u8, 1);
            if k % 8 == 7 {
                p[5] ^= 0x01;
            }
            let st = sm.check(r.check(&p));
            if k >= 3 {
                valid_after_warmup += u32::from(st == SmState::Valid);
            }
        }
        assert_eq!(valid_after_warmup, 397);
    }

    #[test]
    fn a_frozen_sender_is_invalid_within_two_frames_and_two_sources_at_once() {
        let mut sm = StateMachine::new(SmConfig::default());
        feed(&mut sm, Check::Ok, 10);
        sm.check(Check::Repeated);
        assert_eq!(sm.state(), SmState::Valid);
        sm.check(Check::Repeated);
        assert_eq!(sm.verdict(), Err("repeated"));
        let mut sm = StateMachine::new(SmConfig::default());
        feed(&mut sm, Check::Ok, 10);
        sm.check(Check::TwoSources);
        assert_eq!(sm.verdict(), Err("two sources"));
        feed(&mut sm, Check::Ok, 7);
        assert_eq!(sm.state(), SmState::Invalid);
        sm.check(Check::Ok);
        assert_eq!(sm.state(), SmState::Valid);
    }

    #[test]
    fn a_second_stream_interleaved_keeps_the_message_invalid() {
        // Every other frame out of sequence: one jump in a window is
        // tolerated (a sender's glitch), the second is not, and 7 OK in 8
        // never come back while it lasts.
        let mut sm = StateMachine::new(SmConfig::default());
        feed(&mut sm, Check::Ok, 10);
        sm.check(Check::WrongSequence);
        sm.check(Check::Sync);
        assert_eq!(sm.state(), SmState::Valid);
        for _ in 0..50 {
            sm.check(Check::WrongSequence);
            assert_ne!(sm.state(), SmState::Valid);
            sm.check(Check::Sync);
            assert_ne!(sm.state(), SmState::Valid);
        }
    }

    #[test]
    fn protection_writes_the_counter_nibble_and_the_crc_and_nothing_else() {
        // byte 1's high nibble is payload: kept; the counter goes mod 15
        let mut p = [0u8, 0xA7, 0x11, 0x22];
        protect(&mut p, 0x0C11, 5);
        assert_eq!((p[1], &p[2..]), (0xA5, &[0x11, 0x22][..]));
        assert!(crc_ok(&p, 0x0C11));
        assert_eq!(counter_of(&p), Some(5));
        // the shortest protected payload: CRC and counter only
        let mut p = [0u8, 0xF0];
        protect(&mut p, 0x0C11, 16);
        assert_eq!(p[1], 0xF1);
        assert_eq!(p[0], p01_crc(0x0C11, &p));
        assert!(crc_ok(&p, 0x0C11));
        // nothing to protect in a shorter one
        let mut p = [0x5Au8];
        protect(&mut p, 0x0C11, 3);
        assert_eq!(p, [0x5A]);
        assert!(!crc_ok(&p, 0x0C11) && !crc_ok(&[], 0x0C11));
        assert_eq!(counter_of(&p), None);
    }

    #[test]
    fn a_two_byte_message_is_checked_like_any_other() {
        let mut r = Receiver::new(0x0C13, 2, 2, 2);
        let f = |c: u8| {
            let mut p = [0u8, 0x30];
            protect(&mut p, 0x0C13, c);
            p
        };
        assert_eq!(r.check(&f(0)), Check::Initial);
        assert_eq!(r.check(&f(1)), Check::Sync);
        assert_eq!(r.check(&f(2)), Check::Ok);
        assert_eq!(r.check(&f(2)[..1]), Check::BadLength);
        assert_eq!(r.check(&[0u8, 0x34, 0]), Check::BadLength);
    }

    #[test]
    fn receiver_settings_are_held_to_their_ranges() {
        let id = 0x0C11;
        // a largest step of 0 acts as 1, and a sync count of 0 as 1
        let mut r = Receiver::new(id, 8, 0, 0);
        assert_eq!(r.check(&mk(id, 0, 0)), Check::Initial);
        assert_eq!(r.check(&mk(id, 1, 0)), Check::Ok);
        assert_eq!(r.check(&mk(id, 3, 0)), Check::WrongSequence);
        // a largest step of 20 acts as 14: any other counter is in sequence
        let mut r = Receiver::new(id, 8, 20, 1);
        assert_eq!(r.check(&mk(id, 0, 0)), Check::Initial);
        assert_eq!(r.check(&mk(id, 14, 0)), Check::OkSomeLost);
        // a sync count of 20 acts as 14: 13 SYNC frames, then data
        let mut r = Receiver::new(id, 8, 2, 20);
        r.check(&mk(id, 0, 0));
        for c in 1..14 {
            assert_eq!(r.check(&mk(id, c, 0)), Check::Sync, "{c}");
        }
        assert_eq!(r.check(&mk(id, 14, 0)), Check::Ok);
    }

    #[test]
    fn the_first_frame_that_is_not_an_error_starts_a_sender_whatever_its_status() {
        // AUTOSAR: NODATA -> INIT on any frame but an error, a second source
        // included (it cannot contradict anything yet)
        for c in [
            Check::TwoSources,
            Check::Repeated,
            Check::Initial,
            Check::Ok,
        ] {
            let mut sm = StateMachine::new(SmConfig::default());
            assert_eq!(sm.check(c), SmState::Init, "{c:?}");
        }
        for c in [Check::BadCrc, Check::FasterThanCycle, Check::Implausible] {
            let mut sm = StateMachine::new(SmConfig::default());
            assert_eq!(sm.check(c), SmState::NoData, "{c:?}");
        }
    }

    #[test]
    fn a_sender_being_confirmed_may_have_one_error_not_two() {
        let mut sm = StateMachine::new(SmConfig::default());
        for c in [Check::Initial, Check::BadCrc, Check::Sync] {
            assert_eq!(sm.check(c), SmState::Init, "{c:?}");
        }
        assert_eq!(sm.check(Check::Ok), SmState::Valid);
        // the counts over the window: the error is gone, the window is OK
        assert_eq!(sm.counts(), (8, 0));
    }

    #[test]
    fn the_window_is_as_long_as_configured() {
        // a window of 4 frames: an error leaves it after four more frames
        let cfg = SmConfig {
            window: 4,
            min_ok_init: 2,
            max_error_init: 1,
            min_ok_valid: 3,
            max_error_valid: 1,
            min_ok_invalid: 4,
            max_error_invalid: 0,
        };
        cfg.validate().unwrap();
        let mut sm = StateMachine::new(cfg);
        feed(&mut sm, Check::Ok, 6);
        assert_eq!(sm.counts(), (4, 0));
        sm.check(Check::BadCrc);
        assert_eq!(sm.counts(), (3, 1));
        assert_eq!(sm.state(), SmState::Valid);
        feed(&mut sm, Check::Ok, 3);
        assert_eq!(sm.counts(), (3, 1));
        sm.check(Check::Ok);
        assert_eq!(sm.counts(), (4, 0));
        // a repeat is neither OK nor an error
        sm.check(Check::Repeated);
        assert_eq!(sm.counts(), (3, 0));
        // windows beyond 16 act as 16, below 1 as 1
        for (w, n) in [(40u8, 16u8), (0, 1)] {
            let mut sm = StateMachine::new(SmConfig { window: w, ..cfg });
            feed(&mut sm, Check::Ok, 30);
            assert_eq!(sm.counts(), (n, 0), "window {w}");
        }
    }

    #[test]
    fn every_status_has_its_name_and_its_weight() {
        use Check::*;
        let all = [
            (Ok, "ok", PStatus::Ok),
            (OkSomeLost, "lost frames", PStatus::Ok),
            (Sync, "sync", PStatus::Ok),
            (Initial, "initial", PStatus::WrongSequence),
            (WrongSequence, "wrong sequence", PStatus::WrongSequence),
            (Repeated, "repeated", PStatus::Repeated),
            (TwoSources, "two sources", PStatus::Repeated),
            (BadLength, "wrong length", PStatus::Error),
            (BadCrc, "wrong crc", PStatus::Error),
            (InvalidCounter, "counter 15", PStatus::Error),
            (Implausible, "implausible", PStatus::Error),
            (FasterThanCycle, "faster than its cycle", PStatus::Error),
        ];
        for (c, name, p) in all {
            assert_eq!((c.name(), c.p_status()), (name, p), "{c:?}");
            assert_eq!(c.usable(), matches!(c, Ok | OkSomeLost), "{c:?}");
        }
    }

    #[test]
    fn sm_config_limits_are_inclusive() {
        let d = SmConfig::default();
        for (c, ok) in [
            (SmConfig { window: 16, ..d }, true),
            (SmConfig { window: 0, ..d }, false),
            (
                SmConfig {
                    min_ok_valid: 8,
                    ..d
                },
                true,
            ),
            (
                SmConfig {
                    min_ok_init: 0,
                    ..d
                },
                false,
            ),
            (
                SmConfig {
                    min_ok_invalid: 0,
                    ..d
                },
                false,
            ),
            (
                SmConfig {
                    min_ok_valid: 0,
                    ..d
                },
                false,
            ),
            (
                SmConfig {
                    max_error_valid: 0,
                    ..d
                },
                true,
            ),
            (
                SmConfig {
                    max_error_init: 8,
                    ..d
                },
                true,
            ),
            (
                SmConfig {
                    max_error_invalid: 9,
                    ..d
                },
                false,
            ),
        ] {
            assert_eq!(c.validate().is_ok(), ok, "{c:?}");
        }
    }

    #[test]
    fn sm_config_is_validated_by_name() {
        assert!(SmConfig::default().validate().is_ok());
        let c = SmConfig {
            min_ok_valid: 9,
            ..SmConfig::default()
        };
        assert!(c.validate().unwrap_err().contains("rx_min_ok_valid = 9"));
        let c = SmConfig {
            window: 17,
            ..SmConfig::default()
        };
        assert!(c.validate().unwrap_err().contains("rx_window"));
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
        /// the state machine is VALID only with its thresholds met over the
        /// window, never right after a second source, and never after
        /// `window - min_ok_valid + 1` repeats in a row.
        #[test]
        fn receiver_uses_only_confirmed_in_sequence_frames(
            steps in proptest::collection::vec(arb_step(), 1..200),
            max_delta in 1u8..5, sync in 1u8..4, max_err in 0u8..3, slack in 0u8..3,
        ) {
            let id = 0x0C12;
            let mut r = Receiver::new(id, 8, max_delta, sync);
            let cfg = SmConfig { min_ok_valid: 8 - slack, max_error_valid: max_err, ..SmConfig::default() };
            let mut sm = StateMachine::new(cfg);
            let mut repeats = 0u8;
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
                let state = sm.check(s);
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
                if state == SmState::Valid {
                    let (ok, err) = sm.counts();
                    prop_assert!(ok >= cfg.min_ok_valid && err <= cfg.max_error_valid);
                    prop_assert!(s != Check::TwoSources);
                }
                // A repeated counter is never usable; repeats in a row soon invalid.
                if repeat {
                    prop_assert!(matches!(s, Check::Repeated | Check::TwoSources));
                }
                repeats = if s == Check::Repeated { repeats + 1 } else { 0 };
                if repeats > slack {
                    prop_assert!(state != SmState::Valid);
                }
            }
        }
    }
}
