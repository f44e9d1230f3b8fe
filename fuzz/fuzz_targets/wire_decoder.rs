//! Fuzz target: arbitrary bytes (raw, or a mutated encoding of a sample message) into
//! the viewer stream's `decode_frame` with the server's and the client's limits and
//! through `wire::client::FrameReader` in chunks. Checks no panic and that every
//! decoded message re-encodes and decodes to the same bytes
//! (`texel::fuzzing::check_wire`).
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    texel::fuzzing::check_wire(data);
});
