//! The Texel daemon's library: capture inspection now; sources, sync, registration,
//! the model, recording and serving as they arrive.

pub mod export;
pub mod info;
pub mod register;
pub mod register_cli;
pub mod tradeoffs;
