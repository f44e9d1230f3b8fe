//! Fuzz target: arbitrary bytes read as a capture, and a small valid capture damaged
//! as the bytes say (flips, a cut, chunk-like bytes, the input spliced in). Checks
//! that every read ends in an answer: no panic, at most one fatal error and it last,
//! every error naming the file (`texel::fuzzing::check_capture`).
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    texel::fuzzing::check_capture(data);
});
