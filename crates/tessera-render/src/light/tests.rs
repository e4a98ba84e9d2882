//! Chi-squared tests of light sampling (to be written).
