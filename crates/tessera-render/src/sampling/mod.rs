//! Sample generation (to be written).
