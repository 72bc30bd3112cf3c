//! What the unit tests share (compiled only under `cfg(test)`): the number
//! of cases per property, the CAN frame strategies, and a byte stream fed
//! to a parser in arbitrary pieces.

use crate::frame::CanFrame;
use proptest::prelude::*;

/// Cases per property: `default`, or `CAN_BRIDGE_PROPTEST_CASES` when set
/// (the longer runs of the crate's README).
pub(crate) fn cases(default: u32) -> u32 {
    std::env::var("CAN_BRIDGE_PROPTEST_CASES")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(default)
}

/// A standard (11-bit) or extended (29-bit) identifier.
fn id(extended: bool, raw: u32) -> u32 {
    if extended {
        raw & 0x1FFF_FFFF
    } else {
        raw & 0x7FF
    }
}

/// Any data frame: either identifier kind, 0 to 8 bytes.
pub(crate) fn data_frame() -> impl Strategy<Value = CanFrame> {
    (
        any::<bool>(),
        any::<u32>(),
        proptest::collection::vec(any::<u8>(), 0..=8),
    )
        .prop_map(|(ext, raw, data)| CanFrame::new(id(ext, raw), ext, &data).unwrap())
}

/// Any frame: a data frame or a remote frame (its length 0 to 8).
pub(crate) fn any_frame() -> impl Strategy<Value = CanFrame> {
    prop_oneof![
        data_frame(),
        (any::<bool>(), any::<u32>(), 0u8..=8).prop_map(|(ext, raw, len)| CanFrame::remote(
            id(ext, raw),
            ext,
            len
        )
        .unwrap()),
    ]
}

/// Feed `stream` to a parser in pieces cut at `cuts` (each taken modulo
/// `stream.len() + 1`, in ascending order; repeats give empty pieces) and
/// collect what `feed` pushes for each piece.
pub(crate) fn feed_in_pieces<E>(
    stream: &[u8],
    cuts: &[usize],
    mut feed: impl FnMut(&[u8], &mut Vec<E>),
) -> Vec<E> {
    let mut cuts: Vec<usize> = cuts.iter().map(|c| c % (stream.len() + 1)).collect();
    cuts.sort_unstable();
    let mut out = vec![];
    let mut prev = 0;
    for c in cuts.into_iter().chain(std::iter::once(stream.len())) {
        feed(&stream[prev..c], &mut out);
        prev = c;
    }
    out
}

#[test]
fn pieces_cover_the_stream_once_in_order() {
    let stream: Vec<u8> = (0..10).collect();
    let mut seen = vec![];
    let n = feed_in_pieces(&stream, &[7, 3, 3, 25], |b, out: &mut Vec<usize>| {
        seen.extend_from_slice(b);
        out.push(b.len());
    });
    assert_eq!(seen, stream);
    // 25 % 11 = 3: cuts 3, 3, 3, 7 and the end.
    assert_eq!(n, vec![3, 0, 0, 4, 3]);
}
