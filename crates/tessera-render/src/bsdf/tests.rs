//! Chi-squared tests of the BSDFs (to be written).
