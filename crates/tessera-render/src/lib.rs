//! Tessera's deterministic CPU rendering core.
#![deny(missing_docs)]

pub mod sampling;
#[cfg(test)]
mod chi2;
