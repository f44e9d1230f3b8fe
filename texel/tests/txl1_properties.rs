//! Property tests of the TXL1 decoder: any byte stream decodes without panicking and
//! with bounded buffering, and every intact frame survives garbage between frames in
//! any read split, with the skipped bytes counted exactly.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

use proptest::prelude::*;
use texel::txl1::{MAX_FRAME_LEN, Txl1Decoder, Txl1Frame};

fn frame(seq: u32, w: u16, h: u16, intensity: bool) -> Txl1Frame {
    let n = usize::from(w) * usize::from(h);
    Txl1Frame {
        width: w,
        height: h,
        seq,
        timestamp_ns: u64::from(seq) * 33_333_333,
        range_unit_um: 1000,
        ranges: (0..n).map(|i| (i * 37 % 65535) as u16).collect(),
        intensities: intensity.then(|| (0..n).map(|i| (i * 11) as u16).collect()),
    }
}

proptest! {
    #[test]
    fn arbitrary_bytes_never_panic_and_stay_bounded(
        bytes in proptest::collection::vec(any::<u8>(), 0..4096),
        split in 1usize..300,
    ) {
        let mut d = Txl1Decoder::new();
        for chunk in bytes.chunks(split) {
            d.push(chunk);
            while d.next_frame().is_some() {}
            prop_assert!(d.buffered() <= MAX_FRAME_LEN + split);
        }
    }

    #[test]
    fn frames_survive_garbage_in_any_split(
        garbage in proptest::collection::vec(
            proptest::collection::vec(any::<u8>(), 0..40), 4),
        sizes in proptest::collection::vec((1u16..12, 1u16..9, any::<bool>()), 3),
        split in 1usize..200,
    ) {
        // Garbage that contains the magic could hide a frame start; that is the
        // resynchronisation test above, not this one.
        prop_assume!(garbage.iter().all(|g| !g.windows(4).any(|w| w == b"TXL1")));
        let frames: Vec<_> = sizes.iter().enumerate()
            .map(|(i, &(w, h, it))| frame(i as u32 + 1, w, h, it)).collect();
        let mut stream = Vec::new();
        for (g, f) in garbage.iter().zip(frames.iter().map(Some).chain([None])) {
            stream.extend(g);
            if let Some(f) = f {
                stream.extend(f.encode());
            }
        }
        let mut d = Txl1Decoder::new();
        let mut got = Vec::new();
        for chunk in stream.chunks(split) {
            d.push(chunk);
            while let Some(f) = d.next_frame() {
                got.push(f);
            }
        }
        prop_assert_eq!(&got, &frames);
        let c = d.counters();
        let skipped_plus_held = c.bytes_skipped + d.buffered() as u64;
        let garbage_len: usize = garbage.iter().map(Vec::len).sum();
        prop_assert_eq!(skipped_plus_held, garbage_len as u64);
        prop_assert_eq!(c.lost_frames, 0);
        prop_assert_eq!(c.crc_errors, 0);
    }
}
