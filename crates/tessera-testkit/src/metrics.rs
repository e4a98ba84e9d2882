//! Reading a sample from a Prometheus text exposition (`/metrics`).

/// The value of the unlabelled sample `name` in the exposition `text` (`None` if it has
/// no such sample). Comment lines (`# HELP`, `# TYPE`) are skipped, and a labelled sample
/// `name{...}` or a longer name `name_suffix` does not match.
pub fn metric(text: &str, name: &str) -> Option<f64> {
    text.lines()
        .filter(|l| !l.starts_with('#'))
        .find_map(|l| l.strip_prefix(name)?.strip_prefix(' ')?.trim().parse().ok())
}

/// [`metric`], failing the test (with the whole exposition) when the sample is missing.
pub fn require_metric(text: &str, name: &str) -> f64 {
    metric(text, name).unwrap_or_else(|| panic!("no {name} in /metrics:\n{text}"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn finds_unlabelled_samples_only() {
        let text = "# HELP a_total A.\n# TYPE a_total counter\na_total 3\n\
                    a_total_x 4\nb{x=\"1\"} 5\nb 6.5\n";
        assert_eq!(metric(text, "a_total"), Some(3.0));
        assert_eq!(metric(text, "b"), Some(6.5));
        assert_eq!(metric(text, "c"), None);
        assert_eq!(require_metric(text, "a_total_x"), 4.0);
    }
}
