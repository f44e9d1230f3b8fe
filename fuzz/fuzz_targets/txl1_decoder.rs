//! Fuzz target: arbitrary bytes (raw, or a script of valid, corrupt, claiming, nested
//! and flooding frames) into the TXL1 streaming decoder in arbitrary chunkings and
//! work budgets. Checks no panic, a bounded buffer, work linear in the bytes, and the
//! same result as the plain whole-stream rules (`texel::fuzzing::check_txl1`).
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    texel::fuzzing::check_txl1(data);
});
