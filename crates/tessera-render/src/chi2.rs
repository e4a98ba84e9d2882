//! Chi-squared test harness (to be written).
